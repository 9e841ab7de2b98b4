"""Three cogwheels with backlash (000 Fig. 2(c), Example 4).

``q = (theta1, theta2, theta3)``, ``M = diag(J1, J2, J3)``, ``E = I_3``
(every wheel driven), four gaps (000 Example 4):

    f1 = -theta1 + theta2 + alpha1,   f2 = theta1 - theta2 + alpha2,
    f3 = -theta3 + theta2 + alpha3,   f4 = c4 theta3 - theta2 + alpha4.

The paper prints ``f4 = -theta3 - theta2 + alpha4`` (``c4 = -1``), but its
printed ``E_hat`` belongs to ``c4 = +1`` -- the other flank of the mesh whose
first flank is ``f3`` (``grad f4 = -grad f3``).  ``c4 = +1`` is the default;
``--set c4=-1`` reproduces the printed formula (see docs/reproduction.md).
Pre-loading keeps ``f1 = f4 = 0`` with multipliers ``beta``.
"""
from __future__ import annotations


import casadi as ca
import numpy as np

from invctl.model import Gap, Model, ParamSet
from invctl.scenes import Contact, Report, Scene

PARAMS = {
    "J1": 0.01, "J2": 0.01, "J3": 0.01,
    "alpha1": 0.01, "alpha2": 0.01, "alpha3": 0.01, "alpha4": 0.01, "e": 0.5, "c4": 1.0,
    "beta1": 1.0, "beta2": 1.0, "Kp": 2.0, "Kv": 0.5, "qd": 0.5,
    "h": 1e-4, "theta": 0.5, "t_end": 2.0, "activation_tol": 1e-12,
}
MODEL_PARAMS = ("J1", "J2", "J3", "alpha1", "alpha2", "alpha3", "alpha4", "e")

#: 000 Example 4, J1 = J2 = J3 = J
PRINTED_D_TIMES_J = np.array([[2.0, -1.0], [-1.0, 2.0]])
PRINTED_E_HAT = np.array([[-2.0, 1.0, 1.0], [-1.0, -1.0, 2.0]]) / 3.0


def _check(v: dict) -> None:
    from invctl.errors import ParameterError

    if v["c4"] not in (-1.0, 1.0):
        raise ParameterError(f"gear_backlash: c4 selects the f4 variant and must be +1 or -1, got {v['c4']}")
    if not 0 <= v["e"] <= 1:
        raise ParameterError(f"gear_backlash: restitution e must lie in [0, 1], got {v['e']}")
    # the gaps add angles of size 1 + |qd| rad: their round-off must stay below a millionth of each mesh's
    # backlash alpha1 + alpha2, alpha3 + alpha4
    S = 1.0 + abs(v["qd"])
    for a, b in (("alpha1", "alpha2"), ("alpha3", "alpha4")):
        if v[a] + v[b] < 1e-9 * S:
            raise ParameterError(f"gear_backlash: the backlash {a} + {b} = {v[a] + v[b]:.3g} rad is below 1e-9 of the "
                                 f"angles' size {S:.3g} rad: the gap expressions cannot resolve it; use a larger one")
    if not 0 <= v["theta"] <= 1:
        raise ParameterError(f"gear_backlash: theta of the theta-method must lie in [0, 1], got {v['theta']}")
    if v["activation_tol"] < 0:
        raise ParameterError(f"gear_backlash: activation_tol must be >= 0, got {v['activation_tol']}")
    for k in ("Kp", "Kv"):
        if v[k] < 0:
            raise ParameterError(f"gear_backlash: the gain {k} must be >= 0, got {v[k]}")


def build(**overrides: float) -> Model:
    """The gear train; ``c4`` selects the f4 variant (+1 mesh-consistent, -1 as printed)."""
    c4 = float(overrides.get("c4", PARAMS["c4"]))
    P = ParamSet(list(MODEL_PARAMS))
    q = ca.SX.sym("q", 3)
    v = ca.SX.sym("v", 3)
    a = [P[f"alpha{i}"] for i in range(1, 5)]
    gaps = [
        Gap("f1", -q[0] + q[1] + a[0], "e"),
        Gap("f2", q[0] - q[1] + a[1], "e"),
        Gap("f3", -q[2] + q[1] + a[2], "e"),
        Gap("f4", c4 * q[2] - q[1] + a[3], "e"),
    ]
    M = ca.diag(ca.vertcat(P["J1"], P["J2"], P["J3"]))
    ov = {k: v_ for k, v_ in overrides.items() if k in MODEL_PARAMS}
    return Model("gear_backlash", q, v, P, {k: PARAMS[k] for k in MODEL_PARAMS}, M=M, f=ca.SX.zeros(3),
                 B=ca.DM.eye(3), gaps=gaps, overrides=ov, q_names=["theta1", "theta2", "theta3"],
                 u_names=["tau1", "tau2", "tau3"])


