"""The six-bar of 000: clearance configurations (Example 2, Figs. 5(a), 6(a), 7(a)), PD + gravity
compensation with clearances at J4, J5, J6 (Prop. 2), PD+ tracking with a clearance at J3 (Prop. 3)."""
import math

import casadi as ca
import numpy as np
import pytest

import invctl_scenes._sixbar as sb
from invctl.contact.equilibria import static_equilibrium
from invctl.contact.mechanics import ContactSystem
from invctl.contact.structure import open_structure
from invctl.scenes import load_scene
from invctl.stability.lyapunov import equilibrium_check, impact_jump_51
from invctl.studies.contact import contact_setup, run_contact


@pytest.mark.parametrize("code", sorted(sb.CONFIGS))
def test_configurations_match_000(code):
    """n, n_ind and the DoFs of each subsystem are those 000 states (Example 2, Sects. 4, 5); the mass
    matrix is block-diagonal; the nominal pose closes every clearance with centred journals."""
    m = sb.build("sixbar", code, {})
    st = open_structure(m, m.linkage.nominal)
    n, nind, dofs = sb.PRINTED[code]
    assert (st.n, st.n_ind, [s.dof for s in st.subsystems]) == (n, nind, dofs)
    assert st.off_block == 0.0
    g = ca.Function("g", [m.q, m.theta], [m.linkage.closure])(m.linkage.nominal, m.theta_values)
    assert np.abs(np.array(g)).max() < 1e-14     # closed-form loop closure of _sixbar.closed_poses
    np.testing.assert_allclose(ContactSystem(m).gaps(m.linkage.nominal), 0.5 * m.values["c"], rtol=1e-9)


def test_actuation_statements_of_example2():
    """S1: both subsystems fully actuated; S2: B3 unactuated; S3: (B2, B3) underactuated with its
    centre of mass unactuated (000 Example 2); Fig. 6(a): S2 = (B3, B4) has degree of underactuation 3."""
    status = {code: open_structure(sb.build("s", code, {}), sb.build("s", code, {}).linkage.nominal).subsystems
              for code in (1, 2, 3, 4)}
    assert [s.status for s in status[1]] == ["fully actuated"] * 2
    assert status[2][1].status == "unactuated" and status[2][1].com_actuated is False
    assert status[3][1].status == "underactuated" and status[3][1].com_actuated is False
    assert status[4][1].dof - status[4][1].actuators == 3


def test_linkage_mass_matrix_against_two_link_arm():
    """The builder's M for S1 = (B1, B2) (pinned bar + bar, relative angle) equals the textbook two-link
    arm M11 = I1 + I2 + m1 a1^2 + m2 (l1^2 + a2^2 + 2 l1 a2 cos q2), M12 = I2 + m2 (a2^2 + l1 a2 cos q2),
    M22 = I2 + m2 a2^2 (a_i = l_i / 2, I_i about the centre of mass), to round-off."""
    m = sb.build("s", 1, {})
    v = m.values
    l1, l2 = v["l1"], v["l2"]
    m1, m2 = v["rho"] * l1, v["rho"] * l2
    I1, I2, a1, a2 = m1 * l1**2 / 12, m2 * l2**2 / 12, l1 / 2, l2 / 2
    for q2 in (-1.0, 0.3, 2.0):
        q = m.linkage.nominal.copy()
        q[1] = q2
        M = m.evaluate("M", q)[:2, :2]
        c = math.cos(q2)
        ref = np.array([[I1 + I2 + m1 * a1**2 + m2 * (l1**2 + a2**2 + 2 * l1 * a2 * c), I2 + m2 * (a2**2 + l1 * a2 * c)],
                        [I2 + m2 * (a2**2 + l1 * a2 * c), I2 + m2 * a2**2]])
        np.testing.assert_allclose(M, ref, rtol=1e-13)


@pytest.fixture(scope="module")
def pd_scene():
    return load_scene("sixbar_pd")


def _run(scene, values, controller=None):
    params, settings = scene.split(values)
    return run_contact(contact_setup(scene, params, settings, controller=controller), progress=False)


@pytest.mark.parametrize("values", [{"e": 0.5}, {"e": 0.0, "w4": -3.0, "w5": 1.0}, {"e": 0.9, "dq1": -0.1, "w4": 0.0}])
def test_prop2_V_never_increases_and_run_ends_in_E(pd_scene, values):
    """Prop. 2 for several restitution coefficients and initial conditions: V (37) never increases,
    impacts included (to round-off, 1e-12 V0); the run ends next to an equilibrium of (40) (with S1
    deflected by K_p^-1 M_14 lam_14, first row of (40)) that the independent NNLS form of Lemma 2
    confirms, having dissipated all but 0.2 % of its excess V - V(q*, 0).

    Tolerances: without projection the run rests with the journals up to 1.3e-4 m inside their
    bearings (h = 2e-5), which lowers the potential below V(q*) by up to 0.1 % of the excess and shifts
    the rest point along the soft four-bar-like mode of B4, B5 by up to 1.2e-3; hence 2e-3 for both."""
    run = _run(pd_scene, {"t_end": 4.0, "h": 2e-5, **values})
    tr, model, law = run.trajectory, run.model, run.law
    assert tr.stats["n_impacts"] >= 1
    assert tr.max_V_increase <= 1e-12 * tr.V[0]
    assert tr.stats["dV_max_impact"] <= 0.0
    from invctl_scenes.sixbar_pd import _targets, closed_loop_force

    F = closed_loop_force(model, run.settings)
    e = static_equilibrium(model, F, tr.q[:, -1])
    assert np.all(e.lam > 0) and e.gap_min >= -1e-12 and e.residual < 1e-9
    assert np.linalg.norm(tr.q[:, -1] - e.q) < 2e-3
    V_star = float(law.function(model)(e.q, np.zeros(model.n), 0.0, model.theta_values, law.values())[1])
    assert abs(tr.V[-1] - V_star) <= 2e-3 * (tr.V[0] - V_star)
    G = -np.array(ca.Function("F", [model.q, model.theta], [F])(e.q, model.theta_values)).ravel()
    chk = equilibrium_check(ContactSystem(model), e.q, G, gap_tol=1e-9)
    assert chk.is_equilibrium and chk.residual < 1e-9 * np.abs(G).max()
    W = ContactSystem(model).gradients(e.q)
    np.testing.assert_allclose(run.settings["Kp"] * (e.q[:3] - _targets(model, run.settings)),
                               W[:3, 0] * e.lam[0], atol=1e-10)


