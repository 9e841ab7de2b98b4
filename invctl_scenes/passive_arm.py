"""Two-link arm with a passive elastic elbow and a non-colocated output (the end-effector angle).

The arm hangs in a vertical plane; joint 1 (shoulder) is driven by the torque u, joint 2
(elbow) is passive with a torsional spring c2 and damper D2 (a pendubot with an elastic
elbow).  Coordinates q = (q1, q2): shoulder angle from the downward vertical and elbow angle
relative to link 1.  The output is

    y = q1 + w q2,     w = L2 / (L1 + L2) by default,

the angle of the tip seen from the shoulder, linearized at the stretched arm (the tip is at
angle ``q1 + atan2(L2 sin q2, L1 + L2 cos q2) ~ q1 + w q2``).  ``w = 0`` is the colocated
output of ``two_link_arm`` (minimum phase), ``w = 1`` the absolute angle of the passive link.

Relative degree and zeros (closed form)
---------------------------------------
With ``b = I2 + m2 lc2^2`` and ``c0 = m2 L1 lc2`` the mass matrix has ``M22 = b`` and
``M21 = b + c0 cos q2``, and ``Gamma = [1 w] M^-1 e1 = (b - w (b + c0 cos q2)) / det M``.  Holding
``y = y*`` (``q1 = y* - w q2``) leaves the elbow equation

    (b - w (b + c0 cos q2)) q2'' + D2 q2' + c2 q2 + m2 g lc2 sin(q1 + q2) - c0 sin(q2) q1'^2 = 0,

the zero dynamics.  Linearized at an equilibrium (q1*, q2*) their eigenvalues, the
transmission zeros of the plant there, are the roots of

    alpha s^2 + D2 s + kappa,  alpha = b - w (b + c0 cos q2*),
                               kappa = c2 + (1 - w) m2 g lc2 cos(q1* + q2*).

For ``w > b / (b + c0)`` (= 0.348 with the default parameters) ``alpha < 0 < kappa`` at the
hanging arm: one real zero in each half plane, the output is non-minimum phase.  With the
defaults (w = 4/9) the zeros at q = 0 are +26.5/s and -13.0/s.  Gamma vanishes where
``cos q2 = b (1 - w) / (w c0)`` (|q2| = 0.84 rad with the defaults); the operating region
keeps |q2| 0.05 rad below that.  :func:`zero_polynomial` evaluates the closed form.
"""
from __future__ import annotations

import math

import casadi as ca
import numpy as np

from invctl.model import Model, OperatingRegion, ParamSet
from invctl.model.params import resolve_params
from invctl.reference import Reference, rest_to_rest
from invctl.scenes import Scene, Tracking

PARAMS = {
    "m1": 1.0, "m2": 0.5, "L1": 0.5, "L2": 0.4,
    "lc1": 0.25, "lc2": 0.2, "I1": 1.0 * 0.5**2 / 12, "I2": 0.5 * 0.4**2 / 12,
    "c2": 2.0, "D2": 0.1, "g": 9.81, "w": 0.4 / 0.9,
}
#: homogeneous links; the output weight follows the link lengths (linearized tip angle)
DERIVED = {
    "lc1": lambda p: p["L1"] / 2, "lc2": lambda p: p["L2"] / 2,
    "I1": lambda p: p["m1"] * p["L1"] ** 2 / 12, "I2": lambda p: p["m2"] * p["L2"] ** 2 / 12,
    "w": lambda p: p["L2"] / (p["L1"] + p["L2"]),
}
#: distance (rad) the operating region keeps from the elbow angle where Gamma vanishes
SINGULAR_MARGIN = 0.05


def singular_elbow_angle(values: dict) -> float:
    """``|q2|`` where Gamma = 0 (``cos q2 = b (1 - w) / (w c0)``), or ``inf`` if nowhere."""
    p = values
    b, c0, w = p["I2"] + p["m2"] * p["lc2"] ** 2, p["m2"] * p["L1"] * p["lc2"], p["w"]
    if w == 0:
        return math.inf
    ratio = b * (1 - w) / (w * c0)
    return math.acos(ratio) if -1 <= ratio <= 1 else math.inf


def _region(values: dict) -> OperatingRegion:
    qs = singular_elbow_angle(values)
    q2max = min(math.pi / 2, qs - SINGULAR_MARGIN)
    if not q2max > 0:
        q2max = math.pi / 2  # the output weight puts the singular point at the hanging arm: no region
    return OperatingRegion(
        q_lower=[-math.pi, -q2max], q_upper=[math.pi, q2max],
        sample_bounds=([-math.pi / 2, -q2max], [math.pi / 2, q2max]), v_scale=2.0,
        description=f"|q1| < pi, |q2| < {q2max:.3g} rad (Gamma = 0 at |q2| = {qs:.3g} rad)",
    )


