"""Two-link arm in a vertical plane with a passive elastic second joint.

Joint 1 is driven by a torque u, joint 2 is passive with a torsional spring c2
and damper D2; angles are measured from the hanging (downward) position.

``build``            minimal coordinates q = (q1, q2) (q2 relative), colocated output
                     y = q1 (h' = B^T, 003 Sect. 2.3): Gamma = (M^-1)_11 > 0; the zero
                     dynamics (q1 held) are the damped pendulum of link 2 about joint 2:
                     J2 q2'' = -c2 q2 - D2 q2' - m2 g lc2 sin(q1 + q2), J2 = I2 + m2 lc2^2,
                     asymptotically stable: the arm is minimum phase.
``build_redundant``  the same arm in redundant coordinates q = (th1, th2, xc, yc) (absolute
                     angles, centre of link 2) with the joint as a holonomic constraint
                     g(q) = 0 (l = 2): Gamma = [G; B^T] M^-1 [G; B^T]^T is symmetric positive
                     definite and the Schur complement S of 003 (15) equals Gamma of the
                     minimal model (same physics, other coordinates).
``build_tip``        fully actuated arm (B = I) with the tip position as output: Gamma =
                     J_tip M^-1 is singular at the stretched/folded arm (sin q2 = 0), where
                     the relative degree does not exist.
"""
from __future__ import annotations

import math

import casadi as ca
import numpy as np

from invctl.model import Model, OperatingRegion, ParamSet
from invctl.reference import Reference, rest_to_rest
from invctl.scenes import Scene, Tracking

PARAMS = {
    "m1": 1.0, "m2": 0.5, "L1": 0.5, "L2": 0.4,
    "lc1": 0.25, "lc2": 0.2, "I1": 1.0 * 0.5**2 / 12, "I2": 0.5 * 0.4**2 / 12,
    "c2": 2.0, "D2": 0.1, "g": 9.81,
}
#: homogeneous links
DERIVED = {
    "lc1": lambda p: p["L1"] / 2, "lc2": lambda p: p["L2"] / 2,
    "I1": lambda p: p["m1"] * p["L1"] ** 2 / 12, "I2": lambda p: p["m2"] * p["L2"] ** 2 / 12,
}

REGION = OperatingRegion(
    q_lower=[-math.pi, -math.pi / 2], q_upper=[math.pi, math.pi / 2],
    sample_bounds=([-math.pi, -math.pi / 2], [math.pi, math.pi / 2]), v_scale=2.0,
    description="|q1| < pi, |q2| < pi/2",
)
REGION_REDUNDANT = OperatingRegion(
    q_lower=[-math.pi, -math.pi, -2.0, -2.0], q_upper=[math.pi, math.pi, 2.0, 2.0],
    constraints=(lambda q: math.cos(q[1] - q[0]),), v_scale=2.0,
    description="|th1| < pi, cos(th2 - th1) > 0",
)
REGION_TIP = OperatingRegion(
    q_lower=[-math.pi, -math.pi / 2], q_upper=[math.pi, math.pi / 2], v_scale=1.0,
    description="|q1| < pi, |q2| < pi/2 (contains the stretched arm q2 = 0)",
)


def _params():
    P = ParamSet(list(PARAMS))
    return P, {k: P[k] for k in PARAMS}


def _minimal(name, overrides, *, tip=False):
    P, p = _params()
    q, v = ca.SX.sym("q", 2), ca.SX.sym("v", 2)
    q1, q2 = q[0], q[1]
    r1 = ca.vertcat(p["lc1"] * ca.sin(q1), -p["lc1"] * ca.cos(q1))
    r2 = ca.vertcat(p["L1"] * ca.sin(q1) + p["lc2"] * ca.sin(q1 + q2),
                    -p["L1"] * ca.cos(q1) - p["lc2"] * ca.cos(q1 + q2))
    vel = lambda r: ca.mtimes(ca.jacobian(r, q), v)  # noqa: E731
    T = 0.5 * (p["m1"] * ca.sumsqr(vel(r1)) + p["I1"] * v[0] ** 2
               + p["m2"] * ca.sumsqr(vel(r2)) + p["I2"] * (v[0] + v[1]) ** 2)
    V = p["g"] * (p["m1"] * r1[1] + p["m2"] * r2[1]) + 0.5 * p["c2"] * q2**2
    Qnc = ca.vertcat(0, -p["D2"] * v[1])
    if tip:
        tip_pos = ca.vertcat(p["L1"] * ca.sin(q1) + p["L2"] * ca.sin(q1 + q2),
                             -p["L1"] * ca.cos(q1) - p["L2"] * ca.cos(q1 + q2))
        return Model.from_lagrangian(name, q, v, P, PARAMS, T=T, V=V, Q=Qnc, B=ca.DM.eye(2), h=tip_pos,
                                     derived=DERIVED, region=REGION_TIP, overrides=overrides,
                                     q_names=["q1", "q2"], u_names=["u1", "u2"], y_names=["x_tip", "y_tip"])
    return Model.from_lagrangian(name, q, v, P, PARAMS, T=T, V=V, Q=Qnc, B=ca.DM([[1], [0]]), h=q1,
                                 derived=DERIVED, region=REGION, overrides=overrides,
                                 q_names=["q1", "q2"], u_names=["u"], y_names=["q1"])


