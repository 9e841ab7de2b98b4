"""Pivot with gear backlash (000 Fig. 2(a)): a driven shaft and a pendulum link on one pivot, coupled
through a gear with play; two unilateral contacts (the two flanks) that cannot be active together.

``q = (theta_m, theta_l)``: shaft angle (inertia ``J_m``, driven by ``tau``) and link angle from the
downward vertical (uniform bar of mass ``m_l`` and length ``l_l`` about its end, vertical plane).
Through the gear of ratio ``N`` the link follows ``theta_m / N`` up to the play ``2 alpha``:

    f1 = alpha + theta_l - theta_m / N >= 0,    f2 = alpha - theta_l + theta_m / N >= 0

(``f1 + f2 = 2 alpha > 0``: never both zero).  This is 000's model of J1 in Example 1 with
``tau_2 = 0``, a juggling structure (Sect. 4).  Numbers chosen: ``J_m = 1e-3`` kg m^2, ``N = 5``,
``m_l = 0.5`` kg, ``l_l = 0.3`` m, ``alpha = 0.02`` rad, ``e = 0.5``.

Controller ``pd``: PD (36) on the measured shaft only (000 Sect. 5, Remark 6: collocated, the link is
not measured), ``tau = -K_p (theta_m - theta_md) - K_v theta_m'`` (the shaft carries no gravity); ``V``
(37) adds the link's energy.  The equilibrium it converges to is isolated (gravity): the link rests
on flank ``f1`` (lifted to the right) with ``lam = m_l g (l_l/2) sin theta_l`` and the shaft deflected
back by ``lam / (N K_p)``; ``invctl simulate backlash_pivot --json`` reports it next to this closed form.
"""
from __future__ import annotations

import math

import casadi as ca
import numpy as np

from invctl.contact.structure import subsystem_report
from invctl.model import Gap, Model, ParamSet
from invctl.scenes import Contact, Report, Scene

PARAMS = {"Jm": 1e-3, "N": 5.0, "ml": 0.5, "ll": 0.3, "alpha": 0.02, "e": 0.5, "g": 9.81}
MODEL_PARAMS = tuple(PARAMS)
SETTINGS = {"Kp": 2.0, "Kv": 0.05, "link_d": 0.8, "link0": 0.0, "h": 1e-4, "theta": 0.5, "t_end": 3.0,
            "projection": 0.0, "activation_tol": 1e-12}


def build(**overrides: float) -> Model:
    """Shaft and link with the two backlash gaps."""
    P = ParamSet(list(MODEL_PARAMS))
    q, v = ca.SX.sym("q", 2), ca.SX.sym("v", 2)
    Jm, N, ml, ll, a, g = (P[k] for k in ("Jm", "N", "ml", "ll", "alpha", "g"))
    T = 0.5 * Jm * v[0] ** 2 + 0.5 * (ml * ll**2 / 3) * v[1] ** 2
    U = -ml * g * 0.5 * ll * ca.cos(q[1])
    rel = q[1] - q[0] / N
    gaps = [Gap("f1", a + rel, "e"), Gap("f2", a - rel, "e")]
    return Model.from_lagrangian("backlash_pivot", q, v, P, PARAMS, T=T, V=U, B=ca.DM([[1.0], [0.0]]), gaps=gaps,
                                 overrides={k: x for k, x in overrides.items() if k in MODEL_PARAMS},
                                 q_names=["theta_m", "theta_l"], u_names=["tau"])


def link_potential(model) -> ca.SX:
    """Gravity potential of the link (the ``U_2`` of (37))."""
    p = model.params
    return -p["ml"] * p["g"] * 0.5 * p["ll"] * ca.cos(model.q[1])


def _pd(model, s):
    from invctl.control.pdplus import pd_gravity

    return pd_gravity(model, Kp=s["Kp"], Kv=s["Kv"], q_d=model.values["N"] * s["link_d"], idx=[0],
                      potential=link_potential(model))


def _initial(model, s, controller):
    N = model.values["N"]
    return np.array([N * s["link0"], s["link0"]]), np.zeros(2)


