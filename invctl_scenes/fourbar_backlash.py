"""Four-bar driven through its motor shaft with gear backlash at J1 (000 Fig. 6(b), end of Sect. 5).

A crank-rocker four-bar in the vertical plane: ground pivots ``A = (0, 0)`` (J1) and ``D = (a, 0)``,
crank ``AB`` (``b``), coupler ``BC`` (``c``), rocker ``DC`` (``d``); ``a, b, c, d = 0.3, 0.1, 0.3, 0.2``
m (Grashof: the crank turns fully), uniform bars of 1.5 kg/m, ``C`` on the upper branch.  The crank
is driven by the motor shaft (angle ``theta_ms``, inertia ``J_ms = 2e-4`` kg m^2, torque ``tau`` at
J11) through a gear of ratio ``N = 5`` with play ``2 alpha`` (``alpha = 0.02`` rad at the crank):

    f1 = alpha + theta_1 - theta_ms / N >= 0,    f2 = alpha - theta_1 + theta_ms / N >= 0.

The four-bar's loop is closed in closed form (``theta_2(theta_1)``, ``theta_3(theta_1)``), so the open
system is ``q = (theta_ms, theta_1)``: two independent subsystems, the shaft (actuated) and the
four-bar (1 DoF, unactuated).  000 suggests a feedback torque at J11 measuring ``theta_ms`` and its
rate only: PD (36) ``tau = -K_p (theta_ms - N theta_1d) - K_v theta_ms'`` (the shaft carries no
gravity), with ``V`` (37) the shaft's closed-loop energy plus the four-bar's energy.  The four-bar's
gravity torque about J1 changes sign with ``theta_1``, so on its way the crank moves from one flank
to the other (the two contacts are never closed together); at rest it lies on one flank with the
multiplier equal to that torque (virtual work), which the scene report checks.
"""
from __future__ import annotations

import casadi as ca
import numpy as np

from invctl.contact.structure import subsystem_report
from invctl.model import Gap, Model, ParamSet
from invctl.scenes import Contact, Report, Scene

PARAMS = {"a": 0.3, "b": 0.1, "c": 0.3, "d": 0.2, "rho": 1.5, "Jms": 2e-4, "N": 5.0, "alpha": 0.02, "e": 0.5,
          "g": 9.81}
MODEL_PARAMS = tuple(PARAMS)
SETTINGS = {"Kp": 0.5, "Kv": 0.02, "crank_d": 2.0, "crank0": 0.5, "h": 1e-4, "theta": 0.5, "t_end": 4.0,
            "projection": 0.0, "activation_tol": 1e-12}


def fourbar_points(th1, a, b, c, d):
    """``B``, ``C`` and the link angles of the four-bar for crank angle ``th1`` (SX or numpy; upper branch)."""
    lib = ca if isinstance(th1, (ca.SX, ca.MX)) else np
    Bx, By = b * lib.cos(th1), b * lib.sin(th1)
    dx, dy = a - Bx, -By
    L2 = dx**2 + dy**2
    Ld = lib.sqrt(L2)
    k = (c**2 - d**2 + L2) / (2 * Ld)
    h = lib.sqrt(c**2 - k**2)
    Cx = Bx + k * dx / Ld - h * dy / Ld
    Cy = By + k * dy / Ld + h * dx / Ld
    return (Bx, By), (Cx, Cy)


def build(**overrides: float) -> Model:
    """Shaft and four-bar (crank angle) with the two backlash gaps."""
    P = ParamSet(list(MODEL_PARAMS))
    q, v = ca.SX.sym("q", 2), ca.SX.sym("v", 2)
    a, b, c, d, rho, Jms, N, al, g = (P[k] for k in ("a", "b", "c", "d", "rho", "Jms", "N", "alpha", "g"))
    (Bx, By), (Cx, Cy) = fourbar_points(q[1], a, b, c, d)
    B, C, D = ca.vertcat(Bx, By), ca.vertcat(Cx, Cy), ca.vertcat(a, 0)
    th2 = ca.atan2(C[1] - B[1], C[0] - B[0])
    th3 = ca.atan2(C[1] - D[1], C[0] - D[0])
    T = 0.5 * Jms * v[0] ** 2
    U = 0
    for start, angle, length in ((ca.vertcat(0, 0), q[1], b), (B, th2, c), (D, th3, d)):
        m = rho * length
        com = start + 0.5 * length * ca.vertcat(ca.cos(angle), ca.sin(angle))
        vc = ca.mtimes(ca.jacobian(com, q), v)
        om = ca.mtimes(ca.jacobian(angle, q), v)
        T = T + 0.5 * m * ca.sumsqr(vc) + 0.5 * (m * length**2 / 12) * om**2
        U = U + m * g * com[1]
    rel = q[1] - q[0] / N
    gaps = [Gap("f1", al + rel, "e"), Gap("f2", al - rel, "e")]
    return Model.from_lagrangian("fourbar_backlash", q, v, P, PARAMS, T=T, V=U, B=ca.DM([[1.0], [0.0]]), gaps=gaps,
                                 overrides={k: x for k, x in overrides.items() if k in MODEL_PARAMS},
                                 q_names=["theta_ms", "theta_1"], u_names=["tau_J11"])


