"""Stable inversion (003 Sect. 4, 6): manipulator, minimum-phase arm, convergence, I/O, bad input."""
import casadi as ca
import numpy as np
import pytest

import invctl_scenes.manipulator as scene
import invctl_scenes.two_link_arm as arm
from invctl.errors import BoundaryConditionError, InversionFailed, ReferenceSignalError
from invctl.inversion import Inverse, invert, resolve_selection, servo_model
from invctl.studies.tracking import invert_tracking
from invctl.reference import Reference, poly9_timing_law
from invctl.testing import assert_inverts


@pytest.fixture(scope="module")
def model():
    """The 'guess' parameters (m3 = 0.5 kg, c = 5, D = 0.05): the rates and sizes quoted below were measured on
    them (internal eigenvalues -19.64, 24.44)."""
    return scene.build(**scene.PRESETS["guess"])


HAND = {k: scene.INVERSION[k] for k in ("T0", "Tf", "start", "end")}


@pytest.fixture(scope="module")
def ref(model):
    return scene.reference(model)


@pytest.fixture(scope="module")
def inv160(model, ref):
    # the former hand setup (the scene now derives selection and horizon): gamma(Tf) = 0, [T0, Tf] = [-1, 2]
    return invert_tracking(scene.SCENE, model, ref, N=160, backend="newton", **HAND)


def test_manipulator_inverse_reproduces_reference(model, ref, inv160):
    # forward simulation (CVODES, independent of the collocation) under u_ff; HS at N = 160
    # (80 intervals on [t0, tf]) measured 1.1e-7; the target is 1e-6
    rep = assert_inverts(model, inv160, ref, tol=1e-6)
    assert rep["error"] < 1e-6
    res = inv160.diagnostics["residuals"]
    assert res["position"] < 1e-5 and res["velocity_mesh"] < 1e-4


def test_forward_check_cvodes_agrees_with_scipy_dop853(model, ref, inv160):
    # the compiled CVODES check (feedforward as exact piecewise polynomials) against scipy DOP853 with a
    # Python right-hand side: both integrate to 1e-12, so the measured output errors (~1e-7) agree to
    # well below 1 % (measured 3e-10 apart); the sampled trajectories agree to ~1e-9
    fast = assert_inverts(model, inv160, ref, tol=1e-6)
    slow = assert_inverts(model, inv160, ref, tol=1e-6, method="DOP853")
    assert fast["method"] == "cvodes" and slow["method"] == "DOP853"
    assert abs(fast["error"] - slow["error"]) < 0.01 * slow["error"]
    np.testing.assert_allclose(fast["t"], slow["t"])
    assert np.max(np.abs(fast["y"] - slow["y"])) < 1e-8


def test_pre_actuation_and_causal_feedforward(inv160):
    t_pre = np.linspace(inv160.T0, inv160.t0, 300, endpoint=False)
    u_pre = inv160.u(t_pre)
    # non-minimum phase: the bounded inverse acts before t0 (growing like exp(24 t) towards t0)
    assert np.max(np.abs(u_pre)) > 0.1
    assert np.max(np.abs(u_pre[:, :50])) < 1e-3 * np.max(np.abs(u_pre))
    assert np.all(inv160.u_causal(t_pre) == 0)
    t_post = np.linspace(inv160.t0, inv160.Tf, 50)
    np.testing.assert_array_equal(inv160.u_causal(t_post), inv160.u(t_post))
    assert inv160.u_causal(t_post).shape == (2, 50)


def test_equilibria_and_boundary_values(model, ref, inv160):
    q0 = scene.initial_configuration(model)
    np.testing.assert_allclose(inv160.q(inv160.T0).ravel(), q0, atol=1e-12)
    np.testing.assert_allclose(model.evaluate("h", inv160.q(inv160.Tf).ravel()).ravel(), ref(inv160.Tf).ravel(),
                               atol=1e-6)
    assert abs(inv160.q(inv160.Tf)[4, 0]) < 1e-12  # gamma(Tf) = 0 is the end condition


