"""Two outputs, one of them held constant: a cart-pole beside a slider on a spring.

q = (x, theta, z): the cart, the pole angle from the upright vertical and a slider of mass ms tied
to the cart by a spring k; inputs (F, G) push the cart and the slider; y = (x, z).  The reference
moves the cart by 0.5 m and holds the slider at z = 0 (its derivatives are structural zeros).
"""
import casadi as ca

from invctl.model import Model, ParamSet
from invctl.reference import rest_to_rest
from invctl.scenes import Scene, Tracking

PARAMS = {"mc": 1.0, "mp": 0.2, "l": 0.5, "g": 9.81, "ms": 0.5, "k": 2.0}


def build(**overrides):
    P = ParamSet(list(PARAMS))
    mc, mp, l, g, ms, k = (P[n] for n in PARAMS)
    q, v = ca.SX.sym("q", 3), ca.SX.sym("v", 3)
    x, th, z = q[0], q[1], q[2]
    com_v = ca.vertcat(v[0] + l * ca.cos(th) * v[1], -l * ca.sin(th) * v[1])
    T = 0.5 * mc * v[0] ** 2 + 0.5 * mp * ca.sumsqr(com_v) + 0.5 * (mp * l**2 / 3) * v[1] ** 2 \
        + 0.5 * ms * v[2] ** 2
    V = mp * g * l * ca.cos(th) + 0.5 * k * (z - x) ** 2
    return Model.from_lagrangian("cart_pole_and_slider", q, v, P, PARAMS, T=T, V=V,
                                 B=ca.DM([[1, 0], [0, 0], [0, 1]]), h=ca.vertcat(x, z), overrides=overrides,
                                 q_names=["x", "theta", "z"], u_names=["F", "G"], y_names=["x", "z"])


def reference(model):
    return rest_to_rest([0.0, 0.0], [0.5, 0.0], t0=0.0, tf=2.0, smoothness=4)


SCENE = Scene("cart_pole_and_slider", build, params=PARAMS, positive=tuple(PARAMS),
              tracking=Tracking(reference=reference, plant={"mp": 1.2},
                                initial_configuration=lambda model: [0.0, 0.0, 0.0]),
              description="cart-pole and a slider on a spring; the reference holds the slider still")
