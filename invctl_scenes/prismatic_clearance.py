"""One-DoF prismatic joint with clearance (000 Fig. 2(b), Example 3, Remark 4).

Body 1 (mass m1, position q1) carries a slot in which body 2 (m2, q2) moves;
horizontal, no gravity.  Gaps (000 Example 3):
``f1 = q2 - q1 - l >= 0`` and ``f2 = q1 - q2 + L - l >= 0``; the clearance
is ``L - 2 l``.  ``actuators = 2``: both bodies driven (pre-loading
(11)-(13) keeps ``f1 = 0`` with multiplier ``beta``); ``actuators = 1``: body 1
only (PD (36) regulation, or the switching strategy of Remark 4).

Controllers (``--controller``): ``pd`` (default with one actuator),
``preload`` (default with two), ``switching`` (one actuator), ``juggling``
(two actuators: I/O linearization (25) of ``y = f1``, gap driven to a
quarter of the clearance), ``juggling_design`` (one actuator: the recursive
impact design (29)-(33), :mod:`invctl_scenes/_juggling_design.py` (next to its scene): body 2 leaves
wall f1 at ``v20`` and is brought in ``jcycles`` cycles
Sigma_1 -> Sigma_2 -> Sigma_1 to the post-impact state ``(jq2, jv2)`` at its
last impact on f1, through targets spaced evenly between; a target that step 2
cannot reach stops the command with a ``JugglingInfeasible`` error), ``none``.
"""
from __future__ import annotations

import casadi as ca
import numpy as np

from invctl.model import Gap, Model, ParamSet
from invctl.scenes import Contact, Report, Scene

PARAMS = {
    "m1": 1.0, "m2": 0.5, "l": 0.05, "L": 0.11, "e": 0.5,
    "actuators": 1.0,
    "Kp": 100.0, "Kv": 20.0, "qd": 0.2, "beta": 1.0,
    "v20": 0.3, "period": 2.0, "amp": 0.1, "jq2": 0.2, "jv2": 0.1, "jcycles": 3.0,
    "h": 1e-4, "theta": 0.5, "t_end": 2.0, "projection": 0.0, "activation_tol": 1e-12,
}
MODEL_PARAMS = ("m1", "m2", "l", "L", "e")


def build(**overrides: float) -> Model:
    """The two-body model; ``actuators`` (1 or 2) selects the input matrix."""
    P = ParamSet(list(MODEL_PARAMS))
    q = ca.SX.sym("q", 2)
    v = ca.SX.sym("v", 2)
    act = int(overrides.get("actuators", PARAMS["actuators"]))
    if act not in (1, 2):
        from invctl.errors import ParameterError

        raise ParameterError(f"prismatic_clearance: actuators must be 1 or 2, got {act}")
    B = ca.DM([[1.0], [0.0]]) if act == 1 else ca.DM.eye(2)
    M = ca.diag(ca.vertcat(P["m1"], P["m2"]))
    gaps = [Gap("f1", q[1] - q[0] - P["l"], "e"), Gap("f2", q[0] - q[1] + P["L"] - P["l"], "e")]
    ov = {k: v_ for k, v_ in overrides.items() if k in MODEL_PARAMS}
    return Model("prismatic_clearance", q, v, P, {k: PARAMS[k] for k in MODEL_PARAMS}, M=M, f=ca.SX.zeros(2),
                 B=B, gaps=gaps, overrides=ov, q_names=["q1", "q2"],
                 u_names=["tau1"] if act == 1 else ["tau1", "tau2"])