def test_ipopt_and_newton_agree(model, ref):
    a = invert_tracking(scene.SCENE, model, ref, N=60, backend="ipopt")
    b = invert_tracking(scene.SCENE, model, ref, N=60, backend="newton")
    assert a.diagnostics["status"] == "Solve_Succeeded"
    assert a.diagnostics["iterations"] <= 20
    # the same square system solved two ways: agree to the solvers' tolerances
    np.testing.assert_allclose(a.X_mesh, b.X_mesh, atol=1e-7)
    # IPOPT's default on square systems (exact zero Hessian, MUMPS without scaling) against the
    # limited-memory Hessian with IPOPT's own MUMPS defaults: the same Newton iterates
    c = invert_tracking(scene.SCENE, model, ref, N=60, backend="ipopt", ipopt_options={
        "ipopt.hessian_approximation": "limited-memory", "ipopt.mumps_scaling": 77,
        "ipopt.mumps_permuting_scaling": 7, "ipopt.mumps_pivot_order": 7, "ipopt.nlp_scaling_method": "gradient-based"})
    assert c.diagnostics["status"] == "Solve_Succeeded"
    np.testing.assert_allclose(a.X_mesh, c.X_mesh, atol=1e-7)


def test_convergence_order_hermite_simpson(model, ref):
    # error of u_ff against a fine Legendre-4 solution at the common mesh points (t0 and tf are
    # mesh points of every mesh, so the jumps of the 4th derivative of y_ref lie on interval ends)
    fine = invert_tracking(scene.SCENE, model, ref, N=300, scheme="legendre4", backend="newton")
    errs = []
    Ns = [60, 120, 240]
    inv = t = None
    for N in Ns:
        inv = invert_tracking(scene.SCENE, model, ref, N=N, backend="newton", warm_start=inv)
        t = inv.t_mesh if t is None else t  # the default meshes are nested (15/30/15 intervals at N = 60)
        errs.append(np.max(np.abs(inv.u(t) - fine.u(t))))
    order = np.polyfit(np.log(Ns), np.log(errs), 1)[0]
    # Hermite-Simpson is 4th order for the states; accept 3.5..5 (pre-asymptotic at N = 60)
    assert -5.0 < order < -3.5, (errs, order)


def test_save_load_roundtrip(tmp_path, inv160, ref):
    path = tmp_path / "inv.npz"
    inv160.to_npz(str(path), dt=0.01)
    back = Inverse.load(str(path))
    t = np.linspace(-1, 2, 77)
    np.testing.assert_allclose(back.X(t), inv160.X(t), rtol=0, atol=1e-14)
    np.testing.assert_allclose(back.u_causal(t), inv160.u_causal(t), atol=1e-14)
    assert back.t0 == inv160.t0 and back.Tf == inv160.Tf
    with np.load(path) as z:
        for key in ("t", "q", "v", "lam", "mu", "u", "y_ref"):
            assert key in z
        assert z["q"].shape == (5, z["t"].size) and z["lam"].shape == (2, z["t"].size)
        np.testing.assert_allclose(z["y_ref"], ref(z["t"]), atol=1e-14)
        assert abs(z["t"][1] - z["t"][0] - 0.01) < 1e-12


def _zero_dynamics_reference(md, rf, t):
    """Minimum-phase arm, y = q1 colocated: integrate the zero dynamics directly
    (q1 = y_ref, M[1,:] q'' = f_2) and u = M[0,:] q'' - f_1 (no collocation involved)."""
    from scipy.integrate import solve_ivp

    Mf, ff = md.function("M"), md.function("f")
    th = md.theta_values

    def state(tt, z):
        y, yd, ydd = (rf(tt, k).ravel()[0] for k in range(3))
        q, v = np.array([y, z[0]]), np.array([yd, z[1]])
        M, f = np.array(Mf(q, th)), np.array(ff(q, v, th)).ravel()
        q2dd = (f[1] - M[1, 0] * ydd) / M[1, 1]
        return q, v, np.array([ydd, q2dd]), M, f

    sol = solve_ivp(lambda tt, z: [z[1], state(tt, z)[2][1]], (t[0], t[-1]), [0.0, 0.0], method="DOP853",
                    rtol=1e-12, atol=1e-12, dense_output=True)
    u = []
    for tt in t:
        q, v, a, M, f = state(tt, sol.sol(tt))
        u.append(M[0] @ a - f[0])
    return sol.sol(t)[0], np.array(u)


