"""The kinematic chain of 000 Example 1 (Fig. 3): 14 bodies (the ground and 13 moving bodies), 11
revolute and 1 prismatic joints without clearance, clearances at the revolute joints J1, J9, J14 and
at the prismatic joint J16.

The figure carries no numbers; the chain chosen here (all bars uniform, ``rho = 1.5`` kg/m, inertia
``m l^2 / 12``):

* ``S1 = (B1..B7)``: a serial arm of seven 0.2 m bars pinned to the ground at ``O1 = (0, 0)`` (J2)
  and to each other (J3..J8); the tip of B7 is a journal in a ground bearing (J1, clearance);
* ``S2 = (B8..B11)``: B8 (0.25 m) pinned to the ground at ``O2`` (J10), B9 (0.2 m) sliding along B8
  (J11, the prismatic joint without clearance), B10 and B11 (0.2 m) pinned at J12, J13; the end of
  B11 is the bearing of J9 whose journal is the end of B4 (clearance);
* ``S3 = (B12, B13)``: a slider B12 (0.08 x 0.03 m, 0.3 kg) in a horizontal ground guide with lateral
  clearance (J16: four gaps, 000 Fig. 1(a)), B13 (0.25 m) pinned to it (J15); the end of B13 is the
  journal of J14 in a bearing at the middle of B10.

Nominal pose (clearances closed): S1's absolute angles 80, 60, 30, 0, -30, -100, -20 deg; B8 at 100 deg
with B9 out by 0.05 m, B10 at -20 deg, B11 at 60 deg; B13 at 70 deg.  The ground points ``Q1``,
``O2`` and the guide ``G16`` are placed so that this pose closes every clearance with the journals
centred.  Open system: ``n = 15`` (``S1``: 7, ``S2``: 4, ``S3``: 4), ``n_ind = 3``, ``m_u = 7``
(000: ``m_u = 4 n_pr + n_rev``); clearance-free: 7 DoFs.  Actuators at J2..J6, J10, J11 (``p = 7``,
the clearance-free chain is fully actuated: 000 Sect. 3).  Horizontal plane by default (``g = 0``).

The clearance-free model (000 (6)) is computed two ways: by :class:`invctl.contact.reduction.ClearanceFree`
from the open system and its closure constraints, with ``q_wc`` = the first five angles of S1 and
``(theta_B8, s_J11)``, and directly (:func:`direct_clearance_free`: the 7-DoF Lagrangian with the loops
closed in closed form).  000 writes ``M_wc = M_1 + dOmega/dz2^T blockdiag(M2, M3) dOmega/dz2`` assuming
``q_wc = q_1``, which Example 1 cannot satisfy (``f_10`` depends on ``q_1`` only, so closing J1
constrains S1 itself and S1 keeps 5 of its 7 DoFs); the general form used here is
``M_wc = sum_i J_i^T M_i J_i`` with ``J = dq/dq_wc`` (see docs/reproduction.md).

Controller ``pd``: PD (36) on the seven actuated coordinates to the nominal pose plus ``offset``.
"""
from __future__ import annotations

import math

import casadi as ca
import numpy as np

from invctl.contact.linkage import GROUND, Body, Joint, Linkage, bar
from invctl.contact.structure import subsystem_report
from invctl.model import Model, ParamSet
from invctl.scenes import Contact, Report, Scene

PARAMS = {"rho": 1.5, "m12": 0.3, "c": 1e-3, "e": 0.5, "g": 0.0}
MODEL_PARAMS = tuple(PARAMS)
SETTINGS = {"Kp": 5.0, "Kv": 0.5, "offset": 0.01, "h": 1e-4, "theta": 0.5, "t_end": 2.0, "projection": 0.0,
            "activation_tol": 1e-12}

L = {**{f"B{i}": 0.2 for i in range(1, 8)}, "B8": 0.25, "B9": 0.2, "B10": 0.2, "B11": 0.2, "B13": 0.25}
SLIDER = (0.04, 0.015)                 # half-length, half-height of B12
ARM_DEG = (80.0, 60.0, 30.0, 0.0, -30.0, -100.0, -20.0)
S2_DEG, S2_SLIDE, B10_DEG, B11_DEG, B13_DEG = 100.0, 0.05, -20.0, 60.0, 70.0
#: q_wc: theta_B1, theta_J3..theta_J6 (S1), theta_B8, s_J11 (S2)
INDEPENDENT = [0, 1, 2, 3, 4, 7, 8]