def switching_law(model: Model, *, Kp: float, Kv: float, amp: float, period: float, a_c: float = 2.0,
                  d_rel: float = 20.0, contact_tol: float = 1e-9):
    """Remark 4: body 1 alone moves body 2 along ``x_d(t) = l + amp sin(2 pi t/period)``.

    The desired pair acceleration ``a_d = xdd_d - Kp (q2 - x_d) - Kv (v2 - xd_d)``
    fixes which wall must carry body 2: ``f1`` (push) when ``a_d >= 0``, ``f2``
    (pull) otherwise.  In that contact (gap <= ``contact_tol``) body 1 applies
    ``(m1 + m2) a_d`` (the multiplier is then ``m2 a_d >= 0``: persistent
    contact, mode (i)/(iv)); otherwise it crosses the clearance with relative
    acceleration ``a_c`` towards the wanted wall and relative damping ``d_rel``
    (modes (ii), (iii)/(vi): impact and finite-time stabilization by
    restitution ``e < 1``).
    """
    from invctl.control.pdplus import FeedbackLaw

    names = ("Kp", "Kv", "amp", "period", "a_c", "d_rel")

    def build_(model, t, kappa):
        kp, kv, A, T, ac, dr = (kappa[i] for i in range(6))
        m1, m2, l, L = (model.params[k] for k in ("m1", "m2", "l", "L"))
        w = 2 * np.pi / T
        xd = l + A * ca.sin(w * t)
        xd_d = A * w * ca.cos(w * t)
        xd_dd = -A * w**2 * ca.sin(w * t)
        q1, q2 = model.q[0], model.q[1]
        v1, v2 = model.v[0], model.v[1]
        a_d = xd_dd - kp * (q2 - xd) - kv * (v2 - xd_d)
        push = a_d >= 0
        f1 = q2 - q1 - l
        f2 = q1 - q2 + L - l
        gap = ca.if_else(push, f1, f2)
        s = ca.if_else(push, 1, -1)
        tau_contact = (m1 + m2) * a_d
        tau_cross = m1 * (s * ac - dr * (v1 - v2))
        u = ca.if_else(gap <= contact_tol, tau_contact, tau_cross)
        V = 0.5 * m1 * v1**2 + 0.5 * m2 * v2**2
        return u, V

    l_value = model.values["l"]

    def x_d(t):
        return l_value + amp * ca.sin(2 * np.pi * t / period)

    return FeedbackLaw("switching", names, (Kp, Kv, amp, period, a_c, d_rel), build_,
                       {"lyapunov": False, "tracked": ([1], x_d)})


def _pd(model, s):
    from invctl.control.pdplus import pd_gravity

    _need(model, 1, "pd", "PD (36) acts on body 1 only")
    return pd_gravity(model, Kp=s["Kp"], Kv=s["Kv"], q_d=s["qd"], idx=[0])


def _preload(model, s):
    from invctl.control.preload import preload_law

    act = model.m
    l = model.values["l"]
    return preload_law(model, [0], beta=s["beta"], Kp=s["Kp"] if act == 2 else 0.0, Kv=s["Kv"] if act == 2 else 0.0,
                       y_d=[s["qd"], s["qd"] + l][:act])


def _switching(model, s):
    _need(model, 1, "switching", "Remark 4 drives body 1 only")
    return switching_law(model, Kp=s["Kp"], Kv=s["Kv"], amp=s["amp"], period=s["period"])


def _juggling(model, s):
    from invctl.control.juggling import io_decoupling_check, juggling_law

    _need(model, 2, "juggling", "the I/O linearization (25) of y = f1 needs both bodies driven")
    p = model.values
    io_decoupling_check(model, _initial(model, s, "juggling")[0], [0])
    return juggling_law(model, [0], Ky=s["Kp"], Dy=s["Kv"], y_d=0.25 * (p["L"] - 2 * p["l"]))


def juggling_plan(model, s):
    """The plan of the ``juggling_design`` controller (000 (29)-(33)) for the settings ``s``."""
    from invctl_scenes._juggling_design import Juggler, JugglerState, design

    p = model.values
    j = Juggler(p["m1"], p["m2"], p["l"], p["L"], p["e"])
    start = JugglerState(0.0, 0.0, 0.0, p["l"], s["v20"])
    K = int(s["jcycles"])
    targets = [(p["l"] + (s["jq2"] - p["l"]) * k / K, s["v20"] + (s["jv2"] - s["v20"]) * k / K) for k in range(1, K + 1)]
    return design(j, start, targets)