def build(**overrides: float) -> Model:
    """Minimal coordinates (q1, q2), Lagrangian model, output y = q1 + w q2."""
    P = ParamSet(list(PARAMS))
    p = {k: P[k] for k in PARAMS}
    q, v = ca.SX.sym("q", 2), ca.SX.sym("v", 2)
    q1, q2 = q[0], q[1]
    r1 = ca.vertcat(p["lc1"] * ca.sin(q1), -p["lc1"] * ca.cos(q1))
    r2 = ca.vertcat(p["L1"] * ca.sin(q1) + p["lc2"] * ca.sin(q1 + q2),
                    -p["L1"] * ca.cos(q1) - p["lc2"] * ca.cos(q1 + q2))
    vel = lambda r: ca.mtimes(ca.jacobian(r, q), v)  # noqa: E731
    T = 0.5 * (p["m1"] * ca.sumsqr(vel(r1)) + p["I1"] * v[0] ** 2
               + p["m2"] * ca.sumsqr(vel(r2)) + p["I2"] * (v[0] + v[1]) ** 2)
    V = p["g"] * (p["m1"] * r1[1] + p["m2"] * r2[1]) + 0.5 * p["c2"] * q2**2
    values = resolve_params(PARAMS, DERIVED, overrides)
    return Model.from_lagrangian(
        "passive_arm", q, v, P, PARAMS, T=T, V=V, Q=ca.vertcat(0, -p["D2"] * v[1]), B=ca.DM([[1], [0]]),
        h=q1 + p["w"] * q2, derived=DERIVED, region=_region(values), overrides=overrides,
        q_names=["q1", "q2"], u_names=["u"], y_names=["tip_angle"])


def equilibrium(model: Model, y: float) -> tuple[float, float]:
    """``(q1*, q2*)`` at rest with ``q1 + w q2 = y``: the elbow balances spring and gravity,
    ``c2 q2 + m2 g lc2 sin(y + (1 - w) q2) = 0`` (Newton from q2 = 0)."""
    p = model.values
    a, w = p["m2"] * p["g"] * p["lc2"], p["w"]
    q2 = 0.0
    for _ in range(60):
        r = p["c2"] * q2 + a * math.sin(y + (1 - w) * q2)
        q2 -= r / (p["c2"] + a * (1 - w) * math.cos(y + (1 - w) * q2))
        if abs(r) < 1e-15:
            break
    return y - w * q2, q2


def zero_polynomial(model: Model, q1: float, q2: float) -> np.ndarray:
    """Coefficients ``[alpha, D2, kappa]`` of the zero polynomial at the equilibrium (q1, q2)."""
    p = model.values
    b, c0, w = p["I2"] + p["m2"] * p["lc2"] ** 2, p["m2"] * p["L1"] * p["lc2"], p["w"]
    return np.array([b - w * (b + c0 * math.cos(q2)), p["D2"],
                     p["c2"] + (1 - w) * p["m2"] * p["g"] * p["lc2"] * math.cos(q1 + q2)])


def zeros(model: Model, y: float = 0.0) -> np.ndarray:
    """Closed-form transmission zeros at the equilibrium with output ``y`` (sorted)."""
    return np.sort_complex(np.roots(zero_polynomial(model, *equilibrium(model, y))))


def reference(model: Model, *, y0: float = 0.0, yf: float = 0.3, t0: float = 0.0, tf: float = 1.0) -> Reference:
    """The tip angle moved from y0 to yf (rad) with the C^4 timing law of 003 Sect. 6."""
    return rest_to_rest(y0, yf, t0, tf, smoothness=4, name="tip_angle_ref")


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
    from invctl.errors import ParameterError

    if v["c2"] < 0 or v["D2"] < 0:
        raise ParameterError(f"passive_arm: the elbow spring c2 and damper D2 must be >= 0, got c2 = {v['c2']}, "
                             f"D2 = {v['D2']}")
    values = resolve_params(PARAMS, DERIVED, {k: v[k] for k in PARAMS if k in v and v[k] != PARAMS[k]})
    if singular_elbow_angle(values) <= SINGULAR_MARGIN:
        b = values["I2"] + values["m2"] * values["lc2"] ** 2
        c0 = values["m2"] * values["L1"] * values["lc2"]
        raise ParameterError(
            f"passive_arm: with w = {values['w']:.4g} the relative degree is lost at the hanging arm (Gamma = "
            f"b - w (b + c0 cos q2) = 0 near q2 = 0); choose w away from b / (b + c0) = {b / (b + c0):.4g}")


SCENE = Scene(
    "passive_arm", build, params=PARAMS, positive=("m1", "m2", "L1", "L2", "lc1", "lc2", "I1", "I2", "g"),
    validate=_check,
    tracking=Tracking(reference=reference, plant={"m2": 1.2}, initial_configuration=initial_configuration,
                      units={"q1": "rad", "q2": "rad", "tip_angle": "rad", "u": "N m"}),
    drawing=drawing,
    description="two-link arm with a passive elastic elbow, output = tip angle q1 + w q2 (non-colocated): "
                "non-minimum phase for w > b/(b + c0); the simulated plant's second link is 20 % heavier",
)
