"""Four-bar with a clearance at joint J4: the second mechanism of 000 Example 5 (Fig. 4(b)).

Crank-rocker in the horizontal plane (``--set g=9.81``: vertical, gravity along ``-y``): ground pivots
``A = (0, 0)`` (J1) and ``D = (a, 0)`` (J4), crank ``AB`` (``b``), coupler ``BC`` (``c``), rocker ``DC``
(``d``); ``a, b, c, d = 0.3, 0.1, 0.3, 0.2`` m as in ``invctl_scenes/fourbar_backlash.py``, uniform bars of
``rho`` kg/m.  J1, J2 (crank-coupler) and J3 (coupler-rocker) are ideal; J4 has radial clearance ``cl``:
the bearing is the ground at ``D``, the journal the rocker's end.  Opened at J4 the four-bar is one
chain grounded at J1 (000 Sect. 2):

    q = (theta_crank, theta_J2, theta_J3),   n = 3,   m_u = 1   (000 Example 5),
    f = (cl^2 - |P - D|^2) / (2 cl) >= 0,    P the journal centre.

The clearance-free four-bar has one DoF, so ``p = 1`` (a crank torque at J1, ``actuators = 1``) is full
actuation, and keeping the journal on the bearing (``m_u' = 1``) needs ``p >= 1`` only (000 Corollary 1):
no overactuation a priori.  Lemma 1 then asks ``E_hat = D^-1 grad f^T M^-1 E != 0`` (the report
evaluates it along the run).  ``actuators = 2`` adds a torque at J2 between crank and coupler.

Controllers: ``preload`` -- the pre-loading law (13) keeping ``f = 0`` with multiplier ``beta``, its free
part (on ``ker E_hat``) a PD on the crank to ``crank_d``; it runs with ``actuators = 2`` (default): with
one actuator ``ker E_hat = {0}`` and the law is ``tau = E_hat^-1 (w_hat - beta)``, nonzero at rest, so
the mechanism cannot be held under pre-load and accelerates, and ``E_hat`` changes sign at two crank
angles per turn, where Lemma 1 fails (``invctl analyze fourbar_clearance --set actuators=1`` lists them).
``pd`` -- PD (36) on the crank alone (``actuators = 1``), the clearance-free design, journal free in the
bearing.  Both start at rest with the crank at ``crank0`` and the journal on the bearing in line with
the rocker (:func:`fourbar_poses`).
"""
from __future__ import annotations

import math

import casadi as ca
import numpy as np

from invctl.contact.linkage import GROUND, Joint, Linkage, bar
from invctl.contact.structure import subsystem_report
from invctl.model import Model, ParamSet
from invctl.scenes import Contact, Report, Scene

PARAMS = {"a": 0.3, "b": 0.1, "c": 0.3, "d": 0.2, "rho": 1.5, "cl": 1e-3, "e": 0.5, "g": 0.0, "actuators": 2.0}
MODEL_PARAMS = ("a", "b", "c", "d", "rho", "cl", "e", "g")
SETTINGS = {"beta": 1.0, "Kp": 0.5, "Kv": 0.05, "crank0": 0.5, "crank_d": 1.5,
            "h": 1e-4, "theta": 0.5, "t_end": 1.0, "projection": 0.0, "activation_tol": 1e-12}
ACTUATED = {1: ("J1",), 2: ("J1", "J2")}


def linkage(P: ParamSet, actuators: int) -> Linkage:
    """Crank, coupler and rocker; J4 (rocker to ground) with radial clearance ``cl``."""
    act = ACTUATED[actuators]
    bars = [bar(k, P[x], P["rho"] * P[x]) for k, x in (("crank", "b"), ("coupler", "c"), ("rocker", "d"))]
    joints = [Joint("J1", "revolute", GROUND, (0.0, 0.0), "crank", "start", actuated=True),
              Joint("J2", "revolute", "crank", "end", "coupler", "start", actuated="J2" in act),
              Joint("J3", "revolute", "coupler", "end", "rocker", "end"),
              Joint("J4", "revolute", GROUND, (P["a"], 0.0), "rocker", "start", clearance=P["cl"], restitution="e")]
    return Linkage(bars, joints, gravity=P["g"])


