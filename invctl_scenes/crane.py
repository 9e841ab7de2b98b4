"""Overhead crane (gantry) with an elastic rope and a winch: a flat system, output = load position.

A trolley (mass mc, viscous rail friction b) runs on a horizontal rail at height H, driven by the
force F.  A winch on the trolley (drum inertia as an equivalent mass Jw on the rope) pays out the
rope, driven by the force u_w (drum torque over radius).  The load (point mass mL) hangs on the
rope, an elastic spring of stiffness k between the trolley and the load whose unstretched length
``ell`` is the winch coordinate.

    q = (x, ell, xL, yL),  u = (F, u_w),  y = h(q) = (xL, yL)  (the load position)

    T = mc x'^2/2 + Jw ell'^2/2 + mL (xL'^2 + yL'^2)/2,
    V = mL g yL + k (d - ell)^2/2,   d = |(xL - x, H - yL)|   (stretched rope length)

Why the rope is elastic
-----------------------
With an inextensible rope the load's acceleration perpendicular to the rope is ``-g sin(angle)``
whatever the inputs do, so the load position has no vector relative degree (the decoupling matrix
has rank 1; a dynamic extension would be needed), and with one input (fixed rope length) the
crane is, like the cart-pole, not flat at all (span{g, ad_f g, ad_f^2 g} is not involutive).
With the elastic rope the load position has the vector relative degree (4, 4) on the region where
the rope is taut and not horizontal, ``r_bar = 8 = 2n``: no internal dynamics, the load position is
a flat output, the inverse is algebraic in ``y_ref, ..., y_ref''''`` and needs no pre-actuation.
A rope damper is deliberately left out: a tension depending on velocities would let the inputs
reach the load's acceleration through one direction only (relative degree 3, singular Gamma).

Flatness closed form (Newton's laws, not the Lagrangian; :func:`flat_inverse`)
--------------------------------------------------------------------------------
rope force on the load ``f = mL (xL'', yL'' + g)``, tension ``T = |f|``, direction ``e = f / T``
(from the load to the trolley); trolley on the rail ``(x, H) = (xL, yL) + d e`` gives
``d = (H - yL) / e_y`` and ``x = xL + d e_x``; ``ell = d - T / k``;
``F = mc x'' + b x' + mL xL''`` (horizontal momentum) and ``u_w = Jw ell'' - T`` (winch).
"""
from __future__ import annotations

import math

import casadi as ca
import numpy as np

from invctl.model import Model, OperatingRegion, ParamSet, resolve_params
from invctl.reference import Reference, rest_to_rest
from invctl.scenes import Scene, Tracking

#: a laboratory gantry: 5 kg trolley, 1 kg load on a rope of ~1 m under a 1.5 m high rail; the rope
#: stretches 4.9 mm under the load (bounce mode sqrt(k/mL) = 44.7 rad/s), the pendulum mode is ~3 rad/s
PARAMS = {"mc": 5.0, "mL": 1.0, "Jw": 0.5, "k": 2000.0, "H": 1.5, "b": 2.0, "g": 9.81}

#: the load moves from y0 to yf (hall frame, metres): 1 m along the rail and 0.4 m up, in 3 s
Y0, YF = (0.0, 0.3), (1.0, 0.7)
T0_TRANSITION, TF_TRANSITION = 0.0, 3.0
#: rest-to-rest law of this smoothness: the inverse needs r_hat + 1 = 5 continuous derivatives
SMOOTHNESS = 5


def _region(values) -> OperatingRegion:
    """Rope taut (0 < stretch < 0.2 m), load below the rail, rope within 60 degrees of the vertical."""
    H = values["H"]

    def taut(q):
        d = math.hypot(q[2] - q[0], H - q[3])
        return (d - q[1]) * (0.2 - (d - q[1]))

    return OperatingRegion(
        q_lower=[-math.inf, 0.05, -math.inf, -math.inf], q_upper=[math.inf, math.inf, math.inf, H - 0.1],
        constraints=(taut, lambda q: math.sqrt(3.0) * (H - q[3]) - abs(q[2] - q[0])),
        sample_bounds=([-1.0, 0.05, -1.5, -0.5], [1.0, H + 0.5, 1.5, H - 0.1]), v_scale=1.0,
        description=f"rope taut (0 < d - ell < 0.2 m), load below the rail (yL < H - 0.1 = {H - 0.1:g} m), "
                    "rope within 60 degrees of the vertical")


