"""Automatic feedback design for the funnel controller (48) of 003 Sect. 5.

Independent references: controllability indices against rank increments of the controllability
matrix; the new output (41) on synthetic (Q~, P~, S~) in Brunovsky form with known indices (zero
conditions and stacked matrix exact to round-off: 1e-12); the analytic high-gain construction whose
symmetric part is I by design; (A1) margins against LinearizedInternal.check_A1 (analysis layer);
start errors against hand-written formulas; closed loops on mismatched plants (manipulator m3 x 1.2,
cart-pole and gantry with a 20 % heavier pendulum, two-link arm m2 x 1.2) inside every funnel.
"""
import math

import casadi as ca
import numpy as np
import pytest

import invctl_scenes.cartpole as cartpole
import invctl_scenes.manipulator as scene
from invctl.studies.tracking import tracking_linearization
import invctl_scenes.two_link_arm as arm
from invctl.analysis import internal_dynamics, linearize_internal, schur_complement
from invctl.control.funnel_design import DesignRules, design_funnel_feedback, reference_time_scale
from invctl.control.funnel_nmp import NMPFunnelController
from invctl.control.new_output import a1_margin_along, controllability_indices, design_new_output
from invctl.errors import FeedbackDesignError, ParameterError
from invctl.model import Model, OperatingRegion, ParamSet
from invctl.reference import Reference, poly9_timing_law
from invctl.simulate.closed_loop import ClosedLoop


# --------------------------------------------------------------------------- synthetic (Q~, P~, S~)
def _brunovsky(chains, rng, feedback=True):
    """(Q, P) with controllability indices ``chains`` (per input column), in random coordinates."""
    k, m = sum(chains), len(chains)
    A, B = np.zeros((k, k)), np.zeros((k, m))
    off = 0
    for col, c in enumerate(chains):
        for j in range(c - 1):
            A[off + j, off + j + 1] = 1.0
        B[off + c - 1, col] = 1.0
        off += c
    if feedback:
        A = A + B @ rng.normal(size=(m, k))        # indices are invariant under feedback
    T = rng.normal(size=(k, k)) + 3 * np.eye(k)
    Ti = np.linalg.inv(T)
    return T @ A @ Ti, T @ B


def _spd(m, rng):
    X = rng.normal(size=(m, m))
    return X @ X.T + m * np.eye(m)


def _zero_residual(no, Qt, Pt):
    return max([np.abs(no.K[i] @ np.linalg.matrix_power(Qt, j) @ Pt).max()
                for i in range(len(no.k_i)) for j in range(no.k_i[i] - 1)] + [0.0])


@pytest.mark.parametrize("chains", [(3, 1), (2, 2), (1, 3), (2, 1, 1)])
def test_controllability_indices_against_rank_increments(chains):
    """#{l : kappa_l >= j} = rank C_j - rank C_(j-1), C_j = [P, QP, .., Q^(j-1) P] (the dual definition)."""
    rng = np.random.default_rng(sum(chains) * 7 + len(chains))
    Q, P = _brunovsky(chains, rng)
    ind = controllability_indices(Q, P)
    assert ind == chains
    ranks = [0] + [np.linalg.matrix_rank(np.hstack([np.linalg.matrix_power(Q, i) @ P for i in range(j)]))
                   for j in range(1, sum(chains) + 1)]
    for j in range(1, sum(chains) + 1):
        assert sum(1 for x in ind if x >= j) == ranks[j] - ranks[j - 1]
    # mixing the inputs changes the per-column indices but not the (Kronecker) multiset
    V = rng.normal(size=(len(chains), len(chains)))
    assert sorted(controllability_indices(Q, P @ V)) == sorted(chains)


def test_identity_construction_on_brunovsky_pair():
    """Indices (3, 1): q = 2 rows with k = (3, 1); e_1 is reachable with k_1 = 3, e_2 with k_2 = 1, so the
    stacked matrix is I_2 (to round-off) and with S~ SPD the margin is lambda_min(S~)."""
    rng = np.random.default_rng(1)
    Qt, Pt = _brunovsky((3, 1), rng)
    S = _spd(2, rng)
    pts = np.array([_spd(2, rng) for _ in range(5)])
    no = design_new_output(Qt, Pt, S, S_points=pts)
    assert no.construction == "identity" and no.k_i == (3, 1) and no.pairing == (0, 1) and no.rho == 1
    # round-off of the null-space and least-squares solves, relative to the size of K Q~^j P~ (j <= 3)
    scale = np.abs(Pt).max() * max(1.0, np.linalg.norm(Qt, 2)) ** 3
    assert _zero_residual(no, Qt, Pt) < 1e-12 * scale
    np.testing.assert_allclose(no.D, np.eye(2), atol=1e-12 * scale)
    assert no.flatness_rank == 4
    np.testing.assert_allclose(no.margins[0], np.linalg.eigvalsh(S)[0], rtol=1e-10)   # D = I to ~1e-12 scale
    assert no.margins.min() > 0