def _u(deg):
    return np.array([math.cos(math.radians(deg)), math.sin(math.radians(deg))])


def nominal_poses() -> dict:
    """Poses ``body -> (x, y, phi)`` (bar start / slider centre, angle) of the closed nominal pose."""
    poses, p = {}, np.zeros(2)
    for i, a in enumerate(ARM_DEG, start=1):
        poses[f"B{i}"] = (*p, math.radians(a))
        p = p + L[f"B{i}"] * _u(a)
    p4 = sum(L[f"B{i}"] * _u(ARM_DEG[i - 1]) for i in range(1, 5))
    p10 = p4 - L["B11"] * _u(B11_DEG)                 # B11 ends at the J9 journal
    p9 = p10 - L["B10"] * _u(B10_DEG)
    o2 = p9 - (S2_SLIDE + L["B9"]) * _u(S2_DEG)
    poses["B8"] = (*o2, math.radians(S2_DEG))
    poses["B9"] = (*(o2 + S2_SLIDE * _u(S2_DEG)), math.radians(S2_DEG))
    poses["B10"] = (*p9, math.radians(B10_DEG))
    poses["B11"] = (*p10, math.radians(B11_DEG))
    p14 = p9 + 0.5 * L["B10"] * _u(B10_DEG)
    g16 = p14 - L["B13"] * _u(B13_DEG)
    poses["B12"] = (*g16, 0.0)
    poses["B13"] = (*g16, math.radians(B13_DEG))
    return poses


_P = nominal_poses()
Q1 = tuple(np.array(_P["B7"][:2]) + L["B7"] * _u(ARM_DEG[6]))
O2 = tuple(_P["B8"][:2])
G16 = tuple(_P["B12"][:2])


def linkage(P: ParamSet) -> Linkage:
    """The open chain of Example 1 (module docstring)."""
    bodies = [bar(name, length, P["rho"] * length) for name, length in L.items() if name != "B10"]
    bodies.insert(9, bar("B10", L["B10"], P["rho"] * L["B10"], extra={"mid": (0.5 * L["B10"], 0.0)}))
    a, b = SLIDER
    bodies.insert(11, Body("B12", P["m12"], P["m12"] * ((2 * a) ** 2 + (2 * b) ** 2) / 12, {"center": (0.0, 0.0)}))
    R = dict(restitution="e")
    joints = [Joint("J1", "revolute", GROUND, Q1, "B7", "end", clearance=P["c"], **R),
              Joint("J2", "revolute", GROUND, (0.0, 0.0), "B1", "start", actuated=True)]
    joints += [Joint(f"J{k + 2}", "revolute", f"B{k}", "end", f"B{k + 1}", "start", actuated=k <= 4)
               for k in range(1, 7)]
    joints += [Joint("J9", "revolute", "B11", "end", "B4", "end", clearance=P["c"], **R),
               Joint("J10", "revolute", GROUND, O2, "B8", "start", actuated=True),
               Joint("J11", "prismatic", "B8", "start", "B9", "start", actuated=True),
               Joint("J12", "revolute", "B9", "end", "B10", "start"),
               Joint("J13", "revolute", "B10", "end", "B11", "start"),
               Joint("J14", "revolute", "B10", "mid", "B13", "end", clearance=P["c"], **R),
               Joint("J15", "revolute", "B12", "center", "B13", "start"),
               Joint("J16", "prismatic", GROUND, G16, "B12", "center", clearance=P["c"], slider=SLIDER, **R)]
    return Linkage(bodies, joints, gravity=P["g"])


def build(**overrides: float) -> Model:
    """The open system (n = 15) with its nominal pose in ``model.linkage.nominal``."""
    P = ParamSet(list(MODEL_PARAMS))
    link = linkage(P)
    model = link.build("chain14", P, PARAMS, overrides={k: v for k, v in overrides.items() if k in MODEL_PARAMS})
    link.nominal = link.coordinates(nominal_poses(), P, model.theta_values)
    return model


def _two_link(p0, p1, l0, l1, sign):
    """Elbow of two bars of lengths ``l0``, ``l1`` from ``p0`` to ``p1`` (SX), ``sign`` picks the branch."""
    d = p1 - p0
    D = ca.norm_2(d)
    a = (D**2 + l0**2 - l1**2) / (2 * D)
    h = ca.sqrt(l0**2 - a**2)
    return p0 + a * d / D + sign * h * ca.vertcat(-d[1], d[0]) / D