def build(**overrides: float) -> Model:
    P = ParamSet(list(PARAMS))
    mc, mL, Jw, k, H, b, g = (P[n] for n in PARAMS)
    q, v = ca.SX.sym("q", 4), ca.SX.sym("v", 4)
    x, ell, xL, yL = (q[i] for i in range(4))
    d = ca.sqrt((xL - x) ** 2 + (H - yL) ** 2)
    T = 0.5 * mc * v[0] ** 2 + 0.5 * Jw * v[1] ** 2 + 0.5 * mL * (v[2] ** 2 + v[3] ** 2)
    V = mL * g * yL + 0.5 * k * (d - ell) ** 2
    values = resolve_params(PARAMS, None, overrides)
    return Model.from_lagrangian(
        "crane", q, v, P, PARAMS, T=T, V=V, Q=ca.vertcat(-b * v[0], 0, 0, 0),
        B=ca.DM([[1, 0], [0, 1], [0, 0], [0, 0]]), h=ca.vertcat(xL, yL), region=_region(values),
        overrides=overrides, q_names=["x", "ell", "xL", "yL"], u_names=["F", "u_w"], y_names=["xL", "yL"],
    )


def reference(model: Model, *, y0=Y0, yf=YF, t0: float = T0_TRANSITION, tf: float = TF_TRANSITION) -> Reference:
    """Load moved at rest from ``y0`` to ``yf`` (C^5 rest-to-rest polynomial of degree 11)."""
    H = model.values["H"]
    for name, p in (("y0", y0), ("yf", yf)):
        if not p[1] < H - 0.1:
            from invctl.errors import ReferenceSignalError

            raise ReferenceSignalError(f"crane: {name} = {tuple(p)} is not below the rail (yL < H - 0.1 = "
                                       f"{H - 0.1:g} m)")
    return rest_to_rest(y0, yf, t0, tf, smoothness=SMOOTHNESS, name="load_ref")


def rest_configuration(model: Model, y) -> np.ndarray:
    """The load hanging at rest at ``y``: trolley above it, rope stretched by ``mL g / k``."""
    p = model.values
    xL, yL = np.asarray(y, float).ravel()
    return np.array([xL, p["H"] - yL - p["mL"] * p["g"] / p["k"], xL, yL])


def initial_configuration(model: Model) -> np.ndarray:
    return rest_configuration(model, Y0)


def flat_inverse(model: Model, reference: Reference):
    """The flatness-based inverse in closed form (module doc): ``t -> (q, u)`` as CasADi Functions
    of time built from ``y_ref`` and its derivatives by Newton's laws alone."""
    p = model.values
    t = reference.t
    y = reference.expr
    d2 = ca.jacobian(ca.jacobian(y, t), t)
    f = p["mL"] * ca.vertcat(d2[0], d2[1] + p["g"])
    T = ca.norm_2(f)
    e = f / T
    d = (p["H"] - y[1]) / e[1]
    x = y[0] + d * e[0]
    ell = d - T / p["k"]
    dx, dell = ca.jacobian(x, t), ca.jacobian(ell, t)
    F = p["mc"] * ca.jacobian(dx, t) + p["b"] * dx + p["mL"] * d2[0]
    uw = p["Jw"] * ca.jacobian(dell, t) - T
    q = ca.vertcat(x, ell, y[0], y[1])
    return (ca.Function("crane_flat_q", [t], [q], ["t"], ["q"]),
            ca.Function("crane_flat_u", [t], [ca.vertcat(F, uw)], ["t"], ["u"]))


def drawing(model: Model):
    """Rail, trolley, rope and load."""
    from invctl.plot.animate import Drawing

    H = model.params["H"]
    x, xL, yL = model.q[0], model.q[2], model.q[3]
    Hv = model.values["H"]
    return Drawing(points={"trolley": ca.vertcat(x, H), "load": ca.vertcat(xL, yL)},
                   links=[("trolley", "load", {"linewidth": 1.0})],
                   segments=[((-0.5, Hv), (1.5, Hv)), ((-0.5, 0.0), (1.5, 0.0))])


SCENE = Scene(
    "crane", build, params=PARAMS, positive=("mc", "mL", "Jw", "k", "H", "g"),
    tracking=Tracking(reference=reference, plant={"mL": 1.2}, initial_configuration=initial_configuration,
                      units={"x": "m", "ell": "m", "xL": "m", "yL": "m", "F": "N", "u_w": "N"}),
    drawing=drawing,
    description="overhead crane with an elastic rope and a winch, output = load position: flat (vector relative "
                "degree (4, 4), no internal dynamics), so the inverse is algebraic and needs no pre-actuation; the "
                "simulated plant carries a 20 % heavier load",
)