def test_permutation_construction_when_the_long_chain_is_on_the_second_output():
    """Chains (1, 3): the row with k_1 = 3 can only reach e_2, so D = [e_2; e_1] and e_bar_1 must drive u_2:
    D S~ E = Pi S~ Pi^T (a congruence), positive definite for SPD S~.  With the identity pairing forced,
    (A1) can fail: then a clear FeedbackDesignError."""
    rng = np.random.default_rng(2)
    Qt, Pt = _brunovsky((1, 3), rng)
    S = np.diag([2.0, 0.5])
    no = design_new_output(Qt, Pt, S)
    assert no.construction == "permutation" and no.pairing == (1, 0) and no.k_i == (3, 1)
    scale = np.abs(Pt).max() * max(1.0, np.linalg.norm(Qt, 2)) ** 3
    np.testing.assert_allclose(no.D, [[0, 1], [1, 0]], atol=1e-12 * scale)
    np.testing.assert_allclose(no.D @ S @ no.E, np.diag([0.5, 2.0]), atol=1e-12 * scale)
    assert _zero_residual(no, Qt, Pt) < 1e-12 * scale
    with pytest.raises(FeedbackDesignError, match="no choice of rows"):
        design_new_output(Qt, Pt, S, pairing=(0, 1))


def test_high_gain_construction_where_identity_is_unreachable():
    """k = 1, m = 2, P~ with two nonzero entries (the manipulator's situation): K_1 P~ is a multiple of P~, never
    e_1; S~ not symmetric.  Analytic construction (no refinement): sym(D S~ E) = I at the design point exactly;
    the refinement can only raise the relative margin over the points."""
    rng = np.random.default_rng(3)
    Qt, Pt = np.array([[24.0]]), np.array([[31.0, -34.5]])
    S = np.array([[0.31, 0.56], [-0.035, 0.64]])
    pts = S[None] * (1 + 0.1 * rng.normal(size=(8, 2, 2)))
    raw = design_new_output(Qt, Pt, S, S_points=pts, refine=False)
    assert raw.construction == "high-gain" and raw.k_i == (1,)
    G = raw.D @ S @ raw.E
    np.testing.assert_allclose(0.5 * (G + G.T), np.eye(2), atol=1e-12)      # algebra on O(1) numbers: round-off
    np.testing.assert_allclose(raw.D[0] / Pt[0], raw.K[0][0], rtol=1e-12)       # D_1 = K_1 P~
    ref = design_new_output(Qt, Pt, S, S_points=pts)
    assert ref.relative_margin >= raw.relative_margin - 1e-12
    assert ref.margins.min() > 0 and raw.margins[0] > 0
    # ... and with S~ SPD the identity is still unreachable: the high-gain construction is used, margin > 0
    spd = design_new_output(Qt, Pt, _spd(2, rng))
    assert spd.construction == "high-gain" and spd.margins[0] > 0


def test_uncontrollable_unstable_mode_is_reported():
    with pytest.raises(FeedbackDesignError, match="not controllable"):
        design_new_output(np.diag([1.0, 2.0]), np.array([[1.0], [0.0]]), np.eye(1))


# --------------------------------------------------------------------------- manipulator
@pytest.fixture(scope="module")
def manip():
    model = scene.build()
    ref = scene.reference(model)
    lin = tracking_linearization(scene.SCENE, model, ref)
    return model, ref, lin, scene.initial_configuration(model)


@pytest.fixture(scope="module")
def manip_inverse(manip):
    from invctl.studies.tracking import invert_tracking

    model, ref, _, _ = manip
    return invert_tracking(scene.SCENE, model, ref)