@pytest.mark.parametrize("scheme,N", [("hermite-simpson", 120), ("legendre3", 60), ("radau3", 80)])
def test_minimum_phase_arm_matches_direct_integration(scheme, N):
    md = arm.build()
    rf = arm.reference(md)
    inv = invert(md, rf, T0=-0.5, Tf=2.0, N=N, scheme=scheme, start={"q": "all", "v": "all", "u": "all"},
                 end={}, backend="newton")
    t = np.linspace(-0.5, 2.0, 200)
    q2, u = _zero_dynamics_reference(md, rf, t)
    # minimum phase: no pre-actuation, and the BVP solution is the forward one
    assert np.max(np.abs(inv.u(t[t < 0]) - u[t < 0])) < 1e-9
    np.testing.assert_allclose(inv.q(t)[1], q2, atol=2e-5)
    np.testing.assert_allclose(inv.u(t)[0], u, atol=2e-4 * max(1, np.max(np.abs(u))))
    assert_inverts(md, inv, rf, tol=2e-5)


def test_boundary_selection_errors(model):
    sv = servo_model(model)
    with pytest.raises(BoundaryConditionError, match=r"needs n0 \+ nf = 2n \+ l \+ p \+ m .* 14"):
        resolve_selection(sv, {"q": "all"}, {"u": "all"})
    with pytest.raises(BoundaryConditionError, match="unknown entry 'delta'"):
        resolve_selection(sv, {"q": ["delta"]}, {})
    with pytest.raises(BoundaryConditionError, match="unknown block"):
        resolve_selection(sv, {"w": "all"}, {})
    sel = resolve_selection(sv, scene.BOUNDARY_PAPER["start"], scene.BOUNDARY_PAPER["end"])
    assert len(sel.start) == 10 and len(sel.end) == 4
    with pytest.raises(BoundaryConditionError):
        invert_tracking(scene.SCENE, model, scene.reference(model), end={"q": ["gamma"], "u": "all"}, N=40, backend="newton")


def test_reference_outside_workspace(model):
    t = ca.SX.sym("t")
    y0 = scene.reference(model)(0.0).ravel()
    # s2 pushed 5 m away: the loop L1 cos(alpha) = s2 + d - L2/2 cos(beta) cannot close
    expr = ca.vertcat(y0[0] + 5.0 * poly9_timing_law(t, 0, 1), y0[1])
    bad = Reference(t, expr, 0.0, 1.0, smoothness=4)
    with pytest.raises(ReferenceSignalError, match="reachable workspace"):
        invert_tracking(scene.SCENE, model, bad, N=40, backend="newton")


def test_reference_not_smooth_enough(model):
    t = ca.SX.sym("t")
    y0 = scene.reference(model)(0.0).ravel()
    s = ca.if_else(t <= 0, 0, ca.if_else(t >= 1, 1, 3 * t**2 - 2 * t**3))  # C^1 only
    rough = Reference(t, ca.vertcat(y0[0] - 0.1 * s, y0[1]), 0.0, 1.0, smoothness=1)
    with pytest.raises(ReferenceSignalError, match="W\\^\\{3,inf\\}"):
        invert_tracking(scene.SCENE, model, rough, N=40)


def test_solver_failure_keeps_last_iterate(model, ref):
    with pytest.raises(InversionFailed) as exc:
        invert_tracking(scene.SCENE, model, ref, N=40, max_iter=1, continuation=False)
    err = exc.value
    assert isinstance(err.partial, Inverse)
    assert err.diagnostics["status"] == "Maximum_Iterations_Exceeded"
    assert err.partial.X_mesh.shape == (14, 41)
    with pytest.raises(InversionFailed, match="Newton|newton"):
        invert_tracking(scene.SCENE, model, ref, N=40, max_iter=1, backend="newton", continuation=False)


def test_horizon_must_contain_transition(model, ref):
    with pytest.raises(ReferenceSignalError, match="must contain"):
        invert_tracking(scene.SCENE, model, ref, T0=0.5, N=40)


def test_mesh_refinement_reaches_tolerance(model, ref):
    inv = invert_tracking(scene.SCENE, model, ref, N=60, backend="newton", tol=1e-7)
    meshes = inv.diagnostics["meshes"]
    assert meshes[-1]["error"] <= 1e-7 and len(meshes) >= 2
    assert_inverts(model, inv, ref, tol=1e-7)


def test_invert_command_json(tmp_path):
    out = tmp_path / "traj.npz"
    from invctl.studies import commands

    res = commands.invert("manipulator", N=60, backend="newton", out=str(out), dt=0.005, quiet=True)
    for key in ("status", "iterations", "build_s", "solve_s", "max_output_error", "N"):
        assert key in res.data
    assert res.data["N"] == 60 and res.data["status"] == "Solve_Succeeded"
    assert res.data["max_output_error"] < 1e-3
    assert out.exists()


