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
from invctl.scenes import lazy_command

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


COMMANDS = {
    "simulate": lazy_command(__name__, "invctl.studies.contact_commands:slider_crank_command"),
}
