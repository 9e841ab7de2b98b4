"""Slider-crank with a revolute-joint clearance between crank and rod (000 Fig. 4(a)).

Horizontal plane (no gravity).  The crank (inertia J1 about the fixed pivot,
length r, actuated by tau) carries the bearing at its tip
``A = r (cos theta, sin theta)``; the rod (mass mr, length Lr, inertia
mr Lr^2/12) is pinned without clearance to the slider (mass ms, position s,
viscous friction cs) at ``C = (s, 0)`` and carries the journal at
``B = C + Lr (-cos phi, sin phi)``.  Open system (000 Sect. 2):
``S1 = crank (theta)``, ``S2 = rod + slider (s, phi)``, ``n = 3``,
``m_u = 1``, clearance radius c:

    f(q) = (c^2 - |A - B|^2) / (2 c) >= 0

(smooth everywhere, equal to ``c - |A - B|`` to first order at contact).

Controllers: ``pd`` -- PD (36) on the crank to ``theta_d`` (Prop. 2:
convergence to the set of equilibria: crank at ``theta_d``, rod and slider at
rest with the journal anywhere in the bearing); ``pdplus`` -- PD+ (57) on
the crank tracking ``theta_d(t) = theta_0 + amp sin(2 pi t / period)``
(000 Sect. 6; Prop. 3 assumes full actuation, here ``V`` is monitored).
"""
from __future__ import annotations

import math

import casadi as ca
import numpy as np

from invctl.model import Gap, Model, ParamSet
from invctl.scenes import Contact, Scene

PARAMS = {
    "J1": 0.01, "r": 0.1, "Lr": 0.3, "mr": 0.5, "ms": 0.5, "cs": 0.5, "c": 1e-3, "e": 0.5,
    "theta0": 0.5, "theta_d": 1.5, "Kp": 5.0, "Kv": 0.5, "amp": 0.8, "period": 1.0,
    "h": 1e-4, "theta": 0.5, "t_end": 3.0, "projection": 0.0, "activation_tol": 1e-12,
}
MODEL_PARAMS = ("J1", "r", "Lr", "mr", "ms", "cs", "c", "e")


def build(**overrides: float) -> Model:
    """The open slider-crank (q = theta, s, phi) from its Lagrangian."""
    P = ParamSet(list(MODEL_PARAMS))
    q = ca.SX.sym("q", 3)
    v = ca.SX.sym("v", 3)
    th, s, ph = q[0], q[1], q[2]
    J1, r, Lr, mr, ms, cs, c = (P[k] for k in ("J1", "r", "Lr", "mr", "ms", "cs", "c"))
    G = ca.vertcat(s - 0.5 * Lr * ca.cos(ph), 0.5 * Lr * ca.sin(ph))
    vG = ca.mtimes(ca.jacobian(G, q), v)
    T = 0.5 * J1 * v[0] ** 2 + 0.5 * ms * v[1] ** 2 + 0.5 * mr * ca.sumsqr(vG) + 0.5 * (mr * Lr**2 / 12) * v[2] ** 2
    A = r * ca.vertcat(ca.cos(th), ca.sin(th))
    B = ca.vertcat(s - Lr * ca.cos(ph), Lr * ca.sin(ph))
    gap = (c**2 - ca.sumsqr(A - B)) / (2 * c)
    Q = ca.vertcat(0, -cs * v[1], 0)
    ov = {k: v_ for k, v_ in overrides.items() if k in MODEL_PARAMS}
    return Model.from_lagrangian("slider_crank_clearance", q, v, P, {k: PARAMS[k] for k in MODEL_PARAMS}, T=T, Q=Q,
                                 B=ca.DM([[1.0], [0.0], [0.0]]), gaps=[Gap("journal", gap, "e")], overrides=ov,
                                 q_names=["theta", "s", "phi"], u_names=["tau"])