def test_compiled_evaluation_matches_virtual_machine(model, ref, inv160):
    # C code generated from the same SX functions, compiled once and cached on disk
    inv = invert_tracking(scene.SCENE, model, ref, N=160, backend="ipopt", compiled=True, **HAND)
    assert inv.diagnostics["compiled"] and inv.diagnostics["status"] == "Solve_Succeeded"
    np.testing.assert_allclose(inv.X_mesh, inv160.X_mesh, atol=1e-8)


def test_input_energy_selects_among_non_unique_inverses(model, ref):
    # dropping gamma(Tf) = 0 leaves a one-parameter family of inverses; IPOPT picks the one of least
    # input energy, so its energy cannot exceed that of the square problem's solution (which is
    # feasible for the relaxed problem); quadrature differences are O(h^4), tolerance 1e-3 relative
    sq = invert_tracking(scene.SCENE, model, ref, N=30, **HAND)
    free = invert_tracking(scene.SCENE, model, ref, N=30, **{**HAND, "end": {}}, allow_underdetermined=True)
    t = np.linspace(-1, 2, 3001)
    e_sq = np.trapezoid(np.sum(sq.u(t) ** 2, axis=0), t)
    e_free = np.trapezoid(np.sum(free.u(t) ** 2, axis=0), t)
    assert e_free <= e_sq * (1 + 1e-3)
    assert free.diagnostics["residuals"]["position"] < 1e-4


def test_plot(tmp_path, inv160):
    fig = inv160.plot(str(tmp_path / "inv.png"))
    assert (tmp_path / "inv.png").stat().st_size > 1000
    assert len(fig.axes) == 3


def test_rebuilt_model_with_other_parameters_shares_the_nlp(model, ref):
    # a scene rebuilt with other values shares the (structural) caches but must use its own values
    heavy = scene.build(**{**scene.PRESETS["guess"], "m3": 0.8})
    a = invert_tracking(scene.SCENE, heavy, scene.reference(heavy), N=80, backend="newton")
    b = invert_tracking(scene.SCENE, model.with_params(m3=0.8), ref, N=80, backend="newton")
    np.testing.assert_allclose(a.X_mesh, b.X_mesh, atol=1e-9)
    base = invert_tracking(scene.SCENE, model, ref, N=80, backend="newton")
    assert np.max(np.abs(a.u(np.linspace(0, 1, 50)) - base.u(np.linspace(0, 1, 50)))) > 1e-2
    assert_inverts(heavy, a, scene.reference(heavy), tol=1e-5)


def test_paper_selection_is_rank_deficient_in_the_stabilized_formulation(model, ref):
    # 003 Sect. 6 fixes lam2 and u at Tf. With every unknown differentiated and the invariants
    # Baumgarte-stabilized, the linearized inverse model at the equilibria has 12 drift modes (rate
    # -omega) + the stable internal mode (-19.6/s) decaying forward and one growing mode (+24.4/s):
    # 13 conditions belong at T0 and 1 at Tf. On the 2-dim tangent space of the invariant manifold at
    # Tf the paper's 4 end conditions have rank 2 (2 exactly redundant), on the growing mode rank 1.
    from invctl.inversion import dichotomy
    from invctl.inversion.schemes import get_scheme
    from invctl.inversion.cache import transcription

    sv = servo_model(model)
    inv = invert_tracking(scene.SCENE, model, ref, N=40, backend="newton")
    Y = sv.reference_samples(ref, np.array([inv.T0, inv.Tf]))
    E0, Ef = inv.X(inv.T0)[:, 0], inv.X(inv.Tf)[:, 0]
    paper = resolve_selection(sv, scene.BOUNDARY_PAPER["start"], scene.BOUNDARY_PAPER["end"])
    ours = resolve_selection(sv, scene.BOUNDARY["start"], scene.BOUNDARY["end"])
    dp = dichotomy(sv, paper, E0, Y[:, :1], Ef, Y[:, 1:], model.theta_values)
    do = dichotomy(sv, ours, E0, Y[:, :1], Ef, Y[:, 1:], model.theta_values)
    assert (dp["decaying"], dp["growing"], dp["neutral"], dp["tangent_dim"]) == (13, 1, 0, 2)
    assert (dp["n_start"], dp["rank_start"], dp["n_end"], dp["rank_end"], dp["rank_end_tangent"]) == (10, 10, 4, 1, 2)
    assert dp["well_posed"] is False and do["well_posed"] is True
    # independent of the mode analysis: the collocation Jacobian at the solution with the paper's
    # boundary rows in place of ours is numerically singular (3 singular values ~exp(-rate*3 s)),
    # ours is not
    tr = transcription(sv, ours, get_scheme("hermite-simpson"), 40, 0.0, compiled=False)
    x = tr.pack(inv.X(inv.t_mesh), None)
    p = tr.parameters(inv.t_mesh, sv.reference_samples(ref, tr.sample_times(inv.t_mesh)), model.theta_values, E0, Ef)
    J = tr.residual_and_jacobian(x, p)[1].toarray()
    nb = sv.layout.nx
    rows = np.zeros((nb, J.shape[1]))
    rows[np.arange(10), list(paper.start)] = 1.0
    rows[10 + np.arange(4), [40 * nb + i for i in paper.end]] = 1.0
    s_ours = np.linalg.svd(J, compute_uv=False)
    s_paper = np.linalg.svd(np.vstack([J[:-nb], rows]), compute_uv=False)
    assert s_ours[-1] / s_ours[0] > 1e-8
    assert s_paper[-1] / s_paper[0] < 1e-12 and s_paper[-3] / s_paper[0] < 1e-9
    with pytest.raises(BoundaryConditionError, match="13 modes that decay forward"):
        invert_tracking(scene.SCENE, model, ref, N=40, backend="newton", **scene.BOUNDARY_PAPER)