def build(**overrides: float) -> Model:
    """The open four-bar (``q = theta_crank, theta_J2, theta_J3``) with the journal gap of J4."""
    act = int(overrides.get("actuators", PARAMS["actuators"]))
    if act not in ACTUATED:
        from invctl.errors import ParameterError

        raise ParameterError(f"fourbar_clearance: actuators must be 1 or 2, got {act}")
    P = ParamSet(list(MODEL_PARAMS))
    link = linkage(P, act)
    model = link.build("fourbar_clearance", P, {k: PARAMS[k] for k in MODEL_PARAMS},
                       overrides={k: v for k, v in overrides.items() if k in MODEL_PARAMS})
    link.nominal = configuration(model, SETTINGS["crank0"])
    return model


def fourbar_poses(values: dict, crank: float) -> dict:
    """Poses ``body -> (x, y, phi)`` of the four-bar with the crank at ``crank`` and the journal on the
    bearing in line with the rocker, on the side of ``C`` (``P = D + cl (C - D) / |C - D|``: the rocker
    and the taut clearance in one line, ``C`` on the upper branch)."""
    a, b, c, d, cl = (values[k] for k in ("a", "b", "c", "d", "cl"))
    B = np.array([b * math.cos(crank), b * math.sin(crank)])
    D = np.array([a, 0.0])
    L = np.linalg.norm(D - B)
    if not abs(c - d - cl) < L < c + d + cl:
        from invctl.errors import ParameterError

        raise ParameterError(f"fourbar_clearance: coupler and rocker (c = {c}, d = {d}) cannot close the loop at "
                             f"crank angle {crank}")
    u = (D - B) / L
    k = (c**2 - (d + cl) ** 2 + L**2) / (2 * L)
    C = B + k * u + math.sqrt(c**2 - k**2) * np.array([-u[1], u[0]])
    P = D + cl * (C - D) / (d + cl)
    return {"crank": (0.0, 0.0, crank), "coupler": (B[0], B[1], math.atan2(*(C - B)[::-1])),
            "rocker": (P[0], P[1], math.atan2(*(C - P)[::-1]))}


def configuration(model: Model, crank: float) -> np.ndarray:
    """Open-system coordinates of :func:`fourbar_poses`."""
    return model.linkage.coordinates(fourbar_poses(model.values, crank), model.params, model.theta_values)


def _preload(model, s):
    from invctl.control.preload import preload_law

    p = model.m
    return preload_law(model, [0], beta=s["beta"], Kp=[s["Kp"]] + [0.0] * (p - 1), Kv=[s["Kv"]] + [0.0] * (p - 1),
                       y_d=[s["crank_d"]] + [0.0] * (p - 1))


def _pd(model, s):
    from invctl.control.pdplus import pd_gravity

    return pd_gravity(model, Kp=s["Kp"], Kv=s["Kv"], q_d=s["crank_d"], idx=[0], potential=model.linkage.potential)


def _initial(model, s, controller):
    return configuration(model, s["crank0"]), np.zeros(model.n)


