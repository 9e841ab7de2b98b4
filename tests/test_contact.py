"""Contact mechanics of 000: LCP solvers, Delassus matrices (7)-(8), impact law (4)/(5), energy (39),
pre-loading (11)-(13), I/O linearization (24)-(25)."""
import casadi as ca
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from invctl.contact.lcp import is_p_matrix, lcp_sx, solve_lcp
from invctl.contact.mechanics import ContactSystem, energy_loss_39
from invctl.errors import ContactError, ModelError, PreloadInfeasible, RelativeDegreeError
from invctl.model import Gap, Model, ParamSet


def _rand_pd(rng, m):
    R = rng.normal(size=(m, m))
    return R @ R.T + 0.05 * np.eye(m)


# ----------------------------------------------------------------------- LCP
def test_lcp_solvers_agree_on_p_matrices():
    """Enumeration, Lemke and the branch-free symbolic solver give the same
    (unique) solution for random symmetric PD and non-symmetric P-matrices."""
    rng = np.random.default_rng(0)
    fns = {}
    for m in (1, 2, 3, 4, 7):
        for k in range(60):
            A = _rand_pd(rng, m)
            if k % 2:  # non-symmetric P-matrix: PD symmetric part plus a skew part
                S = rng.normal(size=(m, m))
                A = A + 0.5 * (S - S.T)
            b = rng.normal(size=m)
            s1 = solve_lcp(A, b, method="enumeration")
            s2 = solve_lcp(A, b, method="lemke")
            assert s1.unique and s1.residual < 1e-12
            np.testing.assert_allclose(s1.z, s2.z, atol=1e-10)
            if m <= 4:
                if m not in fns:
                    As, bs = ca.SX.sym("A", m, m), ca.SX.sym("b", m)
                    fns[m] = ca.Function("f", [As, bs], [lcp_sx(As, bs)])
                np.testing.assert_allclose(np.array(fns[m](A, b)).ravel(), s1.z, atol=1e-10)


def test_lcp_pgs_fallback_accuracy():
    """Beyond max_enum, the fixed PGS sweeps reach the exact solution on a well-conditioned SPD problem."""
    rng = np.random.default_rng(3)
    m = 6
    A = _rand_pd(rng, m) + 3 * np.eye(m)
    b = rng.normal(size=m)
    As, bs = ca.SX.sym("A", m, m), ca.SX.sym("b", m)
    z = np.array(ca.Function("f", [As, bs], [lcp_sx(As, bs, method="pgs", pgs_sweeps=80)])(A, b)).ravel()
    np.testing.assert_allclose(z, solve_lcp(A, b).z, atol=1e-9)


def test_p_matrix_check_and_non_unique():
    assert is_p_matrix(np.eye(3))
    assert not is_p_matrix(np.array([[1.0, 2.0], [2.0, 1.0]]))  # indefinite
    assert not is_p_matrix(np.array([[0.0, 1.0], [-1.0, 0.0]]) + 0.0)
    # a degenerate (dependent contacts) LCP is flagged as not unique
    sol = solve_lcp(np.ones((2, 2)), np.array([-1.0, -1.0]))
    assert sol.unique is False and sol.residual < 1e-12
    with pytest.raises(ContactError):
        solve_lcp(-np.eye(1), np.array([-1.0]), method="lemke")  # ray termination: no solution


# -------------------------------------------------------------- models
def _point_in_corner():
    """A unit point mass in a corner: gaps x >= 0, y >= 0 (two orthogonal contacts)."""
    P = ParamSet(["m", "e"])
    q, v = ca.SX.sym("q", 2), ca.SX.sym("v", 2)
    return Model("corner", q, v, P, {"m": 2.0, "e": 0.5}, M=P["m"] * ca.SX.eye(2), f=ca.SX.zeros(2),
                 B=ca.SX.zeros(2, 0), gaps=[Gap("x", q[0], "e"), Gap("y", q[1], "e")])


