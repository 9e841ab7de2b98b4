"""1-DOF manipulator against a stiff wall under switched motion/force control (002 Sect. 2, 4).

Plant 002 (1), Kelvin-Voigt wall (2) at x = 0 (contact for x > 0), switched
controller (3) and force-to-motion map (4).  Parameters of 002 Sect. 4:
M = 1 kg, b = 0, ke = 1e6 N/m, be = 10 Ns/m, Ma = 0.8 kg, kp = 4000 N/m,
kd = 80 Ns/m, kf = 1, bf = 5 Ns/m (Fig. 3; bf = 9000 for Fig. 4).

Reference (the paper does not print its profiles; these are our choice, see
docs/switched.md): approach the wall at v_app = 0.02 m/s crossing it at
t_c = 0.15 s, intended contact until t_b = 0.30 s with the force profile
F_max 16 s^2 (1 - s)^2 (F_max = 7 N, the maximum quoted for Fig. 3), then
retract to x_ret = -5 mm.  Gluing filters (31a), (A): gamma1 = 1000 rad/s,
gamma2 = 300 rad/s; the force filter starts when the filtered x_d reaches the
wall (glue_at_crossing = 1; 0 switches at t_c itself).  ke_hat, be_hat (4)
default to ke, be.
"""
from __future__ import annotations

from invctl.model.params import resolve_params
from invctl.scenes import Scene, Switched

PARAMS = {
    # plant and wall (002 Sect. 4)
    "M": 1.0, "b": 0.0, "ke": 1.0e6, "be": 10.0,
    # controller (3)
    "Ma": 0.8, "kp": 4000.0, "kd": 80.0, "kf": 1.0, "bf": 5.0,
    # force-to-motion map (4)
    "ke_hat": 1.0e6, "be_hat": 10.0,
    # reference scenario and gluing (App. A)
    "t_c": 0.15, "t_b": 0.30, "v_app": 0.02, "x_ret": -0.005, "overshoot": 0.02, "F_max": 7.0,
    "gamma1": 1000.0, "gamma2": 300.0, "glue_at_crossing": 1.0,
    # simulation
    "t_end": 0.5, "h_max": 2e-4,
}

DERIVED = {
    "ke_hat": lambda p: p["ke"],
    "be_hat": lambda p: p["be"],
}


def build(**overrides: float):
    """The scenario with parameters resolved (unknown names raise ParameterError)."""
    from invctl.studies.switched import SwitchedProblem

    return SwitchedProblem("stiff_wall", resolve_params(PARAMS, DERIVED, overrides))


def check(v: dict, name: str = "stiff_wall") -> None:
    """Physical signs and the order of the scenario's events (shared with the compliant wrist)."""
    from invctl.errors import ParameterError

    # (controller gains may be anything: the analysis reports unstable choices)
    for k in ("b", "be", "be_hat", "F_max", "overshoot", "bt"):
        if k in v and v[k] < 0:
            raise ParameterError(f"{name}: {k} (a damping, force or time) must be >= 0, got {v[k]}")
    if not 0 < v["t_c"] < v["t_b"]:
        raise ParameterError(f"{name}: the contact window needs 0 < t_c < t_b, got t_c = {v['t_c']}, t_b = {v['t_b']}")
    if not v["v_app"] > 0:
        raise ParameterError(f"{name}: the approach speed v_app must be positive, got {v['v_app']}")
    if not v["x_ret"] < 0:
        raise ParameterError(f"{name}: the retract position x_ret must be in free space (< 0), got {v['x_ret']}")
    for k in ("glue_at_crossing", "switch_on_tip"):
        if k in v and v[k] not in (0, 1):
            raise ParameterError(f"{name}: {k} is a switch, 0 or 1, got {v[k]}")


SCENE = Scene(
    "stiff_wall", build, params=PARAMS,
    positive=("M", "ke", "Ma", "ke_hat", "t_b", "gamma1", "gamma2", "t_end", "h_max"), validate=check,
    switched=Switched(),
    description="1-DOF manipulator against a stiff Kelvin-Voigt wall under switched motion/force control (002)",
)