def _branch(p0, p1, elbow) -> float:
    d, e = np.asarray(p1) - np.asarray(p0), np.asarray(elbow) - np.asarray(p0)
    return float(np.sign(d[0] * e[1] - d[1] * e[0]))


def direct_clearance_free(**overrides: float) -> Model:
    """The clearance-free chain (000 (6)) built directly in ``q_wc`` (7 DoFs), its loops closed in closed
    form: B6, B7 reach the J1 bearing, B10, B11 reach the end of B4, the slider stays on the guide axis."""
    P = ParamSet(list(MODEL_PARAMS))
    q, v = ca.SX.sym("q_wc", 7), ca.SX.sym("v_wc", 7)
    u = lambda phi: ca.vertcat(ca.cos(phi), ca.sin(phi))  # noqa: E731
    ang = lambda p: ca.atan2(p[1], p[0])  # noqa: E731
    bodies = {}
    p, phi = ca.SX.zeros(2), 0
    for i in range(5):
        phi = phi + q[i]
        bodies[f"B{i + 1}"] = (p, phi)
        p = p + L[f"B{i + 1}"] * u(phi)
    p4 = bodies["B4"][0] + L["B4"] * u(bodies["B4"][1])
    q1 = ca.vertcat(*Q1)
    nom = nominal_poses()
    p6 = _two_link(p, q1, L["B6"], L["B7"], _branch(nom["B6"][:2], Q1, nom["B7"][:2]))
    bodies["B6"], bodies["B7"] = (p, ang(p6 - p)), (p6, ang(q1 - p6))
    o2 = ca.vertcat(*O2)
    bodies["B8"] = (o2, q[5])
    bodies["B9"] = (o2 + q[6] * u(q[5]), q[5])
    p9 = o2 + (q[6] + L["B9"]) * u(q[5])
    p4n = np.array(nom["B4"][:2]) + L["B4"] * _u(ARM_DEG[3])
    p10 = _two_link(p9, p4, L["B10"], L["B11"], _branch(nom["B10"][:2], p4n, nom["B11"][:2]))
    bodies["B10"], bodies["B11"] = (p9, ang(p10 - p9)), (p10, ang(p4 - p10))
    p14 = p9 + 0.5 * L["B10"] * u(bodies["B10"][1])
    x12 = p14[0] - ca.sqrt(L["B13"] ** 2 - (p14[1] - G16[1]) ** 2)
    c12 = ca.vertcat(x12, G16[1])
    bodies["B12"], bodies["B13"] = (c12, ca.SX(0)), (c12, ang(p14 - c12))
    T, U = 0, 0
    for name, (r, phi) in bodies.items():
        if name == "B12":
            m, I, com = P["m12"], P["m12"] * ((2 * SLIDER[0]) ** 2 + (2 * SLIDER[1]) ** 2) / 12, r
        else:
            m, I, com = P["rho"] * L[name], P["rho"] * L[name] ** 3 / 12, r + 0.5 * L[name] * u(phi)
        vc = ca.mtimes(ca.jacobian(com, q), v)
        om = ca.mtimes(ca.jacobian(phi, q), v)
        T = T + 0.5 * m * ca.sumsqr(vc) + 0.5 * I * om**2
        U = U + m * P["g"] * com[1]
    # validate=False: the closed-form loops exist near the nominal pose only, not at random q in [-1, 1]^7
    return Model.from_lagrangian("chain14_clearance_free", q, v, P, PARAMS, T=T, V=U, B=ca.DM.eye(7), validate=False,
                                 overrides={k: x for k, x in overrides.items() if k in MODEL_PARAMS})