def test_prop2_horizontal_plane_equilibria_form_a_continuum(pd_scene):
    """With g = 0 the equilibria (41) are a continuum (journals anywhere, 000 after (41)): the run reaches
    q_1 = q_1d exactly up to the remaining motion, and E has positive local dimension there."""
    run = _run(pd_scene, {"t_end": 3.0, "h": 2e-5, "g": 0.0})
    tr = run.trajectory
    from invctl_scenes.sixbar_pd import closed_loop_force, _targets

    e = static_equilibrium(run.model, closed_loop_force(run.model, run.settings), tr.q[:, -1])
    assert e.dimension > 0 and np.all(e.lam <= 1e-9)
    np.testing.assert_allclose(e.q[:3], _targets(run.model, run.settings), atol=1e-10)
    assert tr.max_V_increase <= 1e-12 * tr.V[0]


def test_impact_loss_39_at_the_first_impact(pd_scene):
    """At the first impact of a run, Moreau's law (exact LCP) loses -1/2 (1-e)/(1+e) sigma^T M sigma of
    kinetic energy (000 (39)), to round-off."""
    run = _run(pd_scene, {"t_end": 0.02})
    tr, model = run.trajectory, run.model
    k = int(np.flatnonzero(np.any(tr.impact_mask(), axis=0))[0])
    res = ContactSystem(model, gap_tol=1e-6).impact(tr.q[:, k + 1], tr.v[:, k])   # the step closes the gap to O(h)
    assert res.predicted_jump is not None and res.kinetic_jump < 0
    assert abs(res.kinetic_jump - res.predicted_jump) <= 1e-12 * abs(res.kinetic_jump)


@pytest.fixture(scope="module")
def tracking_runs():
    scene = load_scene("sixbar_tracking")
    return {c: _run(scene, {"t_end": 1.0}, controller=c) for c in ("pdplus", "pdplus_violating")}


def test_prop3_conditions_hold_and_V_never_increases(tracking_runs):
    """The desired trajectory that moves the journal away from the wall it touches satisfies (52) at
    every impact and (54) in persistent contact; V (50) then never increases (Prop. 3)."""
    from invctl.studies.contact import law_report

    run = tracking_runs["pdplus"]
    _, d = law_report(run)
    assert d["impacts_checked"] >= 3 and d["impacts_violating_52"] == 0
    assert d["persistent_steps_violating_54"] == 0
    assert run.trajectory.max_V_increase <= 1e-12 * run.trajectory.V[0]


def test_prop3_violated_conditions_let_V_grow(tracking_runs):
    """The desired journal running through the opposite wall violates (52) and (54); V jumps up at
    the violating impacts and grows in the persistent contact."""
    from invctl.studies.contact import law_report

    run = tracking_runs["pdplus_violating"]
    _, d = law_report(run)
    assert d["impacts_violating_52"] >= 1 and d["max_V_jump_where_52_violated"] > 1e-3 * run.trajectory.V[0]
    assert d["max_V_jump_where_52_holds"] <= 0.0
    assert d["persistent_steps_violating_54"] > 1000
    assert run.trajectory.V[-1] > 10 * np.min(run.trajectory.V)


def test_V_jump_51_at_an_exact_impact(tracking_runs):
    """At an exact impact (Moreau's law at a violating impact configuration), the jump of the law's V
    (50) equals (51): -1/2 (1-e)/(1+e) sigma^T M sigma - qd_dot^T M sigma, to round-off."""
    run = tracking_runs["pdplus_violating"]
    tr, model, law = run.trajectory, run.model, run.law
    k = int(np.flatnonzero(np.any(tr.impact_mask(), axis=0))[-1])
    q, vminus, t = tr.q[:, k + 1], tr.v[:, k], tr.t[k]
    res = ContactSystem(model, gap_tol=1e-6).impact(q, vminus)
    fn = law.function(model)
    V = lambda vv: float(fn(q, vv, t, model.theta_values, law.values())[1])  # noqa: E731
    idx = law.info["idx"]
    tt = ca.SX.sym("t")
    dqd = np.array(ca.Function("dqd", [tt], [ca.jacobian(law.info["q_d"](tt), tt)])(t)).ravel()
    qd_dot = np.zeros(model.n)
    qd_dot[idx] = dqd
    M = model.evaluate("M", q)
    pred = impact_jump_51(M, res.v_plus - vminus, model.values["e"], qd_dot)
    assert abs((V(res.v_plus) - V(vminus)) - pred) <= 1e-12 * max(abs(pred), 1e-12)
    assert pred > 0      # a violating impact: V jumps up