@pytest.fixture(scope="module")
def manip_design(manip, manip_inverse):
    model, ref, lin, q0 = manip
    t = np.linspace(0.0, 2.0, 101)
    return design_funnel_feedback(model, lin, ref, q0=q0, design_points=(manip_inverse.q(t), manip_inverse.v(t)))


def test_feedback_overrides_reproduce_todays_controller_bit_for_bit(manip):
    model, ref, lin, q0 = manip
    d = design_funnel_feedback(model, lin, ref, q0=q0, **scene.FEEDBACK)
    assert all(d.sources[key] == "override" for key in scene.FEEDBACK) and d.construction == "given"
    opts = d.controller_options()
    assert all(opts[key] is scene.FEEDBACK[key] for key in scene.FEEDBACK) and "pairing" not in opts
    mine = NMPFunnelController(model, lin, ref, **opts)
    today = NMPFunnelController(model, lin, ref, t_end=2.0, **scene.FEEDBACK)
    rng = np.random.default_rng(4)
    for _ in range(10):
        q, v, t = q0 + rng.normal(scale=0.05, size=5), rng.normal(scale=0.5, size=5), rng.uniform(0, 2)
        for a, b in zip(mine.core(t, q, v, [], mine.eta2_ref(t)), today.core(t, q, v, [], today.eta2_ref(t))):
            assert np.array_equal(np.array(a), np.array(b))
    # the (A1) margin of FEEDBACK at the design point, against the analysis layer's independent check
    rep = lin.check_A1(scene.FEEDBACK["K"], k_i=scene.FEEDBACK["k_i"], samples=1)
    assert d.a1_design_point == pytest.approx(rep.min_eig_at_design_point, rel=1e-12)    # same math, round-off


def test_manipulator_design_is_high_gain_with_positive_margins(manip, manip_design):
    model, ref, lin, q0 = manip
    d = manip_design
    assert d.construction == "high-gain" and d.k_i == (1,) and d.rho == 1 and d.relative_degrees == (3, 2)
    assert d.a1_design_point > 0 and d.a1_points.min() > 0 and not d.warnings
    assert d.new_output.zero_residual == 0.0 and d.new_output.flatness_rank == 1
    assert d.time_scale == pytest.approx(ref.tf - ref.t0)
    # default expected error: 2 % of the largest excursion (beta: asin(0.9) - asin(0.6))
    assert d.expected_error == pytest.approx([0.02 * (math.asin(0.9) - math.asin(0.6))] * 2, rel=1e-6)
    # funnels: exponential, hence in Phi_(r_i - j); start inside with ratio <= 1/2
    for i, row in enumerate(d.funnels):
        for j, f in enumerate(row):
            assert f.check(d.relative_degrees[i] - j).passed
            assert f.params["p"] + f.params["r"] >= 10 * f.params["r"] * (1 - 1e-12)
    assert d.phi_bar.check(1).passed
    assert d.initial_ratios.max() <= 0.5 + 1e-9
    text = d.describe()
    assert "high-gain" in text and "kappa_bar" in text and "expected error" in text


def test_shared_levels_follow_003_sect_6(manip):
    """levels="shared" (003 Sect. 6: phi_i,j = phi_j, kappa_i,j = kappa_j, phi = phi_2): both outputs' level-0
    funnels are one function, as wide as the wider of the per-output design's (final and initial widths),
    level 1 is 2 kappa_0 times level 0 and phi_bar is phi_2 = 2 kappa_1 times level 1 in its final width;
    the start stays inside; the per-output design gives the two level-0 errors different funnels.  The scene
    declares the rule (Tracking.funnel_levels); an unknown rule is a ParameterError."""
    model, ref, lin, q0 = manip
    per = design_funnel_feedback(model, lin, ref, q0=q0, levels="per-output")
    sh = design_funnel_feedback(model, lin, ref, q0=q0, levels="shared")
    assert scene.SCENE.tracking.funnel_levels == "shared" and sh.levels == "shared" and per.levels == "per-output"
    P = lambda f: (f.params["p"], f.params["q"], f.params["r"])  # noqa: E731
    assert P(per.funnels[0][0]) != P(per.funnels[1][0])
    assert P(sh.funnels[0][0]) == P(sh.funnels[1][0])
    r0 = max(per.funnels[0][0].params["r"], per.funnels[1][0].params["r"])
    w0 = max(sum(P(per.funnels[i][0])[::2]) for i in range(2))
    k = sh.kappa[0][0]
    assert sh.kappa == per.kappa and all(x == k for row in sh.kappa for x in row)
    assert sh.funnels[0][0].params["r"] == pytest.approx(r0, rel=1e-12)
    assert sum(P(sh.funnels[0][0])[::2]) >= w0 * (1 - 1e-12)
    assert sh.funnels[0][1].params["r"] == pytest.approx(2 * k * r0, rel=1e-12)
    assert sh.phi_bar.params["r"] == pytest.approx(2 * k * 2 * k * r0, rel=1e-12)
    assert sh.initial_ratios.max() <= 0.5 + 1e-9
    with pytest.raises(ParameterError, match="levels must be one of"):
        design_funnel_feedback(model, lin, ref, q0=q0, levels="paper")
    with pytest.raises(ParameterError, match="one gain per level"):
        design_funnel_feedback(model, lin, ref, q0=q0, levels="shared", kappa=[[5.0, 5.0], [4.0]])
    from invctl.errors import SceneError
    from invctl.scenes import Tracking

    with pytest.raises(SceneError, match="funnel_levels"):
        Tracking(funnel_levels="paper")._check("s")


