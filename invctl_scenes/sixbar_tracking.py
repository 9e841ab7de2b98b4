"""Six-bar with a clearance at J3 under PD+ tracking (000 Fig. 5(a), Sect. 6, (47)-(56), Prop. 3).

Geometry in ``invctl_scenes/_sixbar.py``.  Open system (47): ``S1 = (B1, B2)``, ``q_1 = (theta_B1,
theta_J2)``; ``S2 = (B3, B4, B5)`` pinned to the ground at J6, ``q_2 = (theta_B5, theta_J5,
theta_J4)``; every joint but J3 is actuated (J1, J2, J4, J5, J6), so the open system is fully
actuated and PD+ (48) applies with ``V`` of (50).  One gap ``f_12`` (J3: bearing at the end of B2,
journal at the start of B3).

Desired trajectories: S1 and the relative angles of S2 at the nominal pose, S2 turned about J6 by

    theta_B5,d(t) = theta_c - alpha0 + A alpha0 (1 - exp(-t / tau)),

``alpha0 = 2 asin(c / (2 R))`` the turn that moves the journal (at distance ``R`` from J6) from the
bearing centre onto its wall.  The run starts on the desired trajectory with the journal on that
wall, S2 turning into it at ``w0`` rad/s (an initial velocity error: impacts follow):

* ``pdplus`` (``A = 1``): the desired journal moves from the wall towards the bearing centre, so
  ``grad f^T qd_dot > 0`` whenever the journal touches that wall: (52) and (54) hold at every impact
  and in persistent contact, and ``V`` (50) never increases (Prop. 3);
* ``pdplus_violating`` (``A = A_violating = 3``): the desired journal runs through the opposite wall
  (an infeasible trajectory); when the journal reaches that wall the desired velocity points out of
  the admissible domain: (52) fails at those impacts and (54) in the persistent contact that follows,
  and ``V`` increases there (51), (53).

The generic report checks (52) at every impact and (54) at every persistent-contact step.
"""
from __future__ import annotations

import math

import casadi as ca
import numpy as np

from invctl.contact.structure import subsystem_report
from invctl.scenes import Contact, Report, Scene
from invctl_scenes import _sixbar as sb

CONFIG = 1
SETTINGS = {"Kp": 20.0, "Kv": 2.0, "tau_d": 0.2, "A_violating": 3.0, "w0": 0.05,
            "h": 1e-5, "theta": 0.5, "t_end": 1.5, "projection": 0.0, "activation_tol": 1e-12}


def build(**overrides: float):
    """The open six-bar with a clearance at J3."""
    return sb.build("sixbar_tracking", CONFIG, overrides)


def wall_turn(model) -> tuple[float, int]:
    """``(alpha0, k)``: the turn of S2 about J6 that brings the journal from the bearing centre onto its
    wall, and the index of ``theta_B5`` in ``q``."""
    v = model.values
    poses = sb.closed_poses(v)
    x2, y2, _ = poses["B3"]
    R = math.hypot(x2 - v["d"], y2)
    return 2 * math.asin(v["c"] / (2 * R)), model.q_names.index("theta_B5")


def desired(model, s, amplitude: float):
    """``q_d(t)`` in the order of the actuated coordinates (the columns of ``B``), and that order."""
    from invctl.control.pdplus import selection_indices

    idx = selection_indices(model)
    alpha0, k = wall_turn(model)
    qc = model.linkage.nominal
    tau = s["tau_d"]

    def q_d(t):
        full = [ca.SX(x) for x in qc]
        full[k] = qc[k] - alpha0 + amplitude * alpha0 * (1 - ca.exp(-t / tau))
        return ca.vertcat(*[full[i] for i in idx])

    return q_d, idx


def _law(amplitude):
    def make(model, s):
        from invctl.control.pdplus import pd_plus_tracking

        A = s["A_violating"] if amplitude is None else amplitude
        q_d, idx = desired(model, s, A)
        return pd_plus_tracking(model, Kp=s["Kp"], Kv=s["Kv"], q_d=q_d, idx=idx)

    return make


def _initial(model, s, controller):
    alpha0, k = wall_turn(model)
    A = 1.0 if controller in ("pdplus", "none") else s["A_violating"]
    q0 = model.linkage.nominal.copy()
    q0[k] -= alpha0
    v0 = np.zeros(model.n)
    v0[k] = A * alpha0 / s["tau_d"] - s["w0"]
    return q0, v0


def _check(values):
    sb.check(values)
    from invctl.errors import ParameterError

    if values["A_violating"] <= 2:
        raise ParameterError(f"sixbar_tracking: A_violating = {values['A_violating']} must exceed 2 (the desired "
                             "journal must run past the opposite wall to violate (52)/(54))")


SCENE = Scene(
    "sixbar_tracking", build, params=dict(sb.PARAMS), settings=SETTINGS,
    positive=("d", "l1", "l2", "l3", "l4", "l5", "rho", "c", "Kp", "Kv", "tau_d", "h", "t_end"), validate=_check,
    contact=Contact(controllers={"pdplus": _law(1.0), "pdplus_violating": _law(None)}, initial_state=_initial),
    reports=(Report("000 Sect. 2: open system (Example 2, S1)", subsystem_report, command="analyze",
                    printed={"n (open system)": sb.PRINTED[CONFIG][0], "n_ind": sb.PRINTED[CONFIG][1],
                             "DoFs per subsystem": sb.PRINTED[CONFIG][2]}),),
    drawing=sb.drawing,
    description="six-bar with a clearance at J3 (000 Fig. 5(a), Sect. 6): PD+ (48), V (50), desired velocities "
                "that satisfy and that violate (52)/(54) (Prop. 3)",
)
