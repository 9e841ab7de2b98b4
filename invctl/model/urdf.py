"""Models from robot descriptions (URDF): kinematic trees with revolute, continuous, prismatic and
fixed joints, as symbolic CasADi expressions.

:func:`read_urdf` parses the file (standard library XML, no document type declarations: no entity
expansion); :class:`Robot` builds the frames (rotation and position of every link in the world as
SX in ``q``) and the kinetic and potential energy; :meth:`Robot.model` turns them, with the joints
the user declares actuated and the springs and dampers of elastic joints, into an ordinary
:class:`~invctl.model.Model` (``M`` and ``f`` by recursive Newton-Euler, or from the Lagrangian).
:meth:`Robot.rigid_body_terms` gives ``M(q)``, the bias forces ``C(q, v) v + g(q)`` and the gravity ``g(q)`` alone, the quantities
an independent dynamics engine computes (``tests/test_urdf.py`` checks them against Pinocchio).

Conventions (the URDF specification's): a joint's frame is its child link's frame, placed by
``origin`` (``xyz``, then ``rpy`` = R_z(yaw) R_y(pitch) R_x(roll)) in the parent link's frame;
``axis`` is in the joint frame (default ``1 0 0``); gravity is ``-g`` along the world ``z``.  The
root link is fixed to the world.  Every link with a mass has the parameter ``m_<link>`` (its
mass; its inertia scales with it, a change of density), every moving joint ``d_<joint>`` (viscous
damping, default the URDF's ``dynamics damping``), every elastic joint ``k_<joint>`` (its spring,
about ``q = 0`` or the rest position ``r_<joint>``), and ``g``.
"""
from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Mapping, Sequence

import casadi as ca
import numpy as np

from ..errors import OptionError, ParameterError, URDFError, UnsupportedURDFError

SUPPORTED_JOINTS = ("revolute", "continuous", "prismatic", "fixed")
#: how :meth:`Robot.model` forms M and f: recursive Newton-Euler (default) or the Lagrangian differentiated by AD
DYNAMICS_METHODS = ("newton-euler", "lagrangian")
GRAVITY = 9.81


@dataclass(frozen=True)
class Joint:
    name: str
    type: str
    parent: str
    child: str
    xyz: tuple
    rpy: tuple
    axis: tuple
    lower: float = -math.inf
    upper: float = math.inf
    damping: float = 0.0


@dataclass(frozen=True)
class Link:
    name: str
    mass: float = 0.0
    com: tuple = (0.0, 0.0, 0.0)
    com_rpy: tuple = (0.0, 0.0, 0.0)
    inertia: tuple = ((0.0,) * 3,) * 3


@dataclass(frozen=True)
class Description:
    """A parsed URDF: links by name, joints in tree order (parents first), the root link."""

    name: str
    path: str
    links: Mapping[str, Link]
    joints: tuple
    root: str

    @property
    def moving(self) -> list:
        """The joints with a coordinate (all but fixed), in tree order: the order of ``q``."""
        return [j for j in self.joints if j.type != "fixed"]


# ------------------------------------------------------------------ parsing
def _numbers(el, attr: str, count: int, where: str, default=None) -> tuple:
    text = el.get(attr) if el is not None else None
    if text is None:
        if default is None:
            raise URDFError(f"{where}: attribute {attr!r} is missing")
        return tuple(default)
    try:
        vals = tuple(float(x) for x in text.split())
    except ValueError:
        raise URDFError(f"{where}: {attr}={text!r} is not {count} number(s)") from None
    if len(vals) != count or not all(math.isfinite(x) for x in vals):
        raise URDFError(f"{where}: {attr}={text!r} must be {count} finite number(s)")
    return vals