def _run(plant, ref, ctrl, q0, t_end=2.0, u_ff=None, signals=None):
    return ClosedLoop(plant, ref, controller=ctrl, t_end=t_end, u_ff=u_ff, signals=signals).run(q0)


def test_manipulator_c1_and_c2_inside_the_funnels_on_the_mismatched_plant(manip, manip_design, manip_inverse):
    """C2 (funnel only), C1 (the paper's: new reference (42)/(43)) and C1-inv (invctl's: new reference along
    the inverse's states) on m3 x 1.2: inside every funnel for the whole 2 s, (A1) > 0 along the runs
    (reference model and plant).  Cumulative errors are printed next to the scene's declared feedback."""
    from invctl.studies.tracking import run_controller, setup_tracking

    model, ref, lin, q0 = manip
    d = manip_design
    out = {}
    for label, feedback in (("auto", d.controller_options()), ("hand", {})):
        s = setup_tracking(scene.SCENE, inverse=manip_inverse, feedback=feedback)
        out[label] = {name: run_controller(s, name) for name in ("C1", "C2", "C1-inv")}
    for r in out["auto"].values():
        assert r.status == "ok" and r.t[-1] == pytest.approx(2.0) and r.max_funnel_ratio < 1
        assert a1_margin_along(d, model, r.q, r.v).min_eig > 0
        assert a1_margin_along(d, model.scaled(**scene.PLANT_FACTORS), r.q, r.v).min_eig > 0
    for label, runs in out.items():
        print(f"{label}: " + ", ".join(f"{n} cum. y {r.cumulative_output_error:.4f} cum. r "
                                       f"{r.cumulative_errors['end effector']:.4f} margin {r.funnel_margin:.3f} "
                                       f"peaks {np.round(r.input_peaks, 2).tolist()}" for n, r in runs.items()))
    # the feedforward pays off with the designed feedback: a little with the paper's new reference (42), whose
    # start differs from the inverse's pre-actuated state, much more with the one along the inverse
    auto = {k: r.cumulative_output_error for k, r in out["auto"].items()}
    assert auto["C1-inv"] < auto["C1"] < auto["C2"]
    assert auto["C1-inv"] < 0.7 * auto["C2"]


def test_a1_margin_along_matches_check_a1_and_the_study(manip):
    """a1_margin_along (new output module) vs LinearizedInternal.check_A1 (analysis) at random states."""
    model, ref, lin, q0 = manip
    ctrl = NMPFunnelController(model, lin, ref, t_end=2.0, **scene.FEEDBACK)
    rng = np.random.default_rng(6)
    q = q0[:, None] + rng.normal(scale=0.05, size=(5, 7))
    v = rng.normal(scale=0.3, size=(5, 7))
    mar = a1_margin_along(ctrl, model, q, v, t=np.arange(7) * 0.1)
    S = schur_complement(model)
    for n in range(7):
        D = ctrl.decoupling_matrix
        G = D @ np.array(S(q[:, n], v[:, n], model.theta_values))
        assert mar.eigenvalues[n] == pytest.approx(np.linalg.eigvalsh(0.5 * (G + G.T))[0], rel=1e-12)
    assert mar.t_min == pytest.approx(0.1 * mar.index)
    assert set(mar.to_dict()) >= {"min_eig", "t_min", "fraction_positive"}