def preloaded_configuration(model: Model, theta1: float = 0.0) -> np.ndarray:
    """A configuration with ``f1 = f4 = 0``."""
    p = model.values
    th2 = theta1 - p["alpha1"]
    c4 = float(np.array(ca.Function("c", [model.q, model.theta], [ca.jacobian(model.gaps[3].expr, model.q)])(
        np.zeros(3), model.theta_values))[0, 2])
    th3 = (th2 - p["alpha4"]) / c4
    return np.array([theta1, th2, th3])


def _preload(model, s):
    from invctl.control.preload import preload_law

    q0 = preloaded_configuration(model)
    return preload_law(model, [0, 3], beta=np.array([s["beta1"], s["beta2"]]), Kp=s["Kp"], Kv=s["Kv"],
                       y_d=q0 + s["qd"])


def example4_report(ctx) -> dict:
    """000 Example 4 (J1 = J2 = J3): E_hat and D at f1 = f4 = 0 for both f4 variants, and the printed
    persistent-contact conditions checked on random torques."""
    from invctl.contact.mechanics import ContactSystem
    from invctl.control.preload import preload_check
    from invctl.errors import SceneError

    p = {**PARAMS, **ctx.params}
    if not (p["J1"] == p["J2"] == p["J3"]):
        raise SceneError("the printed matrices of Example 4 assume J1 = J2 = J3; set equal inertias")
    J = p["J1"]
    out = {}
    for label, c4 in (("f4 as printed (c4 = -1)", -1.0), ("f4 = theta3 - theta2 + alpha4 (c4 = +1)", 1.0)):
        model = build(**{**ctx.params, "c4": c4})
        q = preloaded_configuration(model)
        out[f"E_hat, {label}"] = preload_check(model, q, np.zeros(3), [0, 3]).E_hat
        out[f"D J, {label}"] = ContactSystem(model).delassus(q, [0, 3]) * J
    n = int(ctx.settings.get("samples", 200))
    tau = np.random.default_rng(0).normal(size=(n, 3))
    lhs = np.all(tau @ PRINTED_E_HAT.T < 0, axis=1)
    rhs = (2 * tau[:, 0] > tau[:, 1] + tau[:, 2]) & (tau[:, 0] > -tau[:, 1] + 2 * tau[:, 2])
    out[f"printed conditions 2t1 > t2 + t3, t1 > -t2 + 2t3 <=> E_hat t < 0 ({n} samples)"] = bool(np.all(lhs == rhs))
    return out


SCENE = Scene(
    "gear_backlash", build, params={k: PARAMS[k] for k in (*MODEL_PARAMS, "c4")},
    settings={k: v for k, v in PARAMS.items() if k not in (*MODEL_PARAMS, "c4")},
    positive=("J1", "J2", "J3", "alpha1", "alpha2", "alpha3", "alpha4", "h", "t_end", "beta1", "beta2"),
    validate=_check,
    contact=Contact(controllers={"preload": _preload},
                    initial_state=lambda model, s, controller: (preloaded_configuration(model), np.zeros(3))),
    reports=(Report("000 Example 4 (pre-loading f1 = f4 = 0)", example4_report, command="analyze",
                    printed={"E_hat, f4 as printed (c4 = -1)": PRINTED_E_HAT,
                             "E_hat, f4 = theta3 - theta2 + alpha4 (c4 = +1)": PRINTED_E_HAT,
                             "D J, f4 as printed (c4 = -1)": PRINTED_D_TIMES_J,
                             "D J, f4 = theta3 - theta2 + alpha4 (c4 = +1)": PRINTED_D_TIMES_J}),),
    description="three cogwheels with backlash (000 Fig. 2(c), Example 4), pre-loading of f1 and f4",
)
