"""Slider-crank with play in the prismatic joint J4: the first mechanism of 000 Example 5 (Fig. 4(a)).

Vertical plane, gravity ``g`` along ``-y``.  Crank ``J1``-``J2`` (length ``r``, pinned to the ground at
``O = (0, 0)``), rod ``J2``-``J3`` (length ``Lr``), slider (mass ``ms``, half-length ``sl``, half-height
``sw``) pinned to the rod at its centre (``J3``) and sliding in a horizontal guide of half-height
``sw + c`` centred on ``y = 0`` (``J4``, lateral play ``c``).  Crank and rod are uniform bars of
``rho`` kg/m.  The ideal joints J1, J2, J3 make one subsystem grounded at J1 (000 Sect. 2), so

    q = (theta_crank, theta_J2, theta_J3),   n = 3,   m_u = 4   (000 Example 5)

with the four corner gaps of 000 Fig. 1(a) (:class:`invctl.contact.linkage.Linkage`, ``eta`` the
slider centre's height, ``psi = theta_crank + theta_J2 + theta_J3`` its tilt):

    f_front_top    = sw + c - eta - (sl sin psi + sw cos psi)
    f_front_bottom = sw + c + eta + (sl sin psi - sw cos psi)
    f_back_top     = sw + c - eta - (-sl sin psi + sw cos psi)
    f_back_bottom  = sw + c + eta + (-sl sin psi - sw cos psi)

000 names the corners A, B, C, D in Fig. 4(a), which the text does not show: here the contact pair
``A, B`` is the slider lying flat on the lower face of the guide (``back_bottom``, ``front_bottom``)
and ``C, D`` on the upper face (``back_top``, ``front_top``); ``--set corners=1`` (A, B) or ``2``
(C, D) selects the pair kept closed.  Keeping two corners closed needs ``p >= m_u' = 2`` actuators
(000 Corollary 1), while the clearance-free slider-crank has one DoF (``p = 1`` is full actuation).
``actuators``: 1 (crank torque at J1), 2 (and a torque between rod and slider at J3), 3 (and at J2).

Horizontal plane by default (``g = 0``; ``--set g=9.81``: vertical, gravity along ``-y``).

Controllers: ``preload`` -- the pre-loading law (13) keeping the chosen corner pair closed with
multipliers ``beta``, its free part (projected on ``ker E_hat``) a PD on the crank to ``crank_d``; it
runs with ``actuators = 3`` (default): with ``p = 2`` Lemma 1 holds (``rank E_hat = 2``) but
``ker E_hat = {0}``, so ``tau = E_hat^-1 (w_hat - beta)`` leaves no input to move the mechanism, which
then runs away under the pre-load (``invctl analyze`` shows the rank for every ``p``); with ``p = 1``
000 Corollary 1 fails.  ``pd`` -- PD (36) on the crank alone (``actuators = 1``), the clearance-free
design, with the slider free in its play.
"""
from __future__ import annotations

import math

import casadi as ca
import numpy as np

from invctl.contact.linkage import GROUND, Body, Joint, Linkage, bar
from invctl.contact.structure import subsystem_report
from invctl.model import Model, ParamSet
from invctl.scenes import Contact, Report, Scene

PARAMS = {"r": 0.1, "Lr": 0.3, "rho": 1.5, "ms": 0.5, "sl": 0.04, "sw": 0.02, "c": 1e-3, "e": 0.5, "g": 0.0,
          "actuators": 3.0}
MODEL_PARAMS = ("r", "Lr", "rho", "ms", "sl", "sw", "c", "e", "g")
SETTINGS = {"corners": 1.0, "beta": 2.0, "Kp": 2.0, "Kv": 0.2, "crank0": 0.5, "crank_d": 1.0,
            "h": 1e-4, "theta": 0.5, "t_end": 1.0, "projection": 0.0, "activation_tol": 1e-12}
#: gap indices of the corner pairs (order of the linkage: front_top, front_bottom, back_top, back_bottom)
CORNERS = {1: ("A, B (lower face)", [3, 1]), 2: ("C, D (upper face)", [2, 0])}
ACTUATED = {1: ("J1",), 2: ("J1", "J3"), 3: ("J1", "J2", "J3")}


