"""Planar linkages with joint clearances: the open system of 000 Sect. 2 from bodies and joints.

A :class:`Linkage` is a list of rigid bodies and joints.  A joint *without* clearance is ideal
(two bilateral constraints, 000 Sect. 2); a joint *with* clearance is opened and replaced by its
gap functions:

* revolute joint, radial clearance ``c`` (000 Fig. 1(b)): one gap
  ``f = (c^2 - |d|^2) / (2 c)``, ``d`` the offset of the journal (point on ``b``) from the bearing
  centre (point on ``a``); smooth, equal to ``c - |d|`` to first order at contact;
* prismatic joint, lateral clearance ``c`` (000 Fig. 1(a)): four gaps, the corners of a slider of
  half-length ``l`` and half-height ``w`` in a guide of half-height ``w + c``.

The bodies connected by ideal joints form the independent subsystems ``S_1 ... S_nind`` of the open
system; each gets tree coordinates: the angle of a body pinned to the ground (or the slide of a
body on a ground guide), else the centre-of-mass position and angle of a floating root body, then
one relative angle (or slide) per ideal joint down the tree.  The mass matrix is therefore
block-diagonal, one block per subsystem (000 Sect. 2), and the gap Jacobians have the block
pattern of 000 (3).  Closing the clearances gives the *closure* constraints (two per clearance
joint) of the clearance-free system (000 (6)), see :mod:`invctl.contact.reduction`.

Loops of ideal joints inside a subsystem are not supported (write the loop closure in closed form,
as ``invctl_scenes/fourbar_backlash.py`` does); actuators act on tree coordinates (positive: increases
the coordinate) or, at a joint with clearance, on the relative angle (slide) of its two bodies.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import casadi as ca
import numpy as np

from ..errors import ModelError
from ..model import Gap, Model
from .structure import components

#: name of the ground (body 0)
GROUND = "ground"


def _rot(phi):
    c, s = ca.cos(phi), ca.sin(phi)
    return ca.vertcat(ca.horzcat(c, -s), ca.horzcat(s, c))


def _vec(p) -> ca.SX:
    return ca.vertcat(ca.SX(p[0]), ca.SX(p[1]))


@dataclass(frozen=True)
class Body:
    """A rigid planar body.

    Parameters
    ----------
    name : str
    mass, inertia : float or casadi.SX
        Mass and moment of inertia about the centre of mass.
    points : dict
        Named points ``name -> (x, y)`` in the body frame (joint locations).
    com : (x, y)
        Centre of mass in the body frame.
    """

    name: str
    mass: Any
    inertia: Any
    points: Mapping[str, tuple]
    com: tuple = (0.0, 0.0)


def bar(name: str, length, mass, *, extra: Mapping[str, tuple] | None = None) -> Body:
    """A uniform bar along its x axis: points ``start = (0, 0)``, ``end = (length, 0)``, centre of
    mass at the middle, inertia ``mass length^2 / 12``."""
    pts = {"start": (0.0, 0.0), "end": (length, 0.0), **(extra or {})}
    return Body(name, mass, mass * length**2 / 12, pts, (0.5 * length, 0.0))


@dataclass(frozen=True)
class Joint:
    """A joint between body ``a`` (or the ground) and body ``b``.

    Parameters
    ----------
    name : str
        e.g. ``"J4"``.
    kind : {"revolute", "prismatic"}
    a, b : str
        Body names; ``a`` may be :data:`GROUND`.
    at_a : str or (x, y)
        Point of ``a`` (bearing centre; guide point); ground points are coordinates.
    at_b : str
        Point of ``b`` (journal centre; slider centre).
    clearance : float or SX, optional
        Radial (revolute) or lateral (prismatic) clearance; ``None``: ideal joint.
    axis : float or SX
        Prismatic: slide direction, angle in ``a``'s frame.
    slider : (half_length, half_height)
        Prismatic joint with clearance: slider dimensions (corners of 000 Fig. 1(a)).
    restitution : float or str
        Newton restitution of the gaps (a number or a model parameter name).
    actuated : bool
        An actuator acts on this joint.
    """

    name: str
    kind: str
    a: str
    at_a: Any
    b: str
    at_b: str
    clearance: Any = None
    axis: Any = 0.0
    slider: tuple = (0.0, 0.0)
    restitution: Any = 0.0
    actuated: bool = False

    @property
    def has_clearance(self) -> bool:
        return self.clearance is not None


@dataclass
class _Coordinate:
    name: str
    kind: str           # "angle" | "slide" | "x" | "y" | "phi"
    joint: str | None   # tree joint of angle/slide coordinates
    body: str           # body this coordinate places


@dataclass
class Subsystem:
    """One independent subsystem ``S_i`` of the open system."""

    name: str
    bodies: list
    coordinates: list = field(default_factory=list)   # indices into q
    grounded: bool = False                             # attached to the ground by an ideal joint


class Linkage:
    """A planar linkage with joint clearances (module docstring).

    Parameters
    ----------
    bodies : sequence of Body
    joints : sequence of Joint
    gravity : float or SX
        Gravitational acceleration along ``-y`` (0: horizontal plane).
    names : dict, optional
        Names for coordinates, ``default name -> name`` (defaults: ``theta_<body>`` for a body pinned
        to the ground, ``theta_<joint>`` / ``s_<joint>`` for relative angles / slides,
        ``x_<body>``, ``y_<body>``, ``phi_<body>`` for floating bodies).
    """

    def __init__(self, bodies: Sequence[Body], joints: Sequence[Joint], *, gravity=0.0,
                 names: Mapping[str, str] | None = None):
        self.bodies = {b.name: b for b in bodies}
        self.joints = list(joints)
        self.gravity = gravity
        problems = []
        if len(self.bodies) != len(bodies):
            problems.append("duplicate body names")
        if GROUND in self.bodies:
            problems.append(f"{GROUND!r} is the ground; do not declare it as a body")
        jn = [j.name for j in self.joints]
        if len(set(jn)) != len(jn):
            problems.append(f"duplicate joint names in {jn}")
        for j in self.joints:
            if j.kind not in ("revolute", "prismatic"):
                problems.append(f"joint {j.name}: kind must be 'revolute' or 'prismatic', got {j.kind!r}")
            for side, body, pt in (("a", j.a, j.at_a), ("b", j.b, j.at_b)):
                if body == GROUND:
                    if side == "b":
                        problems.append(f"joint {j.name}: put the ground on side a")
                    elif isinstance(pt, str) or len(pt) != 2:
                        problems.append(f"joint {j.name}: a ground point is given by its coordinates (x, y)")
                elif body not in self.bodies:
                    problems.append(f"joint {j.name}: unknown body {body!r}")
                elif pt not in self.bodies[body].points:
                    problems.append(f"joint {j.name}: body {body!r} has no point {pt!r} "
                                    f"(points: {sorted(self.bodies[body].points)})")
            if j.a == j.b:
                problems.append(f"joint {j.name} connects {j.a!r} to itself")
        if problems:
            raise ModelError("linkage is malformed:\n  - " + "\n  - ".join(problems))
        self._names = dict(names or {})
        self.nominal = None
        self._plan()

    # ------------------------------------------------------------ structure
    def _plan(self):
        """Subsystems (components of ideal joints), their roots and tree coordinates."""
        ideal = [j for j in self.joints if not j.has_clearance]
        comps = components(self.bodies, [(j.a, j.b) for j in ideal if j.a != GROUND])
        self.subsystems: list[Subsystem] = []
        self.coords: list[_Coordinate] = []
        self._tree: list[tuple] = []      # (joint, parent body or GROUND, child body, coordinate index or None)
        used = set()
        for k, members in enumerate(comps):
            sub = Subsystem(f"S{k + 1}", list(members))
            mset = set(members)
            ground_joints = [j for j in ideal if j.a == GROUND and j.b in mset]
            if len(ground_joints) > 1:
                raise ModelError(f"subsystem {members}: more than one ideal joint to the ground "
                                 f"({[j.name for j in ground_joints]}) closes a loop; the linkage builder needs "
                                 "tree-structured subsystems (write the loop closure in closed form)")
            placed = set()
            if ground_joints:
                j = ground_joints[0]
                sub.grounded = True
                kind = "angle" if j.kind == "revolute" else "slide"
                default = f"theta_{j.b}" if kind == "angle" else f"s_{j.name}"
                self._add(sub, default, kind, j.name, j.b)
                self._tree.append((j, GROUND, j.b, len(self.coords) - 1))
                used.add(j.name)
                placed.add(j.b)
            else:
                root = members[0]
                for kind in ("x", "y", "phi"):
                    self._add(sub, f"{kind}_{root}", kind, None, root)
                self._tree.append((None, None, root, None))
                placed.add(root)
            frontier = True
            while frontier:
                frontier = False
                for j in ideal:
                    if j.name in used or j.a == GROUND or not ({j.a, j.b} & placed) or not ({j.a, j.b} <= mset):
                        continue
                    if j.a in placed and j.b in placed:
                        raise ModelError(f"ideal joint {j.name} closes a loop in subsystem {members}; the linkage "
                                         "builder needs tree-structured subsystems (write the loop closure in "
                                         "closed form)")
                    par, child = (j.a, j.b) if j.a in placed else (j.b, j.a)
                    kind = "angle" if j.kind == "revolute" else "slide"
                    self._add(sub, f"theta_{j.name}" if kind == "angle" else f"s_{j.name}", kind, j.name, child)
                    self._tree.append((j, par, child, len(self.coords) - 1))
                    used.add(j.name)
                    placed.add(child)
                    frontier = True
            self.subsystems.append(sub)
        unknown = sorted(set(self._names) - {c.name for c in self.coords})
        if unknown:
            raise ModelError(f"linkage names: unknown coordinates {unknown}; coordinates: "
                             f"{[c.name for c in self.coords]}")
        self.clearance_joints = [j for j in self.joints if j.has_clearance]

    def _add(self, sub, name, kind, joint, body):
        sub.coordinates.append(len(self.coords))
        self.coords.append(_Coordinate(name, kind, joint, body))

    @property
    def n(self) -> int:
        """Coordinates of the open system (its DoFs: no ideal loops)."""
        return len(self.coords)

    @property
    def q_names(self) -> list[str]:
        return [self._names.get(c.name, c.name) for c in self.coords]

    def subsystem_of(self, body: str) -> int | None:
        """Index of the subsystem containing ``body`` (None for the ground)."""
        for k, s in enumerate(self.subsystems):
            if body in s.bodies:
                return k
        return None

    # ------------------------------------------------------------ kinematics
    def _poses(self, q):
        """Body poses ``name -> (r, phi)`` (frame origin, angle) as SX in ``q``."""
        poses = {}
        for j, par, child, k in self._tree:
            body = self.bodies[child]
            if j is None:                                   # floating root: centre of mass and angle
                i = self.subsystems[self.subsystem_of(child)].coordinates
                phi = q[i[2]]
                poses[child] = (ca.vertcat(q[i[0]], q[i[1]]) - ca.mtimes(_rot(phi), _vec(body.com)), phi)
                continue
            if par == GROUND:
                ra, pa = ca.SX.zeros(2, 1), ca.SX(0)
                Pa = _vec(j.at_a)
            else:
                ra, pa = poses[par]
                Pa = ra + ca.mtimes(_rot(pa), _vec(self.bodies[par].points[j.at_a if par == j.a else j.at_b]))
            pc_local = _vec(body.points[j.at_b if child == j.b else j.at_a])
            if j.kind == "revolute":
                phi = q[k] + (pa if par != GROUND else 0)
                poses[child] = (Pa - ca.mtimes(_rot(phi), pc_local), phi)
            else:
                # frames of a and b stay parallel; b's point slides along a's axis by s (joint's own sign)
                phi_a = pa if par != GROUND else ca.SX(0)
                u = ca.mtimes(_rot(phi_a + j.axis), ca.vertcat(1, 0))
                sign = 1 if child == j.b else -1
                poses[child] = (Pa + sign * q[k] * u - ca.mtimes(_rot(phi_a), pc_local), phi_a)
        return poses

    def point(self, poses, body: str, pt) -> ca.SX:
        """World position of point ``pt`` of ``body`` (ground points are coordinates)."""
        if body == GROUND:
            return _vec(pt)
        r, phi = poses[body]
        return r + ca.mtimes(_rot(phi), _vec(self.bodies[body].points[pt]))

    def _angle(self, poses, body):
        return ca.SX(0) if body == GROUND else poses[body][1]

    # ---------------------------------------------------------------- model
    def build(self, name: str, params, values: Mapping[str, float], *, overrides=None, validate: bool = True,
              u_names: Sequence[str] | None = None) -> Model:
        """The open system as a :class:`~invctl.model.Model` (Lagrangian, gaps, actuators).

        After the call, ``self.q``, ``self.poses`` (body -> (origin, angle) SX in ``self.q``),
        ``self.closure`` (the clearance-closing constraints, two per clearance joint),
        ``self.closure_names`` and ``self.gap_joint`` (gap index -> joint name) belong to that model;
        the model carries the linkage as ``model.linkage`` (read by
        :func:`invctl.contact.structure.open_structure`).  ``self.nominal`` (None until a scene sets it)
        is a configuration at which analyses evaluate the structure.
        """
        n = self.n
        q, v = ca.SX.sym("q", n), ca.SX.sym("v", n)
        poses = self._poses(q)
        T, U = 0, 0
        for b in self.bodies.values():
            r, phi = poses[b.name]
            com = r + ca.mtimes(_rot(phi), _vec(b.com))
            vc = ca.mtimes(ca.jacobian(com, q), v)
            om = ca.mtimes(ca.jacobian(phi, q), v)
            T = T + 0.5 * b.mass * ca.sumsqr(vc) + 0.5 * b.inertia * om**2
            U = U + b.mass * self.gravity * com[1]
        gaps, closure, cnames, gap_joint = [], [], [], []
        for j in self.clearance_joints:
            Pa, Pb = self.point(poses, j.a, j.at_a), self.point(poses, j.b, j.at_b)
            d = Pb - Pa
            if j.kind == "revolute":
                c = j.clearance
                gaps.append(Gap(j.name, (c**2 - ca.sumsqr(d)) / (2 * c), j.restitution))
                gap_joint.append(j.name)
                closure += [d[0], d[1]]
                cnames += [f"{j.name}.x", f"{j.name}.y"]
            else:
                half_l, half_w = j.slider
                ang = self._angle(poses, j.a) + j.axis
                nrm = ca.mtimes(_rot(ang), ca.vertcat(0, 1))
                rel = self._angle(poses, j.b) - self._angle(poses, j.a)
                eta = ca.dot(nrm, d)
                for sx, label in ((1, "front"), (-1, "back")):
                    top = ca.dot(nrm, ca.mtimes(_rot(ang + rel), ca.vertcat(sx * half_l, half_w)))
                    bot = ca.dot(nrm, ca.mtimes(_rot(ang + rel), ca.vertcat(sx * half_l, -half_w)))
                    gaps.append(Gap(f"{j.name}.{label}_top", half_w + j.clearance - eta - top, j.restitution))
                    gaps.append(Gap(f"{j.name}.{label}_bottom", half_w + j.clearance + eta + bot, j.restitution))
                    gap_joint += [j.name, j.name]
                closure += [eta, rel]
                cnames += [f"{j.name}.offset", f"{j.name}.angle"]
        cols, unames = [], []
        for j in self.joints:
            if not j.actuated:
                continue
            k = next((kk for jj, _, _, kk in self._tree if jj is j), None)
            if k is not None:
                col = ca.SX.zeros(n)
                col[k] = 1
            elif j.kind == "revolute":
                col = ca.gradient(self._angle(poses, j.b) - self._angle(poses, j.a), q)
            else:
                u = ca.mtimes(_rot(self._angle(poses, j.a) + j.axis), ca.vertcat(1, 0))
                col = ca.gradient(ca.dot(u, self.point(poses, j.b, j.at_b) - self.point(poses, j.a, j.at_a)), q)
            cols.append(col)
            unames.append(f"tau_{j.name}" if j.kind == "revolute" else f"F_{j.name}")
        B = ca.horzcat(*cols) if cols else ca.SX(n, 0)
        model = Model.from_lagrangian(name, q, v, params, values, T=T, V=U, B=B, gaps=gaps, overrides=overrides,
                                      q_names=self.q_names, u_names=list(u_names) if u_names else unames,
                                      validate=validate)
        self.q, self.poses = model.q, poses
        self.closure = ca.vertcat(*closure) if closure else ca.SX(0, 1)
        self.closure_names, self.gap_joint = cnames, gap_joint
        self.potential = U
        model.linkage = self  # type: ignore[attr-defined]  # the linkage a model was built from
        return model

    def potential_of(self, subsystems: Sequence[int]) -> ca.SX:
        """Gravity potential of the bodies of the given subsystems (SX in the built model's ``q``)."""
        U = 0
        for k in subsystems:
            for name in self.subsystems[k].bodies:
                b = self.bodies[name]
                r, phi = self.poses[name]
                U = U + b.mass * self.gravity * (r + ca.mtimes(_rot(phi), _vec(b.com)))[1]
        return ca.SX(U)

    def coordinates(self, poses: Mapping[str, tuple], params, theta_values) -> np.ndarray:
        """Open-system coordinates of numeric body poses ``name -> (x, y, phi)`` (frame origin and angle),
        e.g. of a configuration of the clearance-free mechanism; ``params``/``theta_values``: the
        model's :class:`~invctl.model.ParamSet` and parameter values."""
        entries: list = []
        for b in self.bodies.values():
            entries += [(("pt", b.name, k), p) for k, p in b.points.items()] + [(("pt", b.name, "__com__"), b.com)]
        for j in self.joints:
            if j.a == GROUND:
                entries.append((("ground", j.name), j.at_a))
            entries.append((("axis", j.name), (j.axis, 0.0)))
        ev = ca.Function("linkage_data", [params.sym], [ca.vertcat(*[_vec(p) for _, p in entries])])
        flat = np.array(ev(np.asarray(theta_values, float))).ravel()
        val = {key: flat[2 * i:2 * i + 2] for i, (key, _) in enumerate(entries)}

        def R(phi):
            return np.array([[np.cos(phi), -np.sin(phi)], [np.sin(phi), np.cos(phi)]])

        def world(j, side):
            body, pt = (j.a, j.at_a) if side == "a" else (j.b, j.at_b)
            if body == GROUND:
                return val[("ground", j.name)]
            x, y, phi = poses[body]
            return np.array([x, y]) + R(phi) @ val[("pt", body, pt)]

        missing = sorted(set(self.bodies) - set(poses))
        if missing:
            raise ModelError(f"linkage.coordinates: no pose for bodies {missing}")
        q = np.zeros(self.n)
        for j, par, child, k in self._tree:
            x, y, phi = poses[child]
            if j is None:
                k_sub = self.subsystem_of(child)
                assert k_sub is not None  # a tree's root body belongs to a subsystem
                i = self.subsystems[k_sub].coordinates[:3]
                q[i] = [*(np.array([x, y]) + R(phi) @ val[("pt", child, "__com__")]), phi]
            elif j.kind == "revolute":
                q[k] = phi - (0.0 if par == GROUND else poses[par][2])
            else:
                phi_a = 0.0 if j.a == GROUND else poses[j.a][2]
                u = R(phi_a + val[("axis", j.name)][0]) @ np.array([1.0, 0.0])
                q[k] = u @ (world(j, "b") - world(j, "a"))
        return q

    def drawing_parts(self, model: Model) -> tuple[dict, list]:
        """Points (``body.point`` and ``ground.<joint>``, SX in ``model.q``) and links (polylines through
        each body's points) for an :class:`invctl.plot.animate.Drawing` of the linkage."""
        poses = self._poses(model.q)
        pts, links = {}, []
        for b in self.bodies.values():
            names = list(b.points)
            for p in names:
                pts[f"{b.name}.{p}"] = self.point(poses, b.name, p)
            links += [(f"{b.name}.{a}", f"{b.name}.{c}") for a, c in zip(names[:-1], names[1:])]
        for j in self.joints:
            if j.a == GROUND:
                pts[f"ground.{j.name}"] = _vec(j.at_a)
        return pts, links
