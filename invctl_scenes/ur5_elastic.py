"""A UR5 from its robot description (``robots/ur5.urdf``, Universal Robots' published kinematic and inertial
data as shipped by ROS-Industrial and example-robot-data) with the elbow made passive and elastic: a
torsional spring of 200 N m/rad (rest position: the nominal pose's elbow angle) and a damper of 2 N m s/rad
replace the elbow motor, the five other joints are driven.

Outputs (five, one per input): the tool-frame position ``ee_link`` in the world (x, y, z in m) and the
angles of the two last wrist joints (rad).  The reference moves the tip 2 cm along the world x axis,
rest to rest, from the nominal pose ``Q_NOMINAL`` (upper arm 45 degrees up, elbow at 90 degrees), with the
wrist angles held.  Holding the tip still while the elbow swings is the flexible-arm problem: one real zero
in each half plane (about +17/s and -15/s), non-minimum phase like ``flexible_arm``.  Horizon, boundary
conditions and funnel design are automatic.

The operating region is the URDF's joint limits narrowed to 0.6 rad around the nominal pose (the tip
position loses its relative degree where the arm stretches or folds).
"""
from __future__ import annotations

import functools
import math
from pathlib import Path

import casadi as ca
import numpy as np

from invctl.model.urdf import check_values, robot_from_urdf
from invctl.reference import Reference, poly9_timing_law
from invctl.scenes import Scene, Tracking

URDF = Path(__file__).with_name("robots") / "ur5.urdf"
PASSIVE = "elbow_joint"
#: shoulder pan, shoulder lift, elbow, wrist 1-3 (rad)
Q_NOMINAL = (0.0, -math.pi / 4, math.pi / 2, 0.0, 0.0, 0.0)
SPRING, DAMPER = 200.0, 2.0
SPAN = 0.6  # rad around the nominal pose: the operating region
MOVE = (0.02, 0.0, 0.0, 0.0, 0.0)
#: the runs of ``invctl pipeline``
CONTROLLERS = ("C1", "C2", "C3", "C1-inv")


@functools.lru_cache(maxsize=1)
def robot():
    return robot_from_urdf(URDF)


def output(r) -> ca.SX:
    """Tool position (m) and the angles of wrist joints 2 and 3 (rad)."""
    return ca.vertcat(r.position("ee_link"), r.q[r.joint_index("wrist_2_joint")], r.q[r.joint_index("wrist_3_joint")])


def _limits():
    return {name: (q - SPAN, q + SPAN) for name, q in zip(robot().q_names, Q_NOMINAL)}


SPRINGS = {PASSIVE: (SPRING, Q_NOMINAL[2])}
DAMPERS = {PASSIVE: DAMPER}
PARAMS = robot().parameters(SPRINGS, DAMPERS)


def build(**overrides: float):
    r = robot()
    return r.model("ur5_elastic", actuated=[j for j in r.q_names if j != PASSIVE], output=output, springs=SPRINGS,
                   dampers=DAMPERS, limits=_limits(), y_names=["tip_x", "tip_y", "tip_z", "wrist_2", "wrist_3"],
                   overrides=overrides)


def reference(model, *, t0: float = 0.0, tf: float = 1.0) -> Reference:
    """The tip moved MOVE (m) from the nominal pose's output with the C^4 timing law of 003 Sect. 6."""
    t = ca.SX.sym("t")
    y0 = np.array(model.evaluate("h", Q_NOMINAL)).ravel()
    y = ca.DM(y0) + ca.DM(MOVE) * poly9_timing_law(t, t0, tf)
    return Reference(t, y, t0, tf, smoothness=4, name="tip_ref")


def initial_configuration(model) -> np.ndarray:
    return np.array(Q_NOMINAL)


def drawing(model):
    """The links from the URDF frames, seen from the side (the x-z plane)."""
    return robot().drawing(model, view="xz")


SCENE = Scene(
    "ur5_elastic", build, params=PARAMS, positive=tuple(k for k in PARAMS if k.startswith("m_")),
    validate=lambda values: check_values(values, "ur5_elastic"), tracking=Tracking(
        reference=reference, plant={"m_wrist_3_link": 1.2}, initial_configuration=initial_configuration,
        controllers=CONTROLLERS),
    drawing=drawing,
    description="UR5 (URDF) with a passive elastic elbow, five driven joints, output = tool position and two wrist "
                "angles: non-minimum phase (one real unstable zero); the simulated plant's last link is 20 % heavier",
)
