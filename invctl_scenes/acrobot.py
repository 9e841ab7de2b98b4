"""The acrobot from a robot description: example-robot-data's double pendulum (``robots/double_pendulum.urdf``,
two continuous joints about x, links along z, so the links swing in the y-z plane and ``q = 0`` is the
upright pendulum) with the shoulder ``joint1`` passive (its viscous damping 0.05 N m s/rad from the file)
and the elbow ``joint2`` driven.

Output: the horizontal position ``y`` of the tip of link 2, the point 0.2 m along its z axis (the
length of the link in the original meshes; the file gives no frame there).  At the hanging pendulum
(``q = (pi, 0)``) the zeros are a damped pair, -7.2 +- 4.7j /s: minimum phase.  (The pendubot, shoulder
driven and elbow passive, has one zero at +72/s with this output: docs/robots.md.)  Everything else
(horizon, boundary conditions, funnel gains) is automatic.

Nothing in this file is a model: masses, inertias and geometry are the URDF's (docs/robots.md).
"""
from __future__ import annotations

import functools
import math
from pathlib import Path

import casadi as ca
import numpy as np

from invctl.model.urdf import check_values, robot_from_urdf
from invctl.reference import Reference, rest_to_rest
from invctl.scenes import Scene, Tracking

URDF = Path(__file__).with_name("robots") / "double_pendulum.urdf"
TIP = ("link2", (0.0, 0.0, 0.2))
#: the operating region (the file's continuous joints have no limits): around the hanging pendulum (the
#: tip's relative degree is lost where the links fold or stretch sideways)
LIMITS = {"joint1": (math.pi - 0.4, math.pi + 0.4), "joint2": (-0.35, 0.35)}


@functools.lru_cache(maxsize=1)
def robot():
    return robot_from_urdf(URDF)


PARAMS = dict(robot().values)


def tip_y(r) -> ca.SX:
    """Horizontal (world y) position of the tip of link 2 (m)."""
    return r.position(*TIP)[1]


def build(**overrides: float):
    return robot().model("acrobot", actuated=["joint2"], output=tip_y, limits=LIMITS, y_names=["tip_y"],
                           overrides=overrides)


def reference(model, *, y0: float = 0.0, yf: float = 0.02, t0: float = 0.0, tf: float = 1.0) -> Reference:
    """The tip moved sideways from y0 to yf (m) with the C^4 timing law of 003 Sect. 6."""
    return rest_to_rest(y0, yf, t0, tf, smoothness=4, name="tip_y_ref")


def initial_configuration(model) -> np.ndarray:
    """The hanging pendulum."""
    return np.array([math.pi, 0.0])


def drawing(model):
    """The links from the URDF frames, seen along the joint axes (the y-z plane)."""
    return robot().drawing(model, view="yz", tips={"tip": TIP})


SCENE = Scene(
    "acrobot", build, params=PARAMS, positive=tuple(k for k in PARAMS if k.startswith("m_")),
    validate=lambda values: check_values(values, "acrobot"),
    tracking=Tracking(reference=reference, plant={"m_link2": 1.2}, initial_configuration=initial_configuration),
    drawing=drawing,
    description="acrobot from example-robot-data's double-pendulum URDF: shoulder passive, elbow driven, output = "
                "horizontal tip position (minimum phase); the simulated plant's second link is 20 % heavier",
)