def _juggling_design(model, s):
    from invctl_scenes._juggling_design import juggling_plan_law

    _need(model, 1, "juggling_design", "the juggler drives body 1 only")
    return juggling_plan_law(model, juggling_plan(model, s), Kp=s["Kp"], Kv=s["Kv"])


def juggling_report(ctx) -> dict:
    """Planned impacts (000 (29)-(33)) against the simulated ones."""
    from invctl_scenes._juggling_design import plan_vs_run

    plan = juggling_plan(ctx.model, ctx.settings)
    out = {f"cycle {k + 1}: D0, D1, A = y2'(t1-), B = y1'(t2-)": [c.D0, c.D1, c.A, c.B]
           for k, c in enumerate(plan.cycles)}
    out["designed final post-impact state (q2, q2')"] = [plan.cycles[-1].end.q2, plan.cycles[-1].end.v2]
    out.update(plan_vs_run(plan, ctx.result))
    return out


def juggling_design_analysis(ctx) -> dict:
    """000 (29)-(33) without a run: the default plan, and step 2 failing where it must (body 2 leaving
    wall f1 backwards, target ahead)."""
    from invctl_scenes._juggling_design import Juggler, JugglerState, design_cycle
    from invctl.errors import JugglingInfeasible

    s = {**PARAMS, **ctx.settings}
    plan = juggling_plan(ctx.model, s)
    p = ctx.model.values
    out = {"cycles": len(plan.cycles), "planned impacts (t, wall, q2, q2' after)":
           [[round(float(x), 6) for x in r] for r in plan.impact_table()]}
    j = Juggler(p["m1"], p["m2"], p["l"], p["L"], p["e"])
    try:
        design_cycle(j, JugglerState(0.0, 0.0, -0.5, p["l"], -0.2), p["l"] + 0.1, 0.2)
        out["body 2 leaving backwards, target 0.1 m ahead"] = "feasible"
    except JugglingInfeasible as exc:
        out["body 2 leaving backwards, target 0.1 m ahead"] = str(exc).split(";")[0]
    return out


#: the actuators each controller needs (the pipeline runs those that fit ``--set actuators=...``)
REQUIRES = {"pd": {"actuators": 1}, "switching": {"actuators": 1}, "juggling": {"actuators": 2},
            "juggling_design": {"actuators": 1}}


def _need(model, act, name, why):
    if model.m != act:
        from invctl.errors import SceneError

        raise SceneError(f"prismatic_clearance: controller {name!r} needs actuators={act} ({why}); "
                         f"use --set actuators={act}")


def _initial(model, s, controller):
    p = model.values
    l, L = p["l"], p["L"]
    if controller in ("preload", "switching"):
        return [0.0, l], [0.0, 0.0]
    if controller == "juggling_design":
        return [0.0, l], [0.0, s["v20"]]                    # just after an impact on f1 (000 Sect. 4)
    return [0.0, l + 0.5 * (L - 2 * l)], [0.0, s["v20"]]


def modes_report(ctx) -> dict:
    """Remark 4: which wall carries body 2 (1: f1 closed, 2: f2 closed, 0: crossing) and how often it changes."""
    tr = ctx.result
    modes = np.where(tr.gaps[0] <= 1e-9, 1, np.where(tr.gaps[1] <= 1e-9, 2, 0))
    return {"mode switches": int(np.count_nonzero(np.diff(modes))),
            "time in contact with f1, f2": [float(np.mean(modes == 1)), float(np.mean(modes == 2))]}