def linkage(P: ParamSet, actuators: int) -> Linkage:
    """Crank, rod and slider; J4 (slider in the ground guide) with lateral play ``c``."""
    act = ACTUATED[actuators]
    ms, sl, sw = P["ms"], P["sl"], P["sw"]
    slider = Body("slider", ms, ms * (sl**2 + sw**2) / 3, {"centre": (0.0, 0.0)})
    joints = [Joint("J1", "revolute", GROUND, (0.0, 0.0), "crank", "start", actuated="J1" in act),
              Joint("J2", "revolute", "crank", "end", "rod", "start", actuated="J2" in act),
              Joint("J3", "revolute", "rod", "end", "slider", "centre", actuated="J3" in act),
              Joint("J4", "prismatic", GROUND, (0.0, 0.0), "slider", "centre", clearance=P["c"], slider=(sl, sw),
                    restitution="e")]
    return Linkage([bar("crank", P["r"], P["rho"] * P["r"]), bar("rod", P["Lr"], P["rho"] * P["Lr"]), slider],
                   joints, gravity=P["g"])


def build(**overrides: float) -> Model:
    """The open slider-crank (``q = theta_crank, theta_J2, theta_J3``) with the four corner gaps of J4."""
    act = int(overrides.get("actuators", PARAMS["actuators"]))
    if act not in ACTUATED:
        from invctl.errors import ParameterError

        raise ParameterError(f"slider_crank_prismatic_play: actuators must be 1, 2 or 3, got {act}")
    P = ParamSet(list(MODEL_PARAMS))
    link = linkage(P, act)
    model = link.build("slider_crank_prismatic_play", P, {k: PARAMS[k] for k in MODEL_PARAMS},
                       overrides={k: v for k, v in overrides.items() if k in MODEL_PARAMS})
    link.nominal = configuration(model, SETTINGS["crank0"], -1)
    return model


def slider_poses(values: dict, crank: float, side: int) -> dict:
    """Poses ``body -> (x, y, phi)`` with the crank at ``crank`` and the slider flat on the lower
    (``side = -1``) or upper (``+1``) face of the guide (its centre at height ``side c``)."""
    r, Lr, c = values["r"], values["Lr"], values["c"]
    ax, ay = r * math.cos(crank), r * math.sin(crank)
    ys = side * c
    if abs(ay - ys) >= Lr:
        from invctl.errors import ParameterError

        raise ParameterError(f"slider_crank_prismatic_play: the rod (Lr = {Lr}) cannot reach the guide from crank "
                             f"angle {crank}; use a longer rod or another crank angle")
    xs = ax + math.sqrt(Lr**2 - (ay - ys) ** 2)
    return {"crank": (0.0, 0.0, crank), "rod": (ax, ay, math.atan2(ys - ay, xs - ax)), "slider": (xs, ys, 0.0)}


def configuration(model: Model, crank: float, side: int) -> np.ndarray:
    """Open-system coordinates of :func:`slider_poses`."""
    link = model.linkage
    return link.coordinates(slider_poses(model.values, crank, side), model.params, model.theta_values)


def _active(s) -> list:
    return CORNERS[int(s["corners"])][1]


def _preload(model, s):
    from invctl.control.preload import preload_law

    p = model.m
    return preload_law(model, _active(s), beta=s["beta"], Kp=[s["Kp"]] + [0.0] * (p - 1),
                       Kv=[s["Kv"]] + [0.0] * (p - 1), y_d=[s["crank_d"]] + [0.0] * (p - 1))


def _pd(model, s):
    from invctl.control.pdplus import pd_gravity

    return pd_gravity(model, Kp=s["Kp"], Kv=s["Kv"], q_d=s["crank_d"], idx=[0], potential=model.linkage.potential)


def _initial(model, s, controller):
    return configuration(model, s["crank0"], -1 if int(s["corners"]) == 1 else 1), np.zeros(model.n)


def lemma1_report(ctx) -> dict:
    """000 Corollary 1 / Lemma 1 for both corner pairs at the start (rank of ``E_hat``, Delassus ``D``),
    and, after a run, how well the kept corners stayed closed and their multipliers."""
    from invctl.control.preload import preload_check, preload_terms

    model, s = ctx.model, ctx.settings
    q0, v0 = _initial(model, s, "preload")
    out = {"actuators p": model.m}
    for label, idx in CORNERS.values():
        chk = preload_check(model, q0, v0, idx, raise_=False)
        out[f"corners {label}: rank E_hat, m_u', Lemma 1 holds"] = [chk.rank, chk.m_active, bool(chk.feasible)]
    D = ca.Function("D", [model.q, model.theta], [preload_terms(model, _active(s))[2]])(q0, model.theta_values)
    out["Delassus D of the kept corners at the start [1/kg]"] = np.array(D).round(9).tolist()
    tr = ctx.result
    if tr is not None:
        idx = _active(s)
        lam = tr.P[idx, 1:] / tr.h
        out["kept corners: largest |gap| [m]"] = float(np.abs(tr.gaps[idx]).max())
        out["kept corners: multipliers P/h, min and max [N]"] = [float(lam.min()), float(lam.max())]
        out["other corners: smallest gap [m]"] = float(np.delete(tr.gaps, idx, axis=0).min())
        out["impacts"] = int(tr.impact_mask().sum())
        out["crank at the end [rad]"] = float(tr.q[0, -1])
    return out


