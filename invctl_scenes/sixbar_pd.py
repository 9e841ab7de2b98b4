"""Six-bar with clearances at J4, J5, J6 under PD + gravity compensation (000 Fig. 7(a), Sect. 5, Prop. 2).

The geometry is in ``invctl_scenes/_sixbar.py`` (stated there: bars of 0.3/0.3/0.25/0.25/0.25 m,
1.5 kg/m, 1 mm clearances, vertical plane).  Open system (34): ``S1 = (B1, B2, B3)`` with
``q_1 = (theta_B1, theta_J2, theta_J3)`` (the angle of B1 and the relative angles at J2, J3),
fully actuated at J1, J2, J3; ``S2 = B4`` and ``S3 = B5`` floating, ``q_i = (x, y, phi)`` of their
centres of mass; gaps ``f_14`` (J4), ``f_45`` (J5), ``f_50`` (J6).

Controller ``pd``: (36), ``tau_1 = G_1(q_1) - K_p (q_1 - q_1d) - K_v q_1'`` with
``q_1d = q_1(nominal) + (dq1, dq2, dq3)``; ``V`` is (37) with ``U_4 + U_5`` the gravity potential of
B4 and B5.  Initial state: the nominal pose with centred journals, B4 and B5 spinning at ``w4``,
``w5`` rad/s about their centres of mass (several initial conditions: ``--set w4=... w5=...``).

Reports: ``V`` never increases (impacts included, (39)); the run ends in the set of equilibria
``E`` of (40)-(41): the generic report gives the equilibrium next to the final state and the
distance to it; the scene report lists the equilibria found near the nominal pose (with gravity an
isolated one: the weight of B4 and B5 deflects S1 by ``q_1* - q_1d = K_p^-1 M_14 lam_14``, so the
controller does not reach ``q_1d``, Remark 6; with ``g = 0`` a continuum, journals anywhere).

Time step: ``h = 1e-5`` without position projection (``V`` then never increases, to round-off; the
largest penetration is 2e-5 m, 2 % of the clearance).  With the projection the journals chatter in
persistent contact on their curved bearings (period-2 velocity cycles that the projection hides from
the positions) and ``V`` rises by O(1e-7) per step; see docs/clearances.md.
"""
from __future__ import annotations

import numpy as np

from invctl.contact.structure import subsystem_report
from invctl.scenes import Contact, Report, Scene
from invctl_scenes import _sixbar as sb

CONFIG = 7
SETTINGS = {"Kp": 40.0, "Kv": 2.0, "dq1": 0.15, "dq2": -0.1, "dq3": 0.1, "w4": 2.0, "w5": -2.0,
            "h": 1e-5, "theta": 0.5, "t_end": 8.0, "projection": 0.0, "activation_tol": 1e-12}


def build(**overrides: float):
    """The open six-bar of Fig. 7(a)."""
    return sb.build("sixbar_pd", CONFIG, overrides)


def _targets(model, s):
    return model.linkage.nominal[:3] + np.array([s["dq1"], s["dq2"], s["dq3"]])


def _pd(model, s):
    from invctl.control.pdplus import pd_gravity

    return pd_gravity(model, Kp=s["Kp"], Kv=s["Kv"], q_d=_targets(model, s), idx=[0, 1, 2],
                      potential=model.linkage.potential_of([1, 2]))


def _initial(model, s, controller):
    q0 = model.linkage.nominal.copy()
    v0 = np.zeros(model.n)
    v0[5], v0[8] = s["w4"], s["w5"]
    return q0, v0


def closed_loop_force(model, s):
    """``F(q) = f(q, 0) + B u(q, 0)`` of the PD law (36) (gravity of B4, B5 and ``-K_p (q_1 - q_1d)``)."""
    import casadi as ca

    from invctl.contact.equilibria import static_force

    law = _pd(model, s)
    u, _, kap = law.symbolic(model, ca.SX.sym("t"))
    return ca.substitute(static_force(model, u), kap, ca.DM(law.kappa_values))


def equilibria_report(ctx) -> dict:
    """000 (40)-(41): the equilibria near the nominal pose (Newton with all contacts closed from random
    journal positions within the clearances), the one the run ends at, and the deflection of S1 from
    ``q_1d`` that the weight of B4 and B5 causes (first row of (40): ``K_p (q_1* - q_1d) = M_14 lam_14``)."""
    from invctl.contact.equilibria import equilibrium_points

    model, s, tr = ctx.model, ctx.settings, ctx.result
    F = closed_loop_force(model, s)
    rng = np.random.default_rng(0)
    c = model.values["c"]
    starts = [model.linkage.nominal + np.r_[np.zeros(3), rng.uniform(-3 * c, 3 * c, 6)] for _ in range(20)]
    eqs = equilibrium_points(model, F, [tr.q[:, -1]] + starts, active_tol=np.inf)
    q1d = _targets(model, s)
    near = int(np.argmin([np.linalg.norm(tr.q[:, -1] - e.q) for e in eqs])) if eqs else -1
    isolated = [e for e in eqs if e.dimension == 0]
    out = {"equilibria found (21 starts)": len(eqs), "isolated ones": len(isolated)}
    if len(isolated) < len(eqs):
        dims = sorted({e.dimension for e in eqs if e.dimension > 0})
        out["the others lie on a continuum of local dimension"] = dims
    for k, e in enumerate(isolated):
        out[f"isolated E[{k}]: q_1* - q_1d"] = e.q[:3] - q1d
        out[f"isolated E[{k}]: lam_14, lam_45, lam_50"] = e.lam
    if near >= 0:
        e = eqs[near]
        out["run ends next to"] = (f"{'an isolated' if e.dimension == 0 else 'a continuum'} equilibrium, "
                                   f"|q - q*| = {np.linalg.norm(tr.q[:, -1] - e.q):.3g}, q_1* - q_1d = "
                                   f"{np.round(e.q[:3] - q1d, 8).tolist()}")
    return out


SCENE = Scene(
    "sixbar_pd", build, params=dict(sb.PARAMS), settings=SETTINGS,
    positive=("d", "l1", "l2", "l3", "l4", "l5", "rho", "c", "Kp", "Kv", "h", "t_end"), validate=sb.check,
    contact=Contact(controllers={"pd": _pd}, initial_state=_initial,
                    potential=lambda model: model.linkage.potential),
    reports=(Report("000 Prop. 2: equilibria (40)-(41)", equilibria_report, controllers=("pd",)),
             Report("000 Sect. 2: open system (Fig. 7(a))", subsystem_report, command="analyze",
                    printed={"n (open system)": sb.PRINTED[CONFIG][0], "n_ind": sb.PRINTED[CONFIG][1],
                             "DoFs per subsystem": sb.PRINTED[CONFIG][2]})),
    drawing=sb.drawing,
    description="six-bar with clearances at J4, J5, J6 (000 Fig. 7(a)): PD + gravity compensation (36), "
                "V (37) and convergence to the equilibria (40) (Prop. 2)",
)