def closed_form_equilibrium(values: dict, Kp: float, theta_md: float) -> dict:
    """The rest point of PD (36) with the link on flank ``f1`` (``theta_l > 0``) or ``f2``, by a scalar
    root of ``theta_l = (theta_md - s lam / (N K_p)) / N - s alpha`` with ``lam = m g (l/2) |sin theta_l|``
    (``s = +1`` on ``f1``, ``-1`` on ``f2``)."""
    from scipy.optimize import brentq

    N, m, l, a, g = (values[k] for k in ("N", "ml", "ll", "alpha", "g"))
    out = None
    for s_, name in ((1.0, "f1"), (-1.0, "f2")):
        def r(th):
            lam = s_ * m * g * 0.5 * l * math.sin(th)
            return th - ((theta_md - s_ * lam / (N * Kp)) / N - s_ * a)

        ths = np.linspace(-math.pi / 2, math.pi / 2, 401)
        vals = [r(t) for t in ths]
        for t0, t1, r0, r1 in zip(ths[:-1], ths[1:], vals[:-1], vals[1:]):
            if r0 * r1 <= 0:
                th = brentq(r, t0, t1, xtol=1e-15)
                lam = s_ * m * g * 0.5 * l * math.sin(th)
                if lam >= 0:
                    out = {"flank": name, "theta_l": th, "lam": lam,
                           "theta_m": theta_md - s_ * lam / (N * Kp)}
    return out or {}


def equilibrium_report(ctx) -> dict:
    """The run's end, the generic equilibrium next to it and the closed form."""
    from invctl.contact.equilibria import static_equilibrium, static_force

    model, s, tr = ctx.model, ctx.settings, ctx.result
    theta_md = model.values["N"] * s["link_d"]
    cf = closed_form_equilibrium(model.values, s["Kp"], theta_md)
    law = _pd(model, s)
    u, _, kap = law.symbolic(model, ca.SX.sym("t"))
    F = ca.substitute(static_force(model, u), kap, ca.DM(law.kappa_values))
    e = static_equilibrium(model, F, tr.q[:, -1])
    flanks = np.where(tr.gaps[0] <= 1e-9, 1, np.where(tr.gaps[1] <= 1e-9, 2, 0))
    seq = flanks[flanks > 0]
    return {"closed form: flank, theta_m*, theta_l*, lam": f"{cf.get('flank')}, {cf.get('theta_m', float('nan')):.10f}, "
                                                           f"{cf.get('theta_l', float('nan')):.10f}, "
                                                           f"{cf.get('lam', float('nan')):.8f}",
            "|q* (Newton on (40)) - closed form|": float(np.abs(e.q - [cf["theta_m"], cf["theta_l"]]).max()) if cf
            else float("nan"),
            "|q(t_end) - q* (closed form)|": float(np.abs(tr.q[:, -1] - [cf["theta_m"], cf["theta_l"]]).max()) if cf
            else float("nan"),
            "both flanks closed at some step": bool(np.any((tr.gaps[0] <= 1e-9) & (tr.gaps[1] <= 1e-9))),
            "changes of the flank in contact": int(np.count_nonzero(np.diff(seq))) if seq.size else 0}


def _check(values):
    from invctl.errors import ParameterError

    if not 0 <= values["e"] <= 1:
        raise ParameterError(f"backlash_pivot: restitution e must lie in [0, 1], got {values['e']}")
    if values["g"] < 0:
        raise ParameterError(f"backlash_pivot: gravity g must be >= 0, got {values['g']}")


def drawing(model):
    """The link (pivot to tip) and a shaft marker at the gear's angle ``theta_m / N``."""
    from invctl.plot.animate import Drawing

    th_m, th_l = model.q[0], model.q[1]
    l, N = model.params["ll"], model.params["N"]
    tip = l * ca.vertcat(ca.sin(th_l), -ca.cos(th_l))
    mark = 0.4 * l * ca.vertcat(ca.sin(th_m / N), -ca.cos(th_m / N))
    return Drawing(points={"pivot": ca.vertcat(0, 0), "tip": tip, "gear": mark},
                   links=[("pivot", "tip"), ("pivot", "gear", {"color": "tab:red", "lw": 1.5})])


SCENE = Scene(
    "backlash_pivot", build, params=PARAMS, settings=SETTINGS,
    positive=("Jm", "N", "ml", "ll", "alpha", "Kp", "Kv", "h", "t_end"), validate=_check,
    contact=Contact(controllers={"pd": _pd}, initial_state=_initial, potential=link_potential),
    reports=(Report("000 (40): the rest point", equilibrium_report, controllers=("pd",)),
             Report("000 Sect. 2: open system", subsystem_report, command="analyze",
                    printed={"n (open system)": 2, "n_ind": 2, "unilateral constraints m_u": 2})),
    drawing=drawing,
    description="pivot with gear backlash (000 Fig. 2(a)): two flanks that cannot both be closed; PD (36) on the "
                "shaft, convergence to the rest point on one flank",
)
