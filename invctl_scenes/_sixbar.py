"""The six-bar of 000 Figs. 5(a), 6(a), 7(a) and Example 2, shared by the ``sixbar*`` scenes.

Five uniform bars B1..B5 in a single loop with the ground: ``ground -J1- B1 -J2- B2 -J3- B3 -J4- B4
-J5- B5 -J6- ground`` (revolute joints; 3 DoFs without clearance, ``q_wc = (theta_1, theta_2,
theta_3)`` as in 000 Example 2).  The figures carry no numbers; the geometry chosen here:

* ground pivots ``O1 = (0, 0)`` (J1) and ``O6 = (d, 0)`` (J6), ``d = 0.5`` m;
* bar lengths ``l1 = l2 = 0.3``, ``l3 = l4 = l5 = 0.25`` m, each bar of mass ``rho l`` with
  ``rho = 1.5`` kg/m and inertia ``m l^2 / 12`` about its middle;
* radial clearance ``c = 1 mm`` at every joint with clearance (bearing at the end of the lower-numbered
  bar, journal at the start of the next one; at J6 the bearing is in the ground), restitution ``e``;
* vertical plane, gravity ``g = 9.81`` along ``-y`` (``--set g=0``: horizontal plane);
* nominal pose: absolute bar angles ``theta_1, theta_2, theta_3 = 100, 20, -30`` degrees, B4 and B5
  closing the loop with the elbow J5 on the right (``B4`` at -22.6, ``B5`` at -135 degrees).

``CONFIGS`` lists the clearance configurations of the paper with their actuated joints.
"""
from __future__ import annotations

import math

import numpy as np

from invctl.contact.linkage import GROUND, Joint, Linkage, bar
from invctl.model import ParamSet

PARAMS = {"d": 0.5, "l1": 0.3, "l2": 0.3, "l3": 0.25, "l4": 0.25, "l5": 0.25, "rho": 1.5, "c": 1e-3, "e": 0.5,
          "g": 9.81}
MODEL_PARAMS = tuple(PARAMS)
#: nominal absolute angles of B1, B2, B3 (the clearance-free coordinates of Example 2)
NOMINAL_DEG = (100.0, 20.0, -30.0)

#: code -> (joints with clearance, actuated joints, description)
CONFIGS = {
    1: (("J3",), ("J1", "J2", "J4", "J5", "J6"),
        "000 Example 2, S1: clearance at J3 (actuators at J1, J2, J4, J5, J6 as in Sect. 6)"),
    2: (("J3", "J4"), ("J1", "J2", "J5", "J6"),
        "000 Example 2, S2 / Fig. 5(a): clearances at J3, J4 (actuators at J1, J2, J5, J6 as in Sect. 4)"),
    3: (("J2", "J4"), ("J1", "J3", "J5", "J6"),
        "000 Example 2, S3: clearances at J2, J4 (actuators at J1, J5, J6, and J3 as the only one of S2)"),
    4: (("J3", "J5"), ("J1", "J2", "J4", "J6"),
        "000 Fig. 6(a): clearances at J3, J5 (actuators at J1, J2, J4, J6 as in Sect. 4)"),
    7: (("J4", "J5", "J6"), ("J1", "J2", "J3"),
        "000 Fig. 7(a): clearances at J4, J5, J6 (actuators at J1, J2, J3 as in Sect. 5)"),
}
#: what 000 states for each configuration: n (open system), n_ind, DoFs of S1, S2, (S3)
PRINTED = {1: (5, 2, [2, 3]), 2: (7, 3, [2, 3, 2]), 3: (7, 3, [1, 4, 2]), 4: (7, 3, [2, 4, 1]),
           7: (9, 3, [3, 3, 3])}


def linkage(P: ParamSet, config: int) -> Linkage:
    """The six-bar with the clearances and actuators of ``CONFIGS[config]``."""
    clear, act, _ = CONFIGS[config]
    bodies = [bar(f"B{i}", P[f"l{i}"], P["rho"] * P[f"l{i}"]) for i in range(1, 6)]
    ends = [(GROUND, (0.0, 0.0), "B1", "start"), ("B1", "end", "B2", "start"), ("B2", "end", "B3", "start"),
            ("B3", "end", "B4", "start"), ("B4", "end", "B5", "start"), (GROUND, (P["d"], 0.0), "B5", "end")]
    joints = [Joint(f"J{k + 1}", "revolute", a, at_a, b, at_b, clearance=P["c"] if f"J{k + 1}" in clear else None,
                    restitution="e", actuated=f"J{k + 1}" in act)
              for k, (a, at_a, b, at_b) in enumerate(ends)]
    return Linkage(bodies, joints, gravity=P["g"])


def closed_poses(values: dict, angles_deg=NOMINAL_DEG) -> dict:
    """Poses ``body -> (x, y, phi)`` of the clearance-free six-bar with B1..B3 at ``angles_deg``
    (B4, B5 close the loop, elbow J5 on the right)."""
    th = [math.radians(a) for a in angles_deg]
    p, poses = np.zeros(2), {}
    for i, t in enumerate(th, start=1):
        poses[f"B{i}"] = (p[0], p[1], t)
        p = p + values[f"l{i}"] * np.array([math.cos(t), math.sin(t)])
    o6 = np.array([values["d"], 0.0])
    l4, l5 = values["l4"], values["l5"]
    dist = np.linalg.norm(o6 - p)
    if not abs(l4 - l5) < dist < l4 + l5:
        from invctl.errors import ParameterError

        raise ParameterError(f"six-bar: B4 and B5 (l4 = {l4}, l5 = {l5}) cannot close the loop from "
                             f"{np.round(p, 4).tolist()} to O6 = {o6.tolist()} (distance {dist:.4g})")
    u = (o6 - p) / dist
    a = (dist**2 + l4**2 - l5**2) / (2 * dist)
    h = math.sqrt(l4**2 - a**2)
    p4 = p + a * u + h * np.array([-u[1], u[0]])
    poses["B4"] = (p[0], p[1], math.atan2(*(p4 - p)[::-1]))
    poses["B5"] = (p4[0], p4[1], math.atan2(*(o6 - p4)[::-1]))
    return poses


def build(name: str, config: int, overrides: dict, *, angles_deg=NOMINAL_DEG):
    """The open six-bar of ``config`` with its nominal configuration in ``model.linkage.nominal``."""
    P = ParamSet(list(MODEL_PARAMS))
    link = linkage(P, config)
    ov = {k: v for k, v in overrides.items() if k in MODEL_PARAMS}
    model = link.build(name, P, PARAMS, overrides=ov)
    link.nominal = link.coordinates(closed_poses(model.values, angles_deg), P, model.theta_values)
    return model


def check(values: dict) -> None:
    from invctl.errors import ParameterError

    if not 0 <= values["e"] <= 1:
        raise ParameterError(f"six-bar: restitution e must lie in [0, 1], got {values['e']}")
    if values["g"] < 0:
        raise ParameterError(f"six-bar: gravity g must be >= 0 (it acts along -y), got {values['g']}")
    if values["c"] >= 0.1 * min(values[f"l{i}"] for i in range(1, 6)):
        raise ParameterError(f"six-bar: clearance c = {values['c']} should be small against the bars "
                             "(< 10 % of the shortest)")


def drawing(model):
    """Bars and ground pivots from the linkage, plus the ground line."""
    from invctl.plot.animate import Drawing

    points, links = model.linkage.drawing_parts(model)
    return Drawing(points=points, links=links,
                   segments=[((-0.1, 0.0), (float(model.values["d"]) + 0.1, 0.0))])