def _rod():
    """A planar rod (x, y, phi) whose two ends may touch the ground: gaps y -/+ (L/2) sin(phi)."""
    P = ParamSet(["m", "I", "L", "e"])
    q, v = ca.SX.sym("q", 3), ca.SX.sym("v", 3)
    M = ca.diag(ca.vertcat(P["m"], P["m"], P["I"]))
    half = 0.5 * P["L"]
    return Model("rod", q, v, P, {"m": 1.0, "I": 1.0 / 12, "L": 1.0, "e": 0.3}, M=M,
                 f=ca.vertcat(0, -9.81 * P["m"], 0), B=ca.SX.zeros(3, 0),
                 gaps=[Gap("left", q[1] - half * ca.sin(q[2]), "e"), Gap("right", q[1] + half * ca.sin(q[2]), "e")])


def test_simultaneous_impact_corner_and_rod():
    """Two simultaneous impacts: orthogonal contacts reflect each normal component
    by -e; the flat rod falling on both ends stops its vertical velocity with
    v_y+ = -e v_y- and no rotation (symmetric 2-impact)."""
    cs = ContactSystem(_point_in_corner())
    r = cs.impact([0.0, 0.0], [-1.0, -3.0])
    np.testing.assert_allclose(r.v_plus, [0.5, 1.5], atol=1e-14)
    assert r.involved.all()
    cs = ContactSystem(_rod())
    r = cs.impact([0.0, 0.0, 0.0], [0.2, -2.0, 0.0])
    np.testing.assert_allclose(r.v_plus, [0.2, 0.6, 0.0], atol=1e-13)
    np.testing.assert_allclose(r.p, [0.5 * 1.3 * 2.0] * 2, rtol=1e-12)
    assert r.predicted_jump is not None
    assert abs(r.kinetic_jump - r.predicted_jump) <= 1e-12 * abs(r.kinetic_jump)


@settings(max_examples=120, deadline=None)
@given(st.integers(0, 10_000), st.floats(0.0, 1.0), st.integers(1, 4))
def test_impact_energy_loss_matches_39_and_never_creates_energy(seed, e, m):
    """Moreau's law with a common e: T+ - T- equals -1/2 (1-e)/(1+e) sigma^T M sigma
    (000 (39)) to 1e-12 relative, and is never positive."""
    rng = np.random.default_rng(seed)
    n = m + 2
    P = ParamSet(["e"])
    q, v = ca.SX.sym("q", n), ca.SX.sym("v", n)
    Mn = _rand_pd(rng, n) + np.eye(n)
    Wn = rng.normal(size=(n, m))
    gaps = [Gap(f"g{i}", ca.mtimes(ca.DM(Wn[:, i]).T, q), "e") for i in range(m)]
    model = Model("rand", q, v, P, {"e": e}, M=ca.DM(Mn), f=ca.SX.zeros(n), B=ca.SX.zeros(n, 0), gaps=gaps)
    cs = ContactSystem(model)
    vm = rng.normal(size=n)
    r = cs.impact(np.zeros(n), vm, involved=np.ones(m, bool))
    sigma = r.v_plus - vm
    scale = max(1e-300, 0.5 * vm @ Mn @ vm)
    assert r.kinetic_jump <= 1e-13 * scale
    assert abs(r.kinetic_jump - energy_loss_39(sigma, Mn, e)) <= 1e-12 * scale
    U = Wn.T @ r.v_plus + e * (Wn.T @ vm)  # Newton's law (4) on the involved contacts
    assert np.all(U >= -1e-10) and np.all(np.abs(U * r.p) <= 1e-10)


def test_delassus_with_bilateral_constraints_eq8():
    """(8) computed by the projected inverse equals the null-space reduction
    W^T Z (Z^T M Z)^-1 Z^T W with Z spanning ker G (independent computation)."""
    P = ParamSet(["k"])
    q, v = ca.SX.sym("q", 4), ca.SX.sym("v", 4)
    rng = np.random.default_rng(5)
    Mn = _rand_pd(rng, 4) + np.eye(4)
    model = Model("bil", q, v, P, {"k": 1.0}, M=ca.DM(Mn), f=ca.SX.zeros(4), B=ca.SX.zeros(4, 0),
                  g=ca.vertcat(q[0] + q[1] ** 2, q[2] - q[3]),
                  gaps=[Gap("a", q[0] - 0.3 * q[2]), Gap("b", q[1] + ca.sin(q[3]))])
    cs = ContactSystem(model)
    q0 = np.array([0.1, 0.2, 0.3, 0.3])
    Dc = cs.delassus(q0)
    G = np.array(model.function("G")(q0, [1.0]))
    W = cs.gradients(q0)
    _, _, Vt = np.linalg.svd(G)
    Z = Vt[2:].T
    Dz = W.T @ Z @ np.linalg.solve(Z.T @ Mn @ Z, Z.T @ W)
    np.testing.assert_allclose(Dc, Dz, rtol=1e-12, atol=1e-14)
    assert cs.check_independence(q0) > 0