def test_dichotomy_eigenvalues_from_its_schur_forms_equal_lapack_eigvals(model, ref):
    # the check reads the spectra off the ordered real Schur forms it needs anyway; against an
    # independent general eigensolver (LAPACK dgeev) on the manipulator's ends and on random
    # matrices with complex pairs
    import scipy.linalg as sla

    from invctl.inversion import dichotomy
    from invctl.inversion.boundary import _schur_eigenvalues, tangent_dynamics

    def same(a, b):
        return np.allclose(np.sort_complex(np.round(a, 9)), np.sort_complex(np.round(b, 9)), atol=1e-9)

    rng = np.random.default_rng(3)
    for n in (1, 2, 5, 14):
        A = rng.standard_normal((n, n))
        assert same(_schur_eigenvalues(sla.schur(A, output="real")[0]), np.linalg.eigvals(A))
    sv = servo_model(model)
    inv = invert_tracking(scene.SCENE, model, ref, N=40, backend="newton")
    Y = sv.reference_samples(ref, np.array([inv.T0, inv.Tf]))
    E0, Ef = inv.X(inv.T0)[:, 0], inv.X(inv.Tf)[:, 0]
    d = dichotomy(sv, resolve_selection(sv, scene.BOUNDARY["start"], scene.BOUNDARY["end"]), E0, Y[:, :1], Ef,
                  Y[:, 1:], model.theta_values)
    for ev, X, Yk in ((d["eigenvalues_start"], E0, Y[:, :1]), (d["eigenvalues_end"], Ef, Y[:, 1:])):
        assert same(ev, np.linalg.eigvals(tangent_dynamics(sv, X, Yk, model.theta_values)[0]))
    assert d["decaying"] == int(np.sum(d["eigenvalues_start"].real < -1e-3))


