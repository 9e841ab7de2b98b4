"""Cart-pole with the cart position as output: a textbook non-minimum-phase system.

q = (x, theta): cart position and pole angle from the upright vertical; the
input is the horizontal force on the cart, the output the cart position.  The
output is colocated with the input (h' = B^T, 003 Sect. 2.3), so Gamma is the
positive scalar (M^-1)_11; the zero dynamics (cart held still) are the
inverted pendulum, unstable: eigenvalues +-sqrt(mp g l / (I + mp l^2)).

Closed form of the internal dynamics in the Lemma 3.1/3.2 coordinates
eta1 = theta, eta2 = p_theta / J (J = I + mp l^2, p_theta = mp l cos(theta) x' + J theta'):

    eta1' = eta2 - mp l cos(eta1) y' / J
    eta2' = (mp g l sin(eta1) - mp l sin(eta1) y' eta1' - D eta1') / J
"""
from __future__ import annotations

import math

import casadi as ca

from invctl.model import Model, OperatingRegion, ParamSet
from invctl.reference import Reference, poly9_timing_law
from invctl.scenes import Scene, Tracking

PARAMS = {"mc": 1.0, "mp": 0.2, "l": 0.5, "I": 0.2 * 0.5**2 / 3, "g": 9.81, "D": 0.0}
#: homogeneous pole of length 2 l (centre of mass at l)
DERIVED = {"I": lambda p: p["mp"] * p["l"] ** 2 / 3}

REGION = OperatingRegion(
    q_lower=[-math.inf, -math.pi / 2], q_upper=[math.inf, math.pi / 2],
    sample_bounds=([-2.0, -math.pi / 2], [2.0, math.pi / 2]), v_scale=2.0,
    description="x in R, |theta| < pi/2 (pole above the cart)",
)


def build(**overrides: float) -> Model:
    P = ParamSet(list(PARAMS))
    mc, mp, l, I, g, D = (P[k] for k in PARAMS)
    q, v = ca.SX.sym("q", 2), ca.SX.sym("v", 2)
    x, th = q[0], q[1]
    com_v = ca.vertcat(v[0] + l * ca.cos(th) * v[1], -l * ca.sin(th) * v[1])
    T = 0.5 * mc * v[0] ** 2 + 0.5 * mp * ca.sumsqr(com_v) + 0.5 * I * v[1] ** 2
    V = mp * g * l * ca.cos(th)
    return Model.from_lagrangian(
        "cartpole", q, v, P, PARAMS, T=T, V=V, Q=ca.vertcat(0, -D * v[1]), B=ca.DM([[1], [0]]), h=x,
        derived=DERIVED, region=REGION, overrides=overrides, q_names=["x", "theta"], u_names=["F"],
        y_names=["x"],
    )


def reference(model: Model, *, x0: float = 0.0, xf: float = 0.5, t0: float = 0.0, tf: float = 2.0) -> Reference:
    """Cart moved from x0 to xf with the C^4 timing law."""
    t = ca.SX.sym("t")
    return Reference(t, x0 + (xf - x0) * poly9_timing_law(t, t0, tf), t0, tf, smoothness=4, name="x_ref")


def zero_dynamics_eigenvalues(model: Model):
    """Closed form: eigenvalues of the linearized zero dynamics at the upright equilibrium."""
    p = model.values
    J = p["I"] + p["mp"] * p["l"] ** 2
    a, b = p["mp"] * p["g"] * p["l"] / J, p["D"] / J
    disc = math.sqrt(b * b / 4 + a)
    return (-b / 2 - disc, -b / 2 + disc)


def drawing(model: Model):
    """Cart (a point on the rail) and the pole of length 2 l."""
    from invctl.plot.animate import Drawing

    x, th = model.q[0], model.q[1]
    l = model.params["l"]
    return Drawing(points={"cart": ca.vertcat(x, 0), "tip": ca.vertcat(x + 2 * l * ca.sin(th), 2 * l * ca.cos(th))},
                   links=[("cart", "tip")], segments=[((-1.0, 0.0), (1.5, 0.0))])


def _check(v: dict) -> None:
    if v["D"] < 0:
        from invctl.errors import ParameterError

        raise ParameterError(f"cartpole: the pole damping D must be >= 0, got {v['D']}")


SCENE = Scene(
    "cartpole", build, params=PARAMS, positive=("mc", "mp", "l", "I", "g"), validate=_check,
    tracking=Tracking(reference=reference, plant={"mp": 1.2}, initial_configuration=lambda model: [0.0, 0.0],
                      units={"x": "m", "theta": "rad", "F": "N"}),
    drawing=drawing,
    description="cart-pole, output = cart position: non-minimum phase (the zero dynamics are the inverted "
                "pendulum); the simulated plant has a 20 % heavier pole",
)