def test_bad_input_is_reported(manip):
    model, ref, lin, q0 = manip
    with pytest.raises(ParameterError, match="unknown or misplaced"):
        design_funnel_feedback(model, lin, ref, gain=3.0)
    with pytest.raises(ParameterError, match="misplaced"):
        design_funnel_feedback(model, lin, ref, controller_options={"K": [[1.0], [1.0, 0.0]]})
    with pytest.raises(ParameterError, match="expected_error"):
        design_funnel_feedback(model, lin, ref, expected_error=-1e-3)
    with pytest.raises(ParameterError, match="start_ratio"):
        DesignRules(start_ratio=1.5)
    with pytest.raises(FeedbackDesignError, match="outside a given funnel") as info:
        design_funnel_feedback(model, lin, ref, q0=q0, phi_bar=(0.0, 0.0, 1e-6))
    assert info.value.partial is not None and info.value.partial.initial_ratios.max() >= 1
    with pytest.raises(FeedbackDesignError, match="fails at the design point"):
        design_funnel_feedback(model, lin, ref, K=[[0.1], [1.0, 1.0]], k_i=[1], rho=-1)


def test_reference_time_scale_closed_forms():
    t = ca.SX.sym("t")
    poly = Reference(t, 0.3 + 0.5 * poly9_timing_law(t, 0.5, 2.0), 0.5, 2.0, smoothness=4)
    T, exc, rate = reference_time_scale(poly)
    assert T == 1.5 and exc[0] == pytest.approx(0.5) and rate[0] == pytest.approx(630 / 256 * 0.5 / 1.5)
    # no finite transition: T = (630/256) * excursion / max|y'|; for A sin(w t) (excursion from y(0) = 0 is A,
    # max |y'| = A w): (630/256) / w
    w = 3.0
    sine = Reference(t, 0.2 * ca.sin(w * t), 0.0, math.inf, smoothness=8)
    T, _, _ = reference_time_scale(sine, t_end=2 * math.pi / w, samples=4001)
    assert T == pytest.approx(630 / 256 / w, rel=1e-6)     # the grid holds the extrema to O(h^2) ~ 1e-7


# --------------------------------------------------------------------------- cart-pole (NMP, m = k = 1)
def test_cartpole_identity_construction_and_c2_inside_the_funnel():
    model = cartpole.build()
    ref = cartpole.reference(model)
    lin = linearize_internal(model, internal_dynamics(model, point=[0.0, 0.0]), [([[0.0], [0.0]], [0.0, 0.0])])
    d = design_funnel_feedback(model, lin, ref, q0=np.zeros(2), controller_options={"t_end": 4.0})
    # colocated (S~ = (M^-1)_11 > 0): K_1 P~ = 1 exactly, margin = S~ at the design point
    assert d.construction == "identity" and d.k_i == (1,)
    assert d.K[0][0] * lin.P_tilde[0, 0] == pytest.approx(1.0, rel=1e-14)     # K_1 = 1/P~ by least squares
    Minv = np.linalg.inv(model.evaluate("M", np.zeros(2)))
    assert d.a1_design_point == pytest.approx(Minv[0, 0], rel=1e-12)
    ctrl = NMPFunnelController(model, lin, ref, t_end=4.0, **d.controller_options())
    res = _run(model.scaled(mp=1.2), ref, ctrl, np.zeros(2), t_end=4.0)
    print(f"cart-pole C2 (mp x 1.2): cum. error {res.cumulative_output_error:.4f}, margin {res.funnel_margin:.3f}, "
          f"peak |F| {res.input_peaks[0]:.2f} N, max |theta| {np.abs(res.q[1]).max():.3f}")
    assert res.status == "ok" and res.max_funnel_ratio < 1
    assert a1_margin_along(d, model.scaled(mp=1.2), res.q, res.v).min_eig > 0
    # the design's target (3 x the expected error; not a guarantee: the funnel bounds e_1,0 = K_1 (eta2 - eta2_ref),
    # whose quasi-static image of y - y_ref this is) is met at the end of the run
    assert res.output_error[-1] < 3 * d.expected_error[0]


# --------------------------------------------------------------------------- two-link arm (minimum phase, k = 0)
@pytest.fixture(scope="module")
def arm_setup():
    model = arm.build()
    ref = arm.reference(model)
    lin = linearize_internal(model, internal_dynamics(model, point=[0.0, 0.0]), [([[0.0], [0.0]], [0.0, 0.0])])
    assert lin.k == 0
    return model, ref, lin


