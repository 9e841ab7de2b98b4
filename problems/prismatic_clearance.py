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
quarter of the clearance), ``none``.
"""
from __future__ import annotations

import sys

import casadi as ca
import numpy as np

from invctl.model import Gap, Model, ParamSet
from invctl.scenes import lazy_command

PARAMS = {
    "m1": 1.0, "m2": 0.5, "l": 0.05, "L": 0.11, "e": 0.5,
    "actuators": 1.0,
    "Kp": 100.0, "Kv": 20.0, "qd": 0.2, "beta": 1.0,
    "v20": 0.3, "period": 2.0, "amp": 0.1,
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

    return FeedbackLaw("switching", names, (Kp, Kv, amp, period, a_c, d_rel), build_, {"lyapunov": False})


COMMANDS = {
    "simulate": lazy_command(__name__, "invctl.studies.contact_commands:prismatic_command"),
}


def tradeoff_spec(params, smoke: bool = False):
    from invctl.studies.contact_commands import prismatic_tradeoff

    return prismatic_tradeoff(sys.modules[__name__], params, smoke=smoke)