@pytest.mark.parametrize("scheme,N", [("hermite-simpson", 40), ("legendre3", 12), ("radau2", 16)])
def test_compiled_evaluators_match_numpy_assembly(model, ref, inv160, scheme, N):
    # the Newton backend's buffered CasADi residual/Jacobian against the independent numpy assembly
    # (mapped right-hand side + einsum), and the banded LU against SuperLU on that Jacobian
    import scipy.sparse.linalg as spl

    from invctl.inversion.schemes import get_scheme
    from invctl.inversion.cache import transcription

    sv = servo_model(model)
    sel = resolve_selection(sv, scene.BOUNDARY["start"], scene.BOUNDARY["end"])
    tr = transcription(sv, sel, get_scheme(scheme), N, 0.0, compiled=False)
    t_mesh = np.linspace(inv160.T0, inv160.Tf, N + 1)
    rng = np.random.default_rng(3)
    Xc = inv160.X(tr.collocation_times(t_mesh)) if tr.n_col else None
    x = tr.pack(inv160.X(t_mesh), Xc) + 1e-3 * rng.standard_normal(tr.nX)
    E0, Ef = inv160.X(inv160.T0)[:, 0], inv160.X(inv160.Tf)[:, 0]
    p = tr.parameters(t_mesh, sv.reference_samples(ref, tr.sample_times(t_mesh)), model.theta_values, E0, Ef)
    residual, residual_and_jacobian = tr.evaluators(buffered=True)
    g_np, J_np = tr.residual_and_jacobian(x, p)
    g, J = residual_and_jacobian(x, p)
    assert np.max(np.abs(residual(x, p) - g_np)) < 1e-12 * max(1.0, np.max(np.abs(g_np)))
    assert np.max(np.abs(g - g_np)) < 1e-12 * max(1.0, np.max(np.abs(g_np)))
    assert abs(J - J_np).max() < 1e-12 * abs(J_np).max()
    band = tr.banded_pattern()
    assert band.kl + band.ku < 6 * tr.nx * max(1, tr.n_col // N + 1)  # time order makes it banded
    assert band.worthwhile == (scheme == "hermite-simpson")
    b = rng.standard_normal(tr.nX)
    x_band = band.factor(J.data).solve(b)
    x_lu = spl.splu(J.tocsc(), permc_spec="COLAMD").solve(b)
    assert np.linalg.norm(J @ x_band - b) < 1e-9 * np.linalg.norm(b)
    assert np.allclose(x_band, x_lu, rtol=1e-7, atol=1e-9 * np.max(np.abs(x_lu)))


def test_banded_lu_random_and_singular():
    import scipy.sparse as sps

    from invctl.inversion.banded import BandedPattern

    rng = np.random.default_rng(0)
    n, w = 300, 5
    A = sps.diags([rng.standard_normal(n - abs(k)) for k in range(-w, w + 1)], list(range(-w, w + 1)), format="csc")
    perm_r, perm_c = rng.permutation(n), rng.permutation(n)
    B = A[perm_r][:, perm_c].tocsc()  # scrambled: the column order recovers the band
    B.sort_indices()
    pat = BandedPattern(B.indices, B.indptr, n, col_order=np.argsort(perm_c))
    assert pat.kl <= 2 * w and pat.ku <= 2 * w
    b = rng.standard_normal(n)
    x = pat.factor(B.data).solve(b)
    assert np.linalg.norm(B @ x - b) < 1e-10 * np.linalg.norm(b) * np.linalg.cond(A.toarray())
    cols = np.repeat(np.arange(n), np.diff(B.indptr))
    with pytest.raises(RuntimeError, match="singular"):  # same pattern, column 7 all zero
        pat.factor(np.where(cols == 7, 0.0, B.data))


def test_newton_banded_and_superlu_agree(model, ref):
    from invctl.inversion import square as S
    from invctl.inversion.cache import servo_model

    a = invert_tracking(scene.SCENE, model, ref, N=60, backend="newton")
    orig = S._newton
    try:
        S._newton = lambda *args, **kw: orig(*args, **dict(kw, banded=False))
        for tr in servo_model(model, "baumgarte").transcriptions.values():
            tr._lu = None
        b = invert_tracking(scene.SCENE, model, ref, N=60, backend="newton")
    finally:
        S._newton = orig
    t = np.linspace(a.T0, a.Tf, 301)
    assert np.max(np.abs(a.q(t) - b.q(t))) < 1e-9 and np.max(np.abs(a.u(t) - b.u(t))) < 1e-7


def test_batched_equilibria_match_pointwise_continuation(model, ref):
    # the quasi-static guess solves every 4th point by continuation and the rest in one batched Newton;
    # the pointwise Gauss-Newton continuation over all points is the reference
    from invctl.inversion.cache import equilibrium_solver as _equilibrium_solver
    from invctl.inversion.guess import quasi_static_guess

    times = np.linspace(-1.0, 2.0, 47)
    G = quasi_static_guess(model, ref, times, np.zeros(model.n))
    eq, n = _equilibrium_solver(model), model.n
    w, W = None, []
    for t in times:
        X, _ = eq.solve(ref(t).ravel(), guess_q=np.zeros(n) if w is None else None, guess_w=w)
        w = np.concatenate([X[:n], X[2 * n:]])
        W.append(w)
    W = np.array(W).T
    assert np.max(np.abs(G[:n] - W[:n])) < 1e-10 and np.max(np.abs(G[2 * n:] - W[n:])) < 1e-8
    with pytest.raises(ValueError, match="distinct"):
        quasi_static_guess(model, ref, np.array([0.0, 0.5, 0.5 + 1e-15, 1.0]), np.zeros(n))