def _link(el, where: str) -> Link:
    name = el.get("name")
    inertial = el.find("inertial")
    if inertial is None:
        return Link(name)
    w = f"{where}, link {name!r} <inertial>"
    origin = inertial.find("origin")
    com = _numbers(origin, "xyz", 3, w + " <origin>", (0, 0, 0))
    com_rpy = _numbers(origin, "rpy", 3, w + " <origin>", (0, 0, 0))
    mass_el = inertial.find("mass")
    if mass_el is None:
        raise URDFError(f"{w}: <mass> is missing")
    (mass,) = _numbers(mass_el, "value", 1, w + " <mass>")
    i_el = inertial.find("inertia")
    keys = ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
    if i_el is None:
        raise URDFError(f"{w}: <inertia> is missing")
    ixx, ixy, ixz, iyy, iyz, izz = (_numbers(i_el, k, 1, w + " <inertia>")[0] for k in keys)
    inertia = ((ixx, ixy, ixz), (ixy, iyy, iyz), (ixz, iyz, izz))
    if mass < 0 or np.linalg.eigvalsh(np.array(inertia)).min() < -1e-12 * max(1.0, abs(ixx) + abs(iyy) + abs(izz)):
        raise URDFError(f"{w}: mass {mass} and inertia {inertia} are not physical (need mass >= 0 and a "
                        "positive semi-definite inertia)")
    return Link(name, mass, com, com_rpy, inertia)


def _joint(el, where: str, links) -> Joint:
    name, kind = el.get("name"), el.get("type")
    w = f"{where}, joint {name!r}"
    if kind in ("floating", "planar"):
        raise UnsupportedURDFError(f"{w}: <joint type={kind!r}> is not supported (a floating base or planar "
                                   f"joint); invctl models fixed-base trees with joints of type "
                                   f"{', '.join(SUPPORTED_JOINTS)}")
    if kind not in SUPPORTED_JOINTS:
        raise URDFError(f"{w}: unknown joint type {kind!r}; URDF joints are {', '.join(SUPPORTED_JOINTS)}, "
                        "floating, planar")
    if el.find("mimic") is not None:
        raise UnsupportedURDFError(f"{w}: <mimic joint={el.find('mimic').get('joint')!r}> is not supported (a "
                                   "coupled joint); remove the element to make the joint independent, or fix it")
    ends = {}
    for tag in ("parent", "child"):
        sub = el.find(tag)
        if sub is None or not sub.get("link"):
            raise URDFError(f"{w}: <{tag} link=...> is missing")
        if sub.get("link") not in links:
            raise URDFError(f"{w}: <{tag} link={sub.get('link')!r}> names no link of the file; links: "
                            f"{', '.join(sorted(links))}")
        ends[tag] = sub.get("link")
    origin = el.find("origin")
    xyz = _numbers(origin, "xyz", 3, w + " <origin>", (0, 0, 0))
    rpy = _numbers(origin, "rpy", 3, w + " <origin>", (0, 0, 0))
    axis = _numbers(el.find("axis"), "xyz", 3, w + " <axis>", (1, 0, 0))
    if kind != "fixed":
        norm = math.sqrt(sum(a * a for a in axis))
        if norm == 0:
            raise URDFError(f"{w}: <axis xyz='0 0 0'> has no direction")
        axis = tuple(a / norm for a in axis)
    lower, upper = -math.inf, math.inf
    limit = el.find("limit")
    if kind in ("revolute", "prismatic") and limit is not None:
        lo = _numbers(limit, "lower", 1, w + " <limit>", (0,))[0]
        hi = _numbers(limit, "upper", 1, w + " <limit>", (0,))[0]
        if lo < hi:  # lower = upper (both 0 in many files) declares no range
            lower, upper = lo, hi
    damping = _numbers(el.find("dynamics"), "damping", 1, w + " <dynamics>", (0,))[0]
    return Joint(name, kind, ends["parent"], ends["child"], xyz, rpy, axis, lower, upper, damping)