def centered_configuration(model: Model, theta: float) -> np.ndarray:
    """Configuration with the journal at the bearing centre (f = c/2) for crank angle ``theta``."""
    p = model.values
    ax, ay = p["r"] * math.cos(theta), p["r"] * math.sin(theta)
    if abs(ay) >= p["Lr"]:
        from invctl.errors import ParameterError

        raise ParameterError("rod too short for this crank angle")
    ph = math.asin(ay / p["Lr"])
    return np.array([theta, ax + p["Lr"] * math.cos(ph), ph])


def _pd(model, s):
    from invctl.control.pdplus import pd_gravity

    return pd_gravity(model, Kp=s["Kp"], Kv=s["Kv"], q_d=s["theta_d"], idx=[0])


def _pdplus(model, s):
    from invctl.control.pdplus import pd_plus_tracking

    th0, amp, per = s["theta0"], s["amp"], s["period"]
    return pd_plus_tracking(model, Kp=s["Kp"], Kv=s["Kv"], q_d=lambda t: th0 + amp * ca.sin(2 * np.pi * t / per),
                            idx=[0])


def _check(v: dict) -> None:
    from invctl.errors import ParameterError

    if not 0 <= v["e"] <= 1:
        raise ParameterError(f"slider_crank_clearance: restitution e must lie in [0, 1], got {v['e']}")
    if v["cs"] < 0:
        raise ParameterError(f"slider_crank_clearance: slider friction cs must be >= 0, got {v['cs']}")
    if v["Lr"] <= v["r"]:
        raise ParameterError(f"slider_crank_clearance: the rod (Lr = {v['Lr']}) must be longer than the crank "
                             f"(r = {v['r']})")
    # the gap (c^2 - |A - B|^2) / (2 c) subtracts points of size r + Lr: its round-off (~1e-16 (r + Lr))
    # must stay below a millionth of the clearance
    if v["c"] < 1e-9 * (v["r"] + v["Lr"]):
        raise ParameterError(f"slider_crank_clearance: the clearance c = {v['c']:.3g} is below 1e-9 of the "
                             f"mechanism's size r + Lr = {v['r'] + v['Lr']:.3g}: the gap expression cannot resolve it "
                             "in double precision; use a larger clearance")
    if not 0 <= v["theta"] <= 1:
        raise ParameterError(f"slider_crank_clearance: theta of the theta-method must lie in [0, 1], got {v['theta']}")
    if v["projection"] not in (0, 1):
        raise ParameterError(f"slider_crank_clearance: projection is a switch, 0 or 1, got {v['projection']}")
    if v["activation_tol"] < 0:
        raise ParameterError(f"slider_crank_clearance: activation_tol must be >= 0, got {v['activation_tol']}")


def drawing(model: Model):
    """Crank, rod (journal B in the bearing at the crank tip A) and slider."""
    from invctl.plot.animate import Drawing

    th, s, ph = model.q[0], model.q[1], model.q[2]
    r, Lr = model.params["r"], model.params["Lr"]
    A = r * ca.vertcat(ca.cos(th), ca.sin(th))
    B = ca.vertcat(s - Lr * ca.cos(ph), Lr * ca.sin(ph))
    return Drawing(points={"O": ca.vertcat(0, 0), "A": A, "B": B, "C": ca.vertcat(s, 0)},
                   links=[("O", "A"), ("B", "C")], segments=[((-0.15, -0.02), (0.5, -0.02))])


SCENE = Scene(
    "slider_crank_clearance", build, params={k: PARAMS[k] for k in MODEL_PARAMS},
    settings={k: v for k, v in PARAMS.items() if k not in MODEL_PARAMS},
    integer=("projection",), positive=("J1", "r", "Lr", "mr", "ms", "c", "h", "t_end", "period", "Kp", "Kv"),
    validate=_check,
    contact=Contact(controllers={"pd": _pd, "pdplus": _pdplus}, clearance=lambda model, s: model.values["c"],
                    initial_state=lambda model, s, controller: (centered_configuration(model, s["theta0"]),
                                                                np.zeros(3))),
    drawing=drawing,
    description="slider-crank with a revolute-joint clearance (000 Fig. 4(a)): PD (36) regulation, PD+ (57) "
                "tracking",
)