def lemma1_report(ctx) -> dict:
    """000 Corollary 1 / Lemma 1: ``E_hat`` and the Delassus ``D`` at the start, ``E_hat`` over a crank
    turn (journal in line with the rocker) or along the run, and how well the run kept the journal on
    the bearing."""
    from invctl.control.preload import preload_terms

    model = ctx.model
    Ehat, _, D, _ = preload_terms(model, [0])
    fn = ca.Function("lemma1", [model.q, model.theta], [Ehat, D])
    tr = ctx.result
    q0 = _initial(model, ctx.settings, "preload")[0]
    E0, D0 = (np.array(x) for x in fn(q0, model.theta_values))
    out = {"actuators p": model.m, "m_u'": 1, "Delassus D at the start [1/kg]": float(D0[0, 0]),
           "E_hat at the start": E0.ravel().tolist()}
    if tr is None:
        turn = np.linspace(0.0, 2 * np.pi, 721)
        qs = np.stack([configuration(model, th) for th in turn], axis=1)
        E = np.array(fn.map(turn.size)(qs, model.theta_values)[0]).reshape(-1, model.m).T  # 1 x p blocks side by side
        out["crank turn: smallest |E_hat|"] = float(np.linalg.norm(E, axis=0).min())
        if model.m == 1:
            flips = turn[1:][np.diff(np.sign(E[0])) != 0]
            key = "crank turn: E_hat changes sign near crank angles [rad] (Lemma 1 fails there)"
            out[key] = flips.round(3).tolist()
        return out
    E = np.array(fn.map(tr.q.shape[1])(tr.q, model.theta_values)[0]).reshape(-1, model.m).T
    lam = tr.P[0, 1:] / tr.h
    out["along the run: smallest |E_hat|"] = float(np.linalg.norm(E, axis=0).min())
    out["journal gap: min, max [m]"] = [float(tr.gaps[0].min()), float(tr.gaps[0].max())]
    out["multiplier P/h: min, max [N]"] = [float(lam.min()), float(lam.max())]
    if ctx.controller == "preload":
        beta = float(ctx.settings["beta"])
        w = lam[:lam.size // 100 * 100].reshape(-1, 100).mean(axis=1)
        out["steps with multiplier = beta (1e-3 relative)"] = float(np.mean(np.abs(lam - beta) <= 1e-3 * beta))
        out["multiplier averaged over 100 steps: min, max [N]"] = [float(w.min()), float(w.max())]
    out["impacts"] = int(tr.impact_mask().sum())
    out["crank at the end [rad]"] = float(tr.q[0, -1])
    return out


def _check(v: dict) -> None:
    from invctl.errors import ParameterError

    name = "fourbar_clearance"
    if int(v["actuators"]) not in ACTUATED:
        raise ParameterError(f"{name}: actuators must be 1 or 2, got {v['actuators']}")
    a, b, c, d = (v[k] for k in ("a", "b", "c", "d"))
    s, l = min(a, b, c, d), max(a, b, c, d)
    if not (b == s and s + l <= a + b + c + d - s - l):
        raise ParameterError(f"{name}: a, b, c, d = {a}, {b}, {c}, {d} is not a Grashof crank-rocker with the crank "
                             "b shortest; the crank could not turn fully")
    if v["cl"] >= 0.1 * b:
        raise ParameterError(f"{name}: the clearance cl = {v['cl']} should be small against the crank b = {b} "
                             "(< 10 %)")
    if not 0 <= v["e"] <= 1:
        raise ParameterError(f"{name}: restitution e must lie in [0, 1], got {v['e']}")
    if v["g"] < 0:
        raise ParameterError(f"{name}: gravity g must be >= 0 (it acts along -y), got {v['g']}")
    if not 0 <= v["theta"] <= 1:
        raise ParameterError(f"{name}: theta of the theta-method must lie in [0, 1], got {v['theta']}")
    if v["projection"] not in (0, 1):
        raise ParameterError(f"{name}: projection is a switch, 0 or 1, got {v['projection']}")


def drawing(model: Model):
    """The three bars from the linkage and the ground line."""
    from invctl.plot.animate import Drawing

    points, links = model.linkage.drawing_parts(model)
    return Drawing(points=points, links=links, segments=[((-0.1, 0.0), (float(model.values["a"]) + 0.1, 0.0))])


SCENE = Scene(
    "fourbar_clearance", build, params=PARAMS, settings=SETTINGS, integer=("actuators", "projection"),
    positive=("a", "b", "c", "d", "rho", "cl", "beta", "Kp", "Kv", "h", "t_end"), validate=_check,
    contact=Contact(controllers={"preload": _preload, "pd": _pd}, initial_state=_initial,
                    potential=lambda model: model.linkage.potential, clearance=lambda model, s: model.values["cl"],
                    requires={"preload": {"actuators": 2}, "pd": {"actuators": 1}}),
    reports=(Report("000 Sect. 2: open system", subsystem_report, command="analyze",
                    printed={"n (open system)": 3, "unilateral constraints m_u": 1}),
             Report("000 Example 5: Corollary 1 and Lemma 1", lemma1_report, command="analyze"),
             Report("000 Example 5: Lemma 1 along the run, journal kept on the bearing", lemma1_report)),
    drawing=drawing,
    description="four-bar with a clearance at J4 (000 Example 5, Fig. 4(b)): one journal gap, pre-loading (13) "
                "with p = 1 (Corollary 1), PD (36) on the crank",
)