def read_urdf(path) -> Description:
    """Parse a URDF file into a :class:`Description` (a fixed-base kinematic tree).

    Raises :class:`~invctl.errors.URDFError` for a missing or malformed file and
    :class:`~invctl.errors.UnsupportedURDFError` for closed loops, mimic, floating and planar joints."""
    path = Path(path)
    if not path.is_file():
        raise URDFError(f"no URDF file {str(path)!r}" + (" (it is a directory)" if path.is_dir() else "")
                        + "; give the path of a .urdf file")
    text = path.read_text(encoding="utf-8", errors="replace")
    if re.search(r"<!(DOCTYPE|ENTITY)", text):
        raise URDFError(f"{path}: document type or entity declarations are not accepted in a URDF (nothing is "
                        "expanded); remove the <!DOCTYPE ...> block")
    if "xacro:" in text and re.search(r"<xacro:(macro|include|property)", text):
        raise URDFError(f"{path} is a xacro file, not a URDF; expand it first (xacro file.xacro > file.urdf)")
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise URDFError(f"{path} is not well-formed XML ({exc}); check the file at that line") from None
    if root.tag != "robot":
        raise URDFError(f"{path}: the root element is <{root.tag}>, a URDF's is <robot>")
    where = str(path)
    links: dict[str, Link] = {}
    for el in root.findall("link"):
        name = el.get("name")
        if not name:
            raise URDFError(f"{where}: a <link> has no name")
        if name in links:
            raise URDFError(f"{where}: link {name!r} is declared twice")
        links[name] = _link(el, where)
    if not links:
        raise URDFError(f"{where}: no <link> elements")
    for tag in ("loop_joint", "loop"):
        if root.find(tag) is not None:
            raise UnsupportedURDFError(f"{where}: <{tag}> (a closed kinematic loop) is not supported; invctl "
                                       "models kinematic trees (write loops as holonomic constraints, "
                                       "docs/write_your_own.md)")
    joints, names = [], set()
    for el in root.findall("joint"):
        if not el.get("name"):
            raise URDFError(f"{where}: a <joint> has no name")
        if el.get("name") in names:
            raise URDFError(f"{where}: joint {el.get('name')!r} is declared twice")
        names.add(el.get("name"))
        joints.append(_joint(el, where, links))
    parent_of: dict = {}
    for j in joints:
        if j.child in parent_of:
            raise UnsupportedURDFError(
                f"{where}: link {j.child!r} is the child of joints {parent_of[j.child].name!r} and {j.name!r}: "
                "a closed kinematic loop, which is not supported (invctl models kinematic trees)")
        parent_of[j.child] = j
    roots = [name for name in links if name not in parent_of]
    if len(roots) != 1:
        raise (UnsupportedURDFError if not roots else URDFError)(
            f"{where}: " + ("every link has a parent joint: a closed kinematic loop, which is not supported"
                            if not roots else
                            f"the links {roots} have no parent joint: the file describes {len(roots)} separate "
                            "trees; connect them with joints"))
    ordered, frontier = [], [roots[0]]
    children: dict = {}
    for j in joints:
        children.setdefault(j.parent, []).append(j)
    while frontier:
        link = frontier.pop(0)
        for j in children.get(link, []):
            ordered.append(j)
            frontier.append(j.child)
    if len(ordered) != len(joints):
        loop = sorted(j.name for j in joints if j not in ordered)
        raise UnsupportedURDFError(f"{where}: joints {loop} form a closed kinematic loop, which is not supported")
    return Description(root.get("name") or path.stem, str(path), links, tuple(ordered), roots[0])