def test_dependent_contacts_violate_assumption_2():
    P = ParamSet(["m"])
    q, v = ca.SX.sym("q", 2), ca.SX.sym("v", 2)
    model = Model("dup", q, v, P, {"m": 1.0}, M=ca.SX.eye(2), f=ca.SX.zeros(2), B=ca.SX.zeros(2, 0),
                  gaps=[Gap("a", q[0]), Gap("b", 2 * q[0])])
    with pytest.raises(ContactError, match="Assumption 2"):
        ContactSystem(model).check_independence([0.0, 0.0])


def test_contact_lcp_resting_rod_forces():
    """Rod lying flat on the ground: contact LCP (7) shares the weight equally."""
    cs = ContactSystem(_rod())
    cf = cs.contact_forces([0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    np.testing.assert_allclose(cf.lam, [9.81 / 2, 9.81 / 2], rtol=1e-12)
    np.testing.assert_allclose(cf.acceleration, 0.0, atol=1e-12)


# ------------------------------------------------------------- pre-loading
def test_example3_closed_forms():
    """000 Example 3: D, E_hat, E_hat^+ and the tau giving lam = beta, in closed form."""
    import invctl_scenes.prismatic_clearance as scene
    from invctl.control.preload import preload_check, preload_law

    m1, m2, l = 1.3, 0.7, 0.05
    model = scene.build(actuators=2, m1=m1, m2=m2, l=l)
    q = [0.0, l]
    chk = preload_check(model, q, [0.0, 0.0], [0])
    np.testing.assert_allclose(chk.E_hat, [[-m2 / (m1 + m2), m1 / (m1 + m2)]], rtol=1e-14)
    np.testing.assert_allclose(chk.w_hat, [0.0], atol=1e-15)
    D = ContactSystem(model).delassus(q, [0])
    np.testing.assert_allclose(D, [[(m1 + m2) / (m1 * m2)]], rtol=1e-14)
    Ep = np.linalg.pinv(chk.E_hat)
    np.testing.assert_allclose(Ep.ravel(), (m1 + m2) / (m1**2 + m2**2) * np.array([-m2, m1]), rtol=1e-13)
    beta = 2.5
    law = preload_law(model, [0], beta=beta)
    u, _ = law.function(model)(q, [0.0, 0.0], 0.0, model.theta_values, law.values())
    np.testing.assert_allclose(np.array(u).ravel(),
                               [m2 * (m1 + m2) / (m1**2 + m2**2) * beta, -m1 * (m1 + m2) / (m1**2 + m2**2) * beta],
                               rtol=1e-13)
    cf = ContactSystem(model).contact_forces(q, [0.0, 0.0], np.array(u).ravel(), active=[0])
    np.testing.assert_allclose(cf.lam[0], beta, rtol=1e-13)


def test_preload_infeasible_cases():
    """Corollary 1 (p < m_u') and the rank condition of Lemma 1."""
    import invctl_scenes.prismatic_clearance as scene
    from invctl.control.preload import preload_check, preload_law

    one = scene.build(actuators=1)
    with pytest.raises(PreloadInfeasible, match="Corollary 1"):
        preload_check(one, [0.0, 0.05], [0.0, 0.0], [0, 1])
    with pytest.raises(PreloadInfeasible):
        preload_law(one, [0, 1], beta=1.0)
    # actuator on a body that does not touch the contact: E_hat = 0
    P = ParamSet(["m"])
    q, v = ca.SX.sym("q", 3), ca.SX.sym("v", 3)
    model = Model("far", q, v, P, {"m": 1.0}, M=ca.SX.eye(3), f=ca.SX.zeros(3), B=ca.DM([[1.0], [0.0], [0.0]]),
                  gaps=[Gap("c23", q[2] - q[1])])
    with pytest.raises(PreloadInfeasible, match="rank"):
        preload_check(model, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0])
    assert not preload_check(model, [0.0, 0.0, 0.0], [0.0] * 3, [0], raise_=False).feasible


def test_gear_example4_ehat():
    """000 Example 4: D matches the printed matrix for both f4 variants; the printed
    E_hat is reproduced with f4 = theta3 - theta2 + alpha4 (mesh-consistent) and
    NOT with f4 as printed (-theta3 - theta2 + alpha4), whose E_hat is derived by hand."""
    import invctl_scenes.gear_backlash as scene
    from invctl.control.preload import preload_check

    def gear_ehat(c4, J):
        model = scene.build(c4=c4, J1=J, J2=J, J3=J)
        q = scene.preloaded_configuration(model)
        return ContactSystem(model).delassus(q, [0, 3]), preload_check(model, q, np.zeros(3), [0, 3]).E_hat

    for c4 in (1.0, -1.0):
        D, E = gear_ehat(c4, J=0.02)
        np.testing.assert_allclose(D * 0.02, scene.PRINTED_D_TIMES_J, atol=1e-13)
    E_mesh = gear_ehat(1.0, J=0.02)[1]
    E_print = gear_ehat(-1.0, J=0.02)[1]
    np.testing.assert_allclose(E_mesh, scene.PRINTED_E_HAT, atol=1e-14)
    # by hand: D^-1 = J/3 [[2,1],[1,2]], grad f'^T M^-1 = 1/J [[-1,1,0],[0,-1,-1]]
    np.testing.assert_allclose(E_print, np.array([[-2, 1, -1], [-1, -1, -2]]) / 3, atol=1e-14)


# ---------------------------------------------------------------- juggling
def test_io_linearization_gives_ydd_equal_taubar_plus_delassus_lambda():
    """(24)-(25): with tau = Dcal^+ (tau_bar + Fcal), y'' = tau_bar + Mcal lam for any lam
    (checked with the model's own accelerations at random states)."""
    import invctl_scenes.prismatic_clearance as scene
    from invctl.control.juggling import io_decoupling_check, io_terms

    model = scene.build(actuators=2)
    Dcal, Mcal, Fcal, y, yd = io_terms(model, [0])
    cs = ContactSystem(model)
    tb = ca.SX.sym("tb")
    lam = ca.SX.sym("lam")
    tau = ca.mtimes(ca.pinv(Dcal), tb + Fcal)
    a = ca.solve(model.M, model.f + ca.mtimes(model.B, tau) + cs.W[:, 0] * lam)
    ydd = ca.mtimes(cs.W[:, 0].T, a) + cs.Wdot_v[0]
    f = ca.Function("f", [model.q, model.v, tb, lam, model.theta], [ydd - tb - Mcal * lam])
    rng = np.random.default_rng(1)
    for _ in range(10):
        r = f(rng.normal(size=2), rng.normal(size=2), rng.normal(), abs(rng.normal()), model.theta_values)
        assert abs(float(r)) < 1e-12
    one = scene.build(actuators=1)
    io_decoupling_check(one, [0.0, 0.05], [0])  # rank 1: fine
    P = ParamSet(["m"])
    q, v = ca.SX.sym("q", 3), ca.SX.sym("v", 3)
    far = Model("far", q, v, P, {"m": 1.0}, M=ca.SX.eye(3), f=ca.SX.zeros(3), B=ca.DM([[1.0], [0.0], [0.0]]),
                gaps=[Gap("c23", q[2] - q[1])])
    with pytest.raises(RelativeDegreeError):
        io_decoupling_check(far, [0.0, 0.0, 0.0], [0])


def test_contact_system_rejects_models_without_gaps():
    P = ParamSet(["m"])
    q, v = ca.SX.sym("q", 1), ca.SX.sym("v", 1)
    with pytest.raises(ModelError):
        ContactSystem(Model("free", q, v, P, {"m": 1.0}, M=ca.SX.eye(1), f=ca.SX.zeros(1), B=ca.SX.zeros(1, 0)))


# ------------------------------------------------------------ default records of long runs
@pytest.mark.parametrize("scene, values, controller", [
    ("bouncing_ball", {"h": 1e-5, "t_end": 2.0}, None),        # 200000 steps, energy balance
    ("prismatic_clearance", {"h": 1e-5, "t_end": 1.0}, "pd"),  # 100000 steps, V (37) of PD (36)
])
def test_long_contact_runs_are_saved_decimated_by_default(scene, values, controller, tmp_path, capsys):
    """A long run's saved file holds at most DEFAULT_SAMPLES (+1) samples by default and every step with
    --record-every 1; impacts, largest penetration and the energy / V increases agree between both."""
    from invctl.cli import main
    from invctl.simulate.contact_record import ContactTrajectory
    from invctl.studies.contact import DEFAULT_SAMPLES

    sets = [a for k, v in values.items() for a in ("--set", f"{k}={v}")] + (["--controller", controller]
                                                                            if controller else [])
    runs = {}
    for tag, extra in (("default", []), ("full", ["--record-every", "1"])):
        out = tmp_path / f"{tag}.npz"
        assert main(["simulate", scene, *sets, *extra, "--quiet", "--out", str(out)]) == 0
        runs[tag] = ContactTrajectory.load(out)
    text = capsys.readouterr().out
    steps = round(values["t_end"] / values["h"])
    d, f = runs["default"], runs["full"]
    assert f.t.size == steps + 1 and f.complete
    assert d.t.size <= DEFAULT_SAMPLES + 2 and not d.complete and d.t.size > DEFAULT_SAMPLES / 2
    assert "--record-every 1 records all" in text
    np.testing.assert_array_equal(d.impact_times, f.impact_times)
    assert d.impact_times.size >= 2
    assert d.max_gap_violation == f.max_gap_violation
    assert d.max_energy_increase == f.max_energy_increase and d.max_V_increase == f.max_V_increase
    np.testing.assert_array_equal(d.q[:, -1], f.q[:, -1])
    np.testing.assert_array_equal(d.q, f.q[:, d.stats["step_index"]])  # recorded samples are steps of the run


def test_rest_time_is_the_first_sample_after_the_last_unsettled_one():
    """A hand-made record: the contact closes at sample 2, bounces (U_n = 0.5) at sample 3 and stays still from
    sample 4 on, so it rests from t[4]; a record that is unsettled at its end never rests (nan)."""
    from invctl.simulate.contact_record import ContactTrajectory

    t = 0.1 * np.arange(8)
    gaps = np.array([[1.0, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]])
    Un = np.array([[-1.0, -1.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.0]])
    z = np.zeros((1, 8))
    tr = ContactTrajectory(t, z, z, z, z.astype(bool), gaps, t * 0, t * 0, 0.1, stats={"Un": Un})
    assert tr.rest_time() == t[4]
    tr.stats["Un"] = np.array([[-1.0, -1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.5]])
    assert np.isnan(tr.rest_time())
    tr.stats["Un"] = np.zeros((1, 8))
    assert ContactTrajectory(t, z, z, z, z.astype(bool), 0 * gaps, t * 0, t * 0, 0.1,
                             stats={"Un": np.zeros((1, 8))}).rest_time() == 0.0


def test_preload_with_as_many_inputs_as_contacts_is_feasible():
    """p = m_u' = 1: an actuated mass touching a free one (gap q2 - q1) with E_hat of full rank: one input
    suffices for one contact (000 Corollary 1 needs p >= m_u', Lemma 1 rank E_hat = m_u')."""
    from invctl.control.preload import preload_check

    P = ParamSet(["m"])
    q, v = ca.SX.sym("q", 2), ca.SX.sym("v", 2)
    model = Model("pair", q, v, P, {"m": 1.0}, M=ca.SX.eye(2), f=ca.SX.zeros(2), B=ca.DM([[1.0], [0.0]]),
                  gaps=[Gap("c12", q[1] - q[0])])
    chk = preload_check(model, [0.0, 0.0], [0.0, 0.0], [0], raise_=False)
    assert chk.feasible and chk.rank == 1