def test_minimum_phase_controller_with_and_without_linearization(arm_setup):
    """k = 0: y_new = K y, r = r_hat; lin=None (no internal dynamics needed) gives the same law; the start
    errors match the hand formulas e_0 = K (y - y_ref), e_1 = K (y' - y_ref') + kappa/(1 - phi^2 e_0^2) e_0."""
    model, ref, lin = arm_setup
    q0, v0 = np.array([0.05, 0.02]), np.array([0.2, -0.1])
    d = design_funnel_feedback(model, lin, ref, q0=q0, v0=v0)
    d0 = design_funnel_feedback(model, None, ref, q0=q0, v0=v0)
    assert d.construction == d0.construction == "identity" and d.K[0][0] == 1.0 and d.relative_degrees == (2,)
    assert d0.kappa_bar == pytest.approx(d.kappa_bar, rel=1e-12)
    a = NMPFunnelController(model, lin, ref, **d.controller_options())
    b = NMPFunnelController(model, None, ref, **d.controller_options())
    assert a.nz == b.nz == 0
    for t in (0.0, 0.4, 1.3):
        np.testing.assert_array_equal(np.array(a.core(t, q0, v0, [], [])[0]), np.array(b.core(t, q0, v0, [], [])[0]))
    e0 = q0[0] - float(ref(0.0)[0, 0])
    phi = d.funnels[0][0](0.0)[0]
    e1 = v0[0] - float(ref(0.0, 1)[0, 0]) + d.kappa[0][0] / (1 - phi**2 * e0**2) * e0
    np.testing.assert_allclose(d.initial_errors[0], [e0, e1], rtol=1e-12)
    assert d.initial_ratios.max() <= 0.5 + 1e-9


def test_minimum_phase_arm_inside_the_funnel_on_the_mismatched_plant(arm_setup):
    """Vertical arm: pure feedback must carry gravity (holding input ~2.7 N m), so kappa_bar follows the load
    rule; with m2 x 1.2 the run stays inside, the final error inside the level-0 funnel."""
    model, ref, lin = arm_setup
    d = design_funnel_feedback(model, lin, ref, q0=np.zeros(2))
    assert d.kappa_bar > 20 / (d.time_scale * d.a1_design_point)          # the load rule is active
    ctrl = NMPFunnelController(model, lin, ref, **d.controller_options())
    res = _run(model.scaled(m2=1.2), ref, ctrl, np.zeros(2))
    print(f"two-link arm (m2 x 1.2): cum. error {res.cumulative_output_error:.4f}, margin {res.funnel_margin:.3f}, "
          f"final error {res.output_error[-1]:.4f}, peak |u| {res.input_peaks[0]:.2f}")
    assert res.status == "ok" and res.max_funnel_ratio < 1
    assert res.output_error[-1] < d.funnels[0][0].boundary(2.0)[0]     # k = 0, K = 1: e_1,0 = y - y_ref exactly
    assert a1_margin_along(d, model.scaled(m2=1.2), res.q, res.v).min_eig > 0


# --------------------------------------------------------------------------- a case that needs the pairing
def _gantry(**overrides):
    """Two carts on independent axes (forces F1, F2, outputs x1, x2: colocated); cart 2 carries an inverted
    pendulum, so the unstable internal mode is driven by y_2 only (P~ = [0, p])."""
    params = {"m1": 1.0, "m2": 1.0, "mp": 0.2, "l": 0.5, "g": 9.81}
    P = ParamSet(list(params))
    m1, m2, mp, l, g = (P[key] for key in params)
    q, v = ca.SX.sym("q", 3), ca.SX.sym("v", 3)
    com = ca.vertcat(v[1] + l * ca.cos(q[2]) * v[2], -l * ca.sin(q[2]) * v[2])
    T = 0.5 * m1 * v[0] ** 2 + 0.5 * m2 * v[1] ** 2 + 0.5 * mp * ca.sumsqr(com) + 0.5 * (mp * l**2 / 3) * v[2] ** 2
    region = OperatingRegion(q_lower=[-math.inf, -math.inf, -math.pi / 2], q_upper=[math.inf, math.inf, math.pi / 2],
                             sample_bounds=([-2, -2, -math.pi / 2], [2, 2, math.pi / 2]), v_scale=2.0)
    return Model.from_lagrangian("gantry", q, v, P, params, T=T, V=mp * g * l * ca.cos(q[2]),
                                 B=ca.DM([[1, 0], [0, 1], [0, 0]]), h=q[:2], region=region, overrides=overrides,
                                 q_names=["x1", "x2", "theta"], u_names=["F1", "F2"], y_names=["x1", "x2"])