# ------------------------------------------------------------------ kinematics
def _rpy(rpy) -> ca.DM:
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return ca.DM([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                  [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                  [-sp, cp * sr, cp * cr]])


def _axis_rotation(axis, angle) -> ca.SX:
    """Rodrigues' rotation about the unit ``axis`` by ``angle``."""
    K = ca.DM([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return ca.SX.eye(3) + ca.sin(angle) * K + (1 - ca.cos(angle)) * ca.mtimes(K, K)


def _param_name(prefix: str, name: str) -> str:
    return prefix + re.sub(r"\W", "_", name)


class Robot:
    """The symbolic kinematics and energies of a :class:`Description` (``q``: the moving joints in
    tree order, ``q_names``).

    ``position(frame, offset)`` and ``rotation(frame)`` are SX in ``q`` for any link ``frame``
    (output expressions); ``values`` are the defaults of the parameters (masses, dampers, ``g``)."""

    def __init__(self, description: Description):
        self.description = d = description
        self.joints = d.moving
        self.q_names = [j.name for j in self.joints]
        n = len(self.joints)
        self.q, self.v = ca.SX.sym("q", n), ca.SX.sym("v", n)
        index = {j.name: i for i, j in enumerate(self.joints)}
        moving_links = set()
        self._R, self._p, self._w = {d.root: ca.SX.eye(3)}, {d.root: ca.SX.zeros(3)}, {d.root: ca.SX.zeros(3)}
        for j in d.joints:  # parents first: world pose and body angular velocity of every link
            R0 = ca.mtimes(self._R[j.parent], _rpy(j.rpy))
            p = self._p[j.parent] + ca.mtimes(self._R[j.parent], ca.DM(j.xyz))
            w = ca.mtimes(_rpy(j.rpy).T, self._w[j.parent])  # in the child frame
            if j.type in ("revolute", "continuous"):
                i = index[j.name]
                Rj = _axis_rotation(j.axis, self.q[i])
                R = ca.mtimes(R0, Rj)
                w = ca.mtimes(Rj.T, w) + ca.DM(j.axis) * self.v[i]
            elif j.type == "prismatic":
                i = index[j.name]
                R, p = R0, p + ca.mtimes(R0, ca.DM(j.axis)) * self.q[i]
            else:
                R = R0
            if j.type != "fixed" or j.parent in moving_links:
                moving_links.add(j.child)
            self._R[j.child], self._p[j.child], self._w[j.child] = R, p, w
        # parameters: masses of the moving links that have one, dampers of every moving joint, g
        self.mass_links = [name for name in self._R if name in moving_links and d.links[name].mass > 0]
        self.values = {_param_name("m_", name): d.links[name].mass for name in self.mass_links}
        self.values.update({_param_name("d_", j.name): j.damping for j in self.joints})
        self.values["g"] = GRAVITY

    @property
    def n(self) -> int:
        return self.q.shape[0]

    def _frame(self, frame: str) -> str:
        if frame not in self._R:
            raise URDFError(f"{self.description.path}: no link (frame) {frame!r}; links: "
                            f"{', '.join(sorted(self._R))}")
        return frame

    def position(self, frame: str, offset=(0.0, 0.0, 0.0)) -> ca.SX:
        """World position of the point ``offset`` (in the frame of link ``frame``)."""
        f = self._frame(frame)
        return self._p[f] + ca.mtimes(self._R[f], ca.DM(offset))

    def rotation(self, frame: str) -> ca.SX:
        """World rotation matrix of link ``frame``'s frame."""
        return self._R[self._frame(frame)]

    def joint_index(self, name: str) -> int:
        """Index of joint ``name`` in ``q`` (a moving joint of the file)."""
        if name not in self.q_names:
            fixed = [j.name for j in self.description.joints if j.type == "fixed"]
            raise URDFError(f"{self.description.path}: no moving joint {name!r}"
                            + (" (it is a fixed joint)" if name in fixed else "")
                            + f"; moving joints: {', '.join(self.q_names)}")
        return self.q_names.index(name)

    def energies(self, P) -> tuple[ca.SX, ca.SX]:
        """Kinetic and gravitational potential energy with the masses and ``g`` of the parameters ``P``."""
        T, V = ca.SX(0), ca.SX(0)
        for name in self.mass_links:
            link = self.description.links[name]
            m = P[_param_name("m_", name)]
            Rc = _rpy(link.com_rpy)
            I = ca.mtimes([Rc, ca.DM(link.inertia), Rc.T]) * (m / link.mass)  # about the com, link frame
            pc = self.position(name, link.com)
            vc = ca.jtimes(pc, self.q, self.v)
            w = self._w[name]
            T = T + 0.5 * m * ca.dot(vc, vc) + 0.5 * ca.dot(w, ca.mtimes(I, w))
            V = V + m * P["g"] * pc[2]
        return T, V

    def newton_euler(self, P, a=None, *, velocity: bool = True, gravity: bool = True) -> ca.SX:
        """Joint forces ``tau = M(q) a + C(q, v) v + gravity(q)`` by the recursive Newton-Euler algorithm in the link
        frames (``a = None``: zero; ``velocity``/``gravity`` False drop those terms), with the masses and ``g`` of
        ``P``.  Expressions a few times smaller than the Lagrangian's, whose energy AD differentiates twice."""
        d = self.description
        index = {j.name: i for i, j in enumerate(self.joints)}
        a = ca.SX.zeros(self.n) if a is None else a
        v = self.v if velocity else ca.SX.zeros(self.n)
        zero = ca.SX.zeros(3)
        w, dw = {d.root: zero}, {d.root: zero}
        acc = {d.root: ca.vertcat(0, 0, P["g"]) if gravity else zero}    # the base accelerates up: gravity
        place = {}
        for j in d.joints:  # parents first: angular velocity, its rate, origin acceleration (link frames)
            R, off, s = ca.SX(_rpy(j.rpy)), ca.SX(ca.DM(j.xyz)), ca.DM(j.axis)
            if j.type == "prismatic":
                off = off + ca.mtimes(R, s) * self.q[index[j.name]]
            wp, dwp = w[j.parent], dw[j.parent]
            ao = acc[j.parent] + ca.cross(dwp, off) + ca.cross(wp, ca.cross(wp, off))
            if j.type in ("revolute", "continuous"):
                i = index[j.name]
                R = ca.mtimes(R, _axis_rotation(j.axis, self.q[i]))
                w0 = ca.mtimes(R.T, wp)
                w[j.child] = w0 + s * v[i]
                dw[j.child] = ca.mtimes(R.T, dwp) + s * a[i] + ca.cross(w0, s * v[i])
                acc[j.child] = ca.mtimes(R.T, ao)
            else:
                w[j.child], dw[j.child] = ca.mtimes(R.T, wp), ca.mtimes(R.T, dwp)
                acc[j.child] = ca.mtimes(R.T, ao)
                if j.type == "prismatic":
                    i = index[j.name]
                    acc[j.child] = acc[j.child] + 2 * ca.cross(w[j.child], s * v[i]) + s * a[i]
            place[j.child] = (R, off)
        force = {name: zero for name in self._R}
        moment = {name: zero for name in self._R}
        for name in self.mass_links:  # each link's own inertial force and moment about its origin
            link = d.links[name]
            m = P[_param_name("m_", name)]
            Rc, c = _rpy(link.com_rpy), ca.DM(link.com)
            I = ca.mtimes([Rc, ca.DM(link.inertia), Rc.T]) * (m / link.mass)
            wi, dwi = w[name], dw[name]
            F = m * (acc[name] + ca.cross(dwi, c) + ca.cross(wi, ca.cross(wi, c)))
            force[name] = F
            moment[name] = ca.mtimes(I, dwi) + ca.cross(wi, ca.mtimes(I, wi)) + ca.cross(c, F)
        tau = [ca.SX(0)] * self.n
        for j in reversed(d.joints):  # children first: accumulate into the parent
            f, n = force[j.child], moment[j.child]
            if j.name in index:
                s = ca.DM(j.axis)
                tau[index[j.name]] = ca.dot(s, f if j.type == "prismatic" else n)
            R, off = place[j.child]
            Rf = ca.mtimes(R, f)
            force[j.parent] = force[j.parent] + Rf
            moment[j.parent] = moment[j.parent] + ca.mtimes(R, n) + ca.cross(off, Rf)
        return ca.vertcat(*tau)

    def dynamics(self, P, method: str = "newton-euler") -> tuple[ca.SX, ca.SX]:
        """``(M(q), bias(q, v))`` with ``M v' + bias = tau``, ``bias = C(q, v) v + gravity(q)``: by Newton-Euler
        (``M`` column by column from the acceleration, which it is linear in) or from the Lagrangian."""
        if method == "newton-euler":
            a = ca.SX.sym("a", self.n)
            M = ca.jacobian(self.newton_euler(P, a, velocity=False, gravity=False), a)
            return M, self.newton_euler(P)
        if method == "lagrangian":
            T, V = self.energies(P)
            M, dTdv = ca.hessian(T, self.v)
            return M, ca.mtimes(ca.jacobian(dTdv, self.q), self.v) - ca.gradient(T, self.q) + ca.gradient(V, self.q)
        raise OptionError(f"dynamics={method!r}: use one of {list(DYNAMICS_METHODS)}")

    def rigid_body_terms(self, method: str = "newton-euler") -> ca.Function:
        """``(q, v) -> (M, bias, gravity)`` of the file's values, in the convention of rigid-body libraries:
        ``M(q) v' + bias(q, v) = tau``, ``bias = C(q, v) v + gravity(q)``."""
        from .params import ParamSet

        P = ParamSet(list(self.values))
        M, bias = self.dynamics(P, method)
        grav = self.newton_euler(P, velocity=False) if method == "newton-euler" else ca.gradient(self.energies(P)[1],
                                                                                                 self.q)
        th = ca.DM([self.values[k] for k in P.names])
        out = [ca.substitute(e, P.sym, th) for e in (M, bias, grav)]
        return ca.Function("rigid_body", [self.q, self.v], out, ["q", "v"], ["M", "bias", "gravity"])

    def region(self, limits: Mapping[str, tuple] | None = None, sample_span: float = math.pi):
        """The joint limits as the operating region; ``limits`` (joint -> (lower, upper)) replaces the
        URDF's for the joints it names (the range the user operates in).  Free joints (continuous, or
        revolute without a range) are sampled in ``[-sample_span, sample_span]``."""
        from .region import OperatingRegion

        limits = dict(limits or {})
        for name, pair in limits.items():
            self.joint_index(name)
            if len(pair) != 2 or not pair[0] < pair[1]:
                raise URDFError(f"limits[{name!r}] = {pair!r}: give (lower, upper) with lower < upper")
        lo = [float(limits.get(j.name, (j.lower, j.upper))[0]) for j in self.joints]
        hi = [float(limits.get(j.name, (j.lower, j.upper))[1]) for j in self.joints]
        slo = [a if math.isfinite(a) else -sample_span for a in lo]
        shi = [b if math.isfinite(b) else sample_span for b in hi]
        text = ", ".join(f"{j.name} in ({a:.4g}, {b:.4g})" for j, a, b in zip(self.joints, lo, hi)
                         if math.isfinite(a) or math.isfinite(b))
        return OperatingRegion(q_lower=lo, q_upper=hi, sample_bounds=(slo, shi), v_scale=1.0,
                               description=f"joint limits: {text or 'none'}")

    def parameters(self, springs: Mapping | None = None, dampers: Mapping | None = None) -> dict:
        """The parameter values of :meth:`model` with these ``springs`` and ``dampers``."""
        values = dict(self.values)
        for j, d in (dampers or {}).items():
            values[_param_name("d_", self.q_names[self.joint_index(j)])] = float(d)
        for j, k in (springs or {}).items():
            self.joint_index(j)
            k, r = (k, None) if np.ndim(k) == 0 else k
            values[_param_name("k_", j)] = float(k)
            if r is not None:
                values[_param_name("r_", j)] = float(r)
        return values

    def model(self, name: str, *, actuated: Sequence[str], output: Callable[["Robot"], ca.SX] | None = None,
              springs: Mapping[str, float] | None = None, dampers: Mapping[str, float] | None = None,
              limits: Mapping[str, tuple] | None = None, y_names: Sequence[str] | None = None,
              overrides: Mapping[str, float] | None = None, dynamics: str = "newton-euler", **kwargs):
        """An ordinary :class:`~invctl.model.Model`: ``M`` and ``f = -bias - d v - k (q - r)`` of the tree.

        Parameters
        ----------
        actuated : sequence of str
            The joints driven by an input (in input order); the other moving joints are passive.
        output : callable, optional
            ``output(robot) -> SX``: the output as an expression of :meth:`position`, :meth:`rotation`
            and ``robot.q`` (as many components as ``actuated``).
        springs : dict joint -> stiffness or (stiffness, rest position)
            Elastic joints: a spring ``-k (q - q_rest)`` on the joint (parameters ``k_<joint>`` and, when a
            rest position is given, ``r_<joint>``; default rest position 0).
        dampers : dict joint -> damping
            Viscous damping ``-d v`` on the joint (parameter ``d_<joint>``), replacing the URDF's value.
        limits : dict joint -> (lower, upper)
            The operating region's range of these joints, replacing the URDF's limits (:meth:`region`).
        overrides
            Parameter values (``m_<link>``, ``d_<joint>``, ``k_<joint>``, ``g``).
        dynamics : {"newton-euler", "lagrangian"}
            How ``M`` and the bias forces are formed (:meth:`dynamics`; the same terms, smaller expressions
            by Newton-Euler).
        """
        from .multibody import Model
        from .params import ParamSet

        if dynamics not in DYNAMICS_METHODS:
            raise OptionError(f"{name}: dynamics={dynamics!r}: use one of {list(DYNAMICS_METHODS)}")
        if self.n == 0:
            raise URDFError(f"{self.description.path}: every joint is fixed; a model needs a moving joint")
        springs, dampers = dict(springs or {}), dict(dampers or {})
        acts = [self.joint_index(j) for j in actuated]
        if len(set(acts)) != len(acts):
            raise URDFError(f"{name}: a joint is listed twice in actuated={list(actuated)}")
        values = self.parameters(springs, dampers)
        rest = {j: _param_name("r_", j) for j in springs if _param_name("r_", j) in values}
        P = ParamSet(list(values))
        M, bias = self.dynamics(P, dynamics)
        f = -bias
        for j in springs:
            i = self.joint_index(j)
            f[i] = f[i] - P[_param_name("k_", j)] * (self.q[i] - (P[rest[j]] if j in rest else 0))
        f = f - ca.vertcat(*[P[_param_name("d_", j.name)] * self.v[i] for i, j in enumerate(self.joints)])
        B = ca.DM.zeros(self.n, len(acts))
        for c, i in enumerate(acts):
            B[i, c] = 1
        h = output(self) if output is not None else None
        kwargs.setdefault("region", self.region(limits))
        return Model(name, self.q, self.v, P, values, M=M, f=f, B=B, h=h, overrides=overrides, q_names=self.q_names,
                     u_names=[f"u_{j}" for j in actuated], y_names=y_names, **kwargs)

    def drawing(self, model, view: str | Sequence = "xz", frames: Sequence[str] | None = None,
                tips: Mapping[str, tuple] | None = None):
        """A :class:`~invctl.plot.animate.Drawing` of the links: the origins of the link frames joined
        parent to child, projected on the plane ``view`` (``"xz"``, ``"yz"``, ``"xy"`` or a 2 x 3
        projection matrix); ``tips``: extra points ``name -> (frame, offset)`` joined to their frame."""
        from ..plot.animate import Drawing

        axes = {"x": 0, "y": 1, "z": 2}
        if isinstance(view, str):
            if len(view) != 2 or any(c not in axes for c in view):
                raise URDFError(f"drawing view {view!r}: give two of x, y, z (e.g. 'xz') or a 2 x 3 matrix")
            Pm = ca.DM.zeros(2, 3)
            Pm[0, axes[view[0]]], Pm[1, axes[view[1]]] = 1, 1
            labels = (f"world {view[0]} [m]", f"world {view[1]} [m]")
        else:
            Pm = ca.DM(np.asarray(view, float).reshape(2, 3))
            labels = ("horizontal of the view [m]", "vertical of the view [m]")
        # keep frames that move or carry the tree: origins of every link
        shown = list(frames) if frames is not None else list(self._R)
        sub = lambda e: ca.substitute(e, self.q, model.q)  # noqa: E731  (the model's own symbol)
        pts = {f: sub(ca.mtimes(Pm, self.position(f))) for f in shown}
        links = []
        for j in self.description.joints:
            if j.parent in pts and j.child in pts:
                links.append((j.parent, j.child))
        for tip, (frame, offset) in (tips or {}).items():
            pts[tip] = sub(ca.mtimes(Pm, self.position(frame, offset)))
            links.append((frame, tip))
        return Drawing(points=pts, links=links, axis_labels=labels)


def check_values(values: Mapping[str, float], where: str) -> None:
    """Reject negative dampers ``d_*``, springs ``k_*`` and gravity ``g`` (a scene's ``validate``)."""
    bad = {k: v for k, v in values.items() if (k.startswith(("d_", "k_")) or k == "g") and v < 0}
    if bad:
        raise ParameterError(f"{where}: dampers d_*, springs k_* and g must be >= 0, got {bad}")


def robot_from_urdf(path) -> Robot:
    """:func:`read_urdf` and the symbolic :class:`Robot` of it."""
    return Robot(read_urdf(path))