def _check(v: dict) -> None:
    from invctl.errors import ParameterError

    name = "slider_crank_prismatic_play"
    if int(v["actuators"]) not in ACTUATED:
        raise ParameterError(f"{name}: actuators must be 1, 2 or 3, got {v['actuators']}")
    if int(v["corners"]) not in CORNERS:
        raise ParameterError(f"{name}: corners must be 1 (A, B: lower face) or 2 (C, D: upper face), got "
                             f"{v['corners']}")
    if not 0 <= v["e"] <= 1:
        raise ParameterError(f"{name}: restitution e must lie in [0, 1], got {v['e']}")
    if v["Lr"] <= v["r"] + v["c"]:
        raise ParameterError(f"{name}: the rod (Lr = {v['Lr']}) must be longer than the crank (r = {v['r']}) "
                             "plus the play")
    if v["c"] >= 0.5 * v["sw"]:
        raise ParameterError(f"{name}: the play c = {v['c']} should be small against the slider's half-height "
                             f"sw = {v['sw']} (< 50 %)")
    if v["g"] < 0:
        raise ParameterError(f"{name}: gravity g must be >= 0 (it acts along -y), got {v['g']}")
    if not 0 <= v["theta"] <= 1:
        raise ParameterError(f"{name}: theta of the theta-method must lie in [0, 1], got {v['theta']}")
    if v["projection"] not in (0, 1):
        raise ParameterError(f"{name}: projection is a switch, 0 or 1, got {v['projection']}")


def drawing(model: Model):
    """Crank, rod, the slider's outline and the guide's faces."""
    from invctl.plot.animate import Drawing

    link = model.linkage
    poses = link.poses
    p = model.params
    r, phi = poses["slider"]
    rot = ca.vertcat(ca.horzcat(ca.cos(phi), -ca.sin(phi)), ca.horzcat(ca.sin(phi), ca.cos(phi)))
    corners = {f"k{i}": r + ca.mtimes(rot, ca.vertcat(sx * p["sl"], sy * p["sw"]))
               for i, (sx, sy) in enumerate(((1, 1), (1, -1), (-1, -1), (-1, 1)))}
    pts = {"O": ca.vertcat(0, 0), "A": link.point(poses, "crank", "end"), "C": r, **corners}
    face = float(model.values["sw"] + model.values["c"])
    return Drawing(points=pts, links=[("O", "A"), ("A", "C"), ("k0", "k1"), ("k1", "k2"), ("k2", "k3"), ("k3", "k0")],
                   segments=[((0.1, face), (0.5, face)), ((0.1, -face), (0.5, -face))])


SCENE = Scene(
    "slider_crank_prismatic_play", build, params=PARAMS, settings=SETTINGS,
    integer=("actuators", "corners", "projection"),
    positive=("r", "Lr", "rho", "ms", "sl", "sw", "c", "beta", "Kp", "Kv", "h", "t_end"), validate=_check,
    contact=Contact(controllers={"preload": _preload, "pd": _pd}, initial_state=_initial,
                    potential=lambda model: model.linkage.potential, clearance=lambda model, s: 2 * model.values["c"],
                    requires={"preload": {"actuators": 3}, "pd": {"actuators": 1}}),
    reports=(Report("000 Sect. 2: open system", subsystem_report, command="analyze",
                    printed={"n (open system)": 3, "unilateral constraints m_u": 4}),
             Report("000 Example 5: Corollary 1 and Lemma 1 for the corner pairs", lemma1_report, command="analyze"),
             Report("000 Example 5: corners kept closed", lemma1_report)),
    drawing=drawing,
    description="slider-crank with play in the prismatic joint J4 (000 Example 5, Fig. 4(a)): four corner gaps, "
                "pre-loading (13) of two corners (p >= 2, Corollary 1), PD (36) on the crank",
)