def test_pairing_is_needed_and_works_for_a_pendulum_on_the_second_axis():
    model = _gantry()
    t = ca.SX.sym("t")
    lam = poly9_timing_law(t, 0.0, 2.0)
    ref = Reference(t, ca.vertcat(0.3 * lam, 0.5 * lam), 0.0, 2.0, smoothness=4)
    lin = linearize_internal(model, internal_dynamics(model, point=[0.0, 0.0, 0.0]),
                             [([[0.0, 0.0], [0.0, 0.0]], [0.0, 0.0])])
    assert lin.k == 1 and abs(lin.P_tilde[0, 0]) < 1e-12 * abs(lin.P_tilde[0, 1])
    d = design_funnel_feedback(model, lin, ref, q0=np.zeros(3), controller_options={"t_end": 4.0})
    assert d.construction == "permutation" and d.pairing == (1, 0)
    np.testing.assert_allclose(d.decoupling_matrix, [[0, 1], [1, 0]], atol=1e-12)
    # the identity pairing cannot satisfy (A1): (S~)_21 = 0 (the carts are not inertially coupled)
    with pytest.raises(FeedbackDesignError, match="no choice of rows"):
        design_funnel_feedback(model, lin, ref, q0=np.zeros(3), pairing=(0, 1))
    ctrl = NMPFunnelController(model, lin, ref, t_end=4.0, **d.controller_options())
    assert ctrl.pairing == (1, 0)
    res = _run(model.scaled(mp=1.2), ref, ctrl, np.zeros(3), t_end=4.0)
    print(f"gantry (mp x 1.2): cum. error {res.cumulative_output_error:.4f}, margin {res.funnel_margin:.3f}, "
          f"peaks {np.round(res.input_peaks, 2).tolist()}")
    assert res.status == "ok" and res.max_funnel_ratio < 1
    assert a1_margin_along(ctrl, model.scaled(mp=1.2), res.q, res.v).min_eig > 0
    # the pairing is applied: u_fb = E u_law, so u_fb,1 is driven by e_bar_2 (the y_1 row) and vice versa
    u = np.array(ctrl.core(0.3, np.array([0.01, 0.0, 0.0]), np.zeros(3), [], ctrl.eta2_ref(0.3))[0]).ravel()
    ebar = np.array(ctrl.core(0.3, np.array([0.01, 0.0, 0.0]), np.zeros(3), [], ctrl.eta2_ref(0.3))[2]).ravel()
    assert np.sign(u[0]) == -np.sign(ebar[1]) and abs(u[0] / u[1]) == pytest.approx(abs(ebar[1] / ebar[0]))


@pytest.mark.parametrize("name", ["expected_fraction", "final_factor", "level_factor", "transient_factor",
                                  "decay", "kappa_rate", "kappa_bar_rate"])
def test_design_rule_constants_must_be_positive_not_zero(name):
    from invctl.control.funnel_design import DesignRules

    with pytest.raises(ParameterError, match=f"DesignRules.{name} must be > 0, got 0.0"):
        DesignRules(**{name: 0.0})


def test_new_output_refines_by_default():
    """The case of test_high_gain_construction_where_identity_is_unreachable: the Nelder-Mead refinement is on
    by default and raises the relative margin over the points (here from 0.174 to 0.204)."""
    rng = np.random.default_rng(3)
    Qt, Pt = np.array([[24.0]]), np.array([[31.0, -34.5]])
    S = np.array([[0.31, 0.56], [-0.035, 0.64]])
    pts = S[None] * (1 + 0.1 * rng.normal(size=(8, 2, 2)))
    default = design_new_output(Qt, Pt, S, S_points=pts)
    refined = design_new_output(Qt, Pt, S, S_points=pts, refine=True)
    raw = design_new_output(Qt, Pt, S, S_points=pts, refine=False)
    assert default.relative_margin == refined.relative_margin > raw.relative_margin + 0.01