def clearance_free_report(ctx) -> dict:
    """000 Sect. 2.2: the clearance-free model from the open system (``ClearanceFree``) against the model
    built directly, at the nominal pose and at 5 random ``q_wc`` around it; the block sum; Assumption 1."""
    from invctl.contact.reduction import ClearanceFree

    model = ctx.model
    link = model.linkage
    cf = ClearanceFree(model, link.closure, INDEPENDENT)
    direct = direct_clearance_free(**ctx.params)
    rng = np.random.default_rng(0)
    qn = link.nominal
    dM = dF = dE = dB = 0.0
    for k in range(6):
        qwc = qn[INDEPENDENT] + (0 if k == 0 else rng.uniform(-0.02, 0.02, 7))
        qfull = cf.configuration(qwc, qn)
        vwc = rng.normal(size=7)
        Md = direct.evaluate("M", qwc)
        Mw = cf.mass_matrix(qfull)
        scale = np.abs(Md).max()
        dM = max(dM, np.abs(Mw - Md).max() / scale)
        blocks = sum(cf.blocks(qfull, [s.coordinates for s in link.subsystems]))
        dB = max(dB, np.abs(blocks - Mw).max() / scale)
        fd = direct.evaluate("f", qwc, vwc).ravel()
        dF = max(dF, np.abs(cf.forces(qfull, vwc) - fd).max() / max(1e-12, np.abs(fd).max()))
        dE = max(dE, np.abs(cf.input_matrix(qfull) - np.eye(7)).max())
    a1 = cf.assumption1(qn)
    M1 = model.evaluate("M", qn)[np.ix_(link.subsystems[0].coordinates, link.subsystems[0].coordinates)]
    return {"M_wc: reduction vs direct (max relative difference, 6 poses)": dM,
            "M_wc = sum_i J_i^T M_i J_i (max relative difference)": dB,
            "f_wc (Coriolis, centrifugal, gravity): reduction vs direct": dF,
            "E_wc - I (actuators J2..J6, J10, J11)": dE,
            "M_wc - M_1 restricted to q_wc at the nominal pose (redistribution of inertia, 000 Sect. 2.2)":
                float(np.abs(cf.mass_matrix(qn)[:5, :5] - M1[:5, :5]).max()),
            "Assumption 1": f"p = {a1['p']}, dim q_wc = {a1['dim_q_wc']}, rank E_wc = {a1['rank_E_wc']}: "
                            f"{'holds' if a1['holds'] else 'fails'}"}


def blocks_report(ctx) -> dict:
    """000 (2)-(3): which subsystems each gap's Jacobian touches and the sizes of the blocks M_ij."""
    from invctl.contact.structure import contact_blocks

    q = ctx.model.linkage.nominal + np.random.default_rng(1).uniform(-1e-3, 1e-3, ctx.model.n)
    out = {}
    for gap, blocks in contact_blocks(ctx.model, q).items():
        out[f"grad {gap}"] = ", ".join(f"{s}: {b.size} entries" for s, b in blocks.items()) + (
            " (and the ground)" if len(blocks) == 1 else "")
    return out


def _pd(model, s):
    from invctl.control.pdplus import pd_gravity, selection_indices

    idx = selection_indices(model)
    return pd_gravity(model, Kp=s["Kp"], Kv=s["Kv"], q_d=model.linkage.nominal[idx] + s["offset"], idx=idx,
                      potential=model.linkage.potential_of([2]))


def _check(values):
    from invctl.errors import ParameterError

    if not 0 <= values["e"] <= 1:
        raise ParameterError(f"chain14: restitution e must lie in [0, 1], got {values['e']}")
    if not 0 < values["c"] < 0.01:
        raise ParameterError(f"chain14: clearance c = {values['c']} must lie in (0, 0.01) m")
    if values["g"] != 0 and values["g"] < 0:
        raise ParameterError(f"chain14: gravity g must be >= 0, got {values['g']}")


def drawing(model):
    from invctl.plot.animate import Drawing

    points, links = model.linkage.drawing_parts(model)
    return Drawing(points=points, links=links,
                   segments=[((G16[0] - 0.15, G16[1] - SLIDER[1] - 0.002), (G16[0] + 0.15, G16[1] - SLIDER[1] - 0.002))])


SCENE = Scene(
    "chain14", build, params=PARAMS, settings=SETTINGS,
    positive=("rho", "m12", "c", "Kp", "Kv", "h", "t_end"), validate=_check,
    contact=Contact(controllers={"pd": _pd},
                    initial_state=lambda model, s, controller: (model.linkage.nominal.copy(), np.zeros(model.n))),
    reports=(Report("000 Example 1: open system", subsystem_report, command="analyze",
                    printed={"n (open system)": 15, "n_ind": 3, "DoFs per subsystem": [7, 4, 4],
                             "unilateral constraints m_u": 7, "clearance-free DoFs (dim q_wc)": 7,
                             "actuators p": 7}),
             Report("000 (2)-(3): contact Jacobian blocks", blocks_report, command="analyze"),
             Report("000 Sect. 2.2: clearance-free model M_wc", clearance_free_report, command="analyze")),
    drawing=drawing,
    description="000 Example 1 (Fig. 3): 14-body chain with clearances at J1, J9, J14 and the prismatic J16; "
                "open system, blocks of M and of the contact Jacobians, clearance-free model M_wc",
)