def _check(v: dict) -> None:
    from invctl.errors import ParameterError

    if v["actuators"] not in (1, 2):
        raise ParameterError(f"prismatic_clearance: actuators must be 1 or 2, got {v['actuators']}")
    if not 0 <= v["e"] <= 1:
        raise ParameterError(f"prismatic_clearance: restitution e must lie in [0, 1], got {v['e']}")
    if not v["L"] > 2 * v["l"]:
        raise ParameterError(f"prismatic_clearance: the clearance L - 2 l = {v['L'] - 2 * v['l']:.3g} must be "
                             "positive")
    # the gaps are differences of positions of size S: their round-off (~1e-16 S) must stay below a
    # millionth of the clearance, or the contact decisions are made on round-off
    S = v["L"] + abs(v["qd"]) + abs(v["amp"])
    if v["L"] - 2 * v["l"] < 1e-9 * S:
        raise ParameterError(f"prismatic_clearance: the clearance L - 2 l = {v['L'] - 2 * v['l']:.3g} is below "
                             f"1e-9 of the positions' size {S:.3g}: the gap expressions cannot resolve it in double "
                             "precision; use a larger clearance")
    _common(v)


def _common(v: dict, name: str = "prismatic_clearance") -> None:
    """Checks shared by the time-stepping settings and the PD/pre-loading gains."""
    from invctl.errors import ParameterError

    if not 0 <= v["theta"] <= 1:
        raise ParameterError(f"{name}: theta of the theta-method must lie in [0, 1], got {v['theta']}")
    if v["projection"] not in (0, 1):
        raise ParameterError(f"{name}: projection is a switch, 0 or 1, got {v['projection']}")
    if v["activation_tol"] < 0:
        raise ParameterError(f"{name}: activation_tol (a gap threshold) must be >= 0, got {v['activation_tol']}")
    for k in ("Kp", "Kv"):
        if v[k] < 0:
            raise ParameterError(f"{name}: the gain {k} must be >= 0, got {v[k]}")


def drawing(model: Model):
    """Body 1 (the slot, drawn as its two walls) and body 2 (a point between them), side by side."""
    from invctl.plot.animate import Drawing

    q1, q2 = model.q[0], model.q[1]
    l, L = model.params["l"], model.params["L"]
    return Drawing(points={"wall1": ca.vertcat(q1 + l, 0), "wall1top": ca.vertcat(q1 + l, 0.05),
                           "wall2": ca.vertcat(q1 + L - l, 0), "wall2top": ca.vertcat(q1 + L - l, 0.05),
                           "body1": ca.vertcat(q1, 0.025), "body2": ca.vertcat(q2, 0.025)},
                   links=[("wall1", "wall1top"), ("wall2", "wall2top"), ("wall1", "wall2")])


SCENE = Scene(
    "prismatic_clearance", build, params={k: PARAMS[k] for k in (*MODEL_PARAMS, "actuators")},
    settings={k: v for k, v in PARAMS.items() if k not in (*MODEL_PARAMS, "actuators")},
    integer=("actuators", "projection", "jcycles"),
    positive=("m1", "m2", "l", "L", "h", "t_end", "period", "beta", "jcycles"), validate=_check,
    contact=Contact(controllers={"pd": _pd, "preload": _preload, "switching": _switching, "juggling": _juggling,
                                 "juggling_design": _juggling_design},
                    initial_state=_initial, clearance=lambda model, s: model.values["L"] - 2 * model.values["l"],
                    default_controller=lambda model, s: "pd" if model.m == 1 else "preload", requires=REQUIRES),
    reports=(Report("Remark 4 switching modes", modes_report, controllers=("switching",)),
             Report("000 (29)-(33): planned and simulated impacts", juggling_report, controllers=("juggling_design",)),
             Report("000 (29)-(33): recursive juggling design", juggling_design_analysis, command="analyze")),
    drawing=drawing,
    description="one-DoF prismatic joint with clearance (000 Fig. 2(b), Example 3, Remark 4)",
)