def fourbar_potential(model) -> ca.SX:
    """Gravity potential of the four-bar (``U_2`` of (37)), as in :func:`build`."""
    p = model.params
    a, b, c, d, rho, g = (p[k] for k in ("a", "b", "c", "d", "rho", "g"))
    (Bx, By), (Cx, Cy) = fourbar_points(model.q[1], a, b, c, d)
    return rho * g * (b * 0.5 * By + c * 0.5 * (By + Cy) + d * 0.5 * Cy)


def _pd(model, s):
    from invctl.control.pdplus import pd_gravity

    return pd_gravity(model, Kp=s["Kp"], Kv=s["Kv"], q_d=model.values["N"] * s["crank_d"], idx=[0],
                      potential=fourbar_potential(model))


def _initial(model, s, controller):
    return np.array([model.values["N"] * s["crank0"], s["crank0"]]), np.zeros(2)


def gravity_torque(values: dict, th1: float, dth: float = 1e-6) -> float:
    """``dU/dtheta_1`` of the four-bar by central differences of numpy positions (virtual work)."""
    def U(t):
        (_, By), (_, Cy) = fourbar_points(t, *(values[k] for k in ("a", "b", "c", "d")))
        return values["rho"] * values["g"] * (values["b"] * 0.5 * By + values["c"] * 0.5 * (By + Cy)
                                               + values["d"] * 0.5 * Cy)

    return (U(th1 + dth) - U(th1 - dth)) / (2 * dth)


def rest_report(ctx) -> dict:
    """The rest point: flank, multiplier against the gravity torque (virtual work), shaft deflection."""
    tr, model, s = ctx.result, ctx.model, ctx.settings
    v = model.values
    th_ms, th1 = tr.q[:, -1]  # q, P, gaps: time along the last axis
    lam = tr.P[:, -1] / tr.h
    k = int(np.argmax(lam))
    tq = gravity_torque(v, th1)
    flanks = np.where(tr.gaps[0] <= 1e-9, 1, np.where(tr.gaps[1] <= 1e-9, 2, 0))
    seq = flanks[flanks > 0]
    sign = 1.0 if k == 0 else -1.0
    return {"flank at rest": model.gaps[k].name,
            "multiplier P/h at the end": float(lam[k]),
            "gravity torque dU/dtheta_1 (virtual work, finite differences)": tq,
            "|lam - sign dU/dtheta_1|": float(abs(lam[k] - sign * tq)),
            "shaft: K_p (theta_ms - theta_msd) + lam_1/N - lam_2/N": float(
                s["Kp"] * (th_ms - v["N"] * s["crank_d"]) + (lam[0] - lam[1]) / v["N"]),
            "changes of the flank in contact": int(np.count_nonzero(np.diff(seq))) if seq.size else 0,
            "both flanks closed at some step": bool(np.any((tr.gaps[0] <= 1e-9) & (tr.gaps[1] <= 1e-9)))}


def _check(values):
    from invctl.errors import ParameterError

    a, b, c, d = (values[k] for k in ("a", "b", "c", "d"))
    s, l = min(a, b, c, d), max(a, b, c, d)
    if not (b == s and s + l <= a + b + c + d - s - l):
        raise ParameterError(f"fourbar_backlash: a, b, c, d = {a}, {b}, {c}, {d} is not a Grashof crank-rocker with "
                             "the crank b shortest; the crank could not turn fully")
    if not 0 <= values["e"] <= 1:
        raise ParameterError(f"fourbar_backlash: restitution e must lie in [0, 1], got {values['e']}")


def drawing(model):
    from invctl.plot.animate import Drawing

    p = model.params
    (Bx, By), (Cx, Cy) = fourbar_points(model.q[1], p["a"], p["b"], p["c"], p["d"])
    gear = 0.5 * p["b"] * ca.vertcat(ca.cos(model.q[0] / p["N"]), ca.sin(model.q[0] / p["N"]))
    return Drawing(points={"A": ca.vertcat(0, 0), "B": ca.vertcat(Bx, By), "C": ca.vertcat(Cx, Cy),
                           "D": ca.vertcat(p["a"], 0), "gear": gear},
                   links=[("A", "B"), ("B", "C"), ("C", "D"), ("A", "gear", {"color": "tab:red", "lw": 1.5})])


SCENE = Scene(
    "fourbar_backlash", build, params=PARAMS, settings=SETTINGS,
    positive=("a", "b", "c", "d", "rho", "Jms", "N", "alpha", "Kp", "Kv", "h", "t_end"), validate=_check,
    contact=Contact(controllers={"pd": _pd}, initial_state=_initial, potential=fourbar_potential),
    reports=(Report("000 Sect. 5 (Fig. 6(b)): rest on a flank", rest_report, controllers=("pd",)),
             Report("000 Sect. 2: open system", subsystem_report, command="analyze",
                    printed={"n (open system)": 2, "n_ind": 2, "unilateral constraints m_u": 2})),
    drawing=drawing,
    description="four-bar driven through its motor shaft with gear backlash at J1 (000 Fig. 6(b)): PD (36) on "
                "the shaft angle (torque at J11), V (37), rest on one flank",
)