def build(**overrides: float) -> Model:
    """Minimal coordinates, colocated output y = q1 (minimum phase)."""
    return _minimal("two_link_arm", overrides)


def build_tip(**overrides: float) -> Model:
    """Fully actuated, tip-position output: relative degree undefined at sin(q2) = 0."""
    return _minimal("two_link_arm_tip", overrides, tip=True)


def build_redundant(**overrides: float) -> Model:
    """Redundant coordinates (th1, th2, xc, yc) with the joint as holonomic constraint (l = 2)."""
    P, p = _params()
    q, v = ca.SX.sym("q", 4), ca.SX.sym("v", 4)
    th1, th2, xc, yc = (q[i] for i in range(4))
    J1 = p["I1"] + p["m1"] * p["lc1"] ** 2
    M = ca.diag(ca.vertcat(J1, p["I2"], p["m2"], p["m2"]))
    rel, relv = th2 - th1, v[1] - v[0]
    spring = p["c2"] * rel + p["D2"] * relv
    f = ca.vertcat(-p["m1"] * p["g"] * p["lc1"] * ca.sin(th1) + spring, -spring, 0, -p["m2"] * p["g"])
    g = ca.vertcat(xc - p["L1"] * ca.sin(th1) - p["lc2"] * ca.sin(th2),
                   yc + p["L1"] * ca.cos(th1) + p["lc2"] * ca.cos(th2))
    return Model("two_link_arm_redundant", q, v, P, PARAMS, M=M, f=f, B=ca.DM([[1], [0], [0], [0]]), g=g, h=th1,
                 derived=DERIVED, region=REGION_REDUNDANT, overrides=overrides,
                 q_names=["th1", "th2", "xc", "yc"], u_names=["u"], y_names=["th1"])


def redundant_configuration(model: Model, q1: float, q2: float) -> np.ndarray:
    """Redundant coordinates of the minimal configuration (q1, q2)."""
    p = model.values
    th2 = q1 + q2
    return np.array([q1, th2, p["L1"] * math.sin(q1) + p["lc2"] * math.sin(th2),
                     -p["L1"] * math.cos(q1) - p["lc2"] * math.cos(th2)])


def zero_dynamics_equilibrium(model: Model, q1: float = 0.0) -> float:
    """q2* with c2 q2 + m2 g lc2 sin(q1 + q2) = 0 (link 2 at rest while q1 is held), by Newton."""
    p = model.values
    a = p["m2"] * p["g"] * p["lc2"]
    q2 = 0.0
    for _ in range(50):
        r = p["c2"] * q2 + a * math.sin(q1 + q2)
        q2 -= r / (p["c2"] + a * math.cos(q1 + q2))
        if abs(r) < 1e-15:
            break
    return q2


def zero_dynamics_eigenvalues(model: Model, q1: float = 0.0):
    """Closed form: eigenvalues of the zero dynamics J2 q2'' = -c2 q2 - D2 q2' - m2 g lc2 sin(q1 + q2)
    (q1 held) linearized at their equilibrium q2*."""
    p = model.values
    J2 = p["I2"] + p["m2"] * p["lc2"] ** 2
    q2 = zero_dynamics_equilibrium(model, q1)
    k = (p["c2"] + p["m2"] * p["g"] * p["lc2"] * math.cos(q1 + q2)) / J2
    return np.roots([1.0, p["D2"] / J2, k])


def reference(model: Model, *, y0: float = 0.0, yf: float = 0.5, t0: float = 0.0, tf: float = 1.0) -> Reference:
    """Joint 1 moved from y0 to yf with the C^4 timing law of 003 Sect. 6."""
    return rest_to_rest(y0, yf, t0, tf, smoothness=4, name="q1_ref")


def initial_configuration(model: Model) -> np.ndarray:
    return np.zeros(2)


def drawing(model: Model):
    """The two links hanging from the shoulder."""
    from invctl.plot.animate import Drawing

    q1, q2 = model.q[0], model.q[1]
    L1, L2 = model.params["L1"], model.params["L2"]
    elbow = ca.vertcat(L1 * ca.sin(q1), -L1 * ca.cos(q1))
    tip = elbow + ca.vertcat(L2 * ca.sin(q1 + q2), -L2 * ca.cos(q1 + q2))
    return Drawing(points={"shoulder": ca.vertcat(0, 0), "elbow": elbow, "tip": tip},
                   links=[("shoulder", "elbow"), ("elbow", "tip")])


def _check(v: dict) -> None:
    if v["c2"] < 0 or v["D2"] < 0:
        from invctl.errors import ParameterError

        raise ParameterError(f"two_link_arm: the elbow spring c2 and damper D2 must be >= 0, got c2 = {v['c2']}, "
                             f"D2 = {v['D2']}")


SCENE = Scene(
    "two_link_arm", build, params=PARAMS, positive=("m1", "m2", "L1", "L2", "lc1", "lc2", "I1", "I2", "g"),
    validate=_check,
    tracking=Tracking(reference=reference, plant={"m2": 1.2}, initial_configuration=initial_configuration),
    drawing=drawing,
    description="two-link arm with a passive elastic elbow, output = shoulder angle (colocated): minimum phase",
)
