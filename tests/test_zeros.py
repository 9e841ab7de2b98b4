"""Invariant/transmission/decoupling zeros, and analysis around operating points without a region.

References: systems built with known zeros (products of SISO transfer functions mixed by
constant invertible matrices, then a random change of state coordinates), systems with a
prescribed Kalman structure, python-control's own ``zeros()`` and ``ctrb``/``obsv`` ranks,
the closed-form zero dynamics of the cart-pole and the arm, and for every scene the
eigenvalues of invctl's linearized internal dynamics (003 Sect. 2 and 3), which at an
equilibrium are the invariant zeros of the plant.

Tolerances: zeros of well-conditioned test systems to 1e-9 relative (QZ after a random
similarity with condition number ~1e2 loses ~1e-13); internal eigenvalues vs zeros to 1e-9
(both from exact AD Jacobians, different eigen-solvers); python-control's QZ on the
unreduced pencil returns the infinite eigenvalues of relative degree >= 2 as huge finite
numbers (we measured 7e14), so its values above 1e8 times the system norm are dropped.
"""
import casadi as ca
import numpy as np
import pytest
import scipy.linalg as sla
from scipy.optimize import linear_sum_assignment

import invctl_scenes.cartpole as cartpole
import invctl_scenes.knife_edge as knife
import invctl_scenes.manipulator as manip
import invctl_scenes.two_link_arm as arm
from invctl.analysis import (
    classify_statespace, classify_zeros, internal_dynamics, invariant_zeros, linearize_internal,
    neighbourhood_samples, operating_points, plant_linearization, relative_degree, transmission_zeros,
)
from invctl.errors import DimensionError, ReferenceSignalError, RelativeDegreeError, ZeroError
from invctl.model import Model
from invctl.reference import Reference, poly9_timing_law

control = pytest.importorskip("control")

#: python-control without slycot runs QZ on the unreduced pencil: an infinite eigenvalue block of size
#: r + 1 (relative degree r) is perturbed to finite values ~ eps^(-1/(r+1)) times the system norm.  For the
#: mixed systems below we measured four values at 3e3 .. 4.5e3 times the norm (5.6e4 .. 6.3e4) and one at
#: 1e13 .. 5e14.  The true zeros of every system here are below 0.2 times the norm, so python-control's values
#: above 1e2 times the norm are dropped before comparing (30x margin to the spurious ones).
SPURIOUS = 1e2


def _companion(num, den):
    """Controllable canonical realization of num/den (deg num < deg den, den monic)."""
    den = np.asarray(den, float) / den[0]
    num = np.asarray(num, float) / 1.0
    n = den.size - 1
    A = np.zeros((n, n))
    A[:-1, 1:] = np.eye(n - 1)
    A[-1] = -den[:0:-1]
    B = np.zeros((n, 1))
    B[-1] = 1
    C = np.zeros((1, n))
    C[0, :num.size] = num[::-1]
    return A, B, C


def _mixed_system(blocks, rng):
    """diag(num_i/den_i) mixed by random invertible U (outputs), V (inputs) and a random state similarity."""
    parts = [_companion(n, d) for n, d in blocks]
    A = sla.block_diag(*[p[0] for p in parts])
    B = sla.block_diag(*[p[1] for p in parts])
    C = sla.block_diag(*[p[2] for p in parts])
    m = len(blocks)
    U, V = np.eye(m) + 0.3 * rng.normal(size=(m, m)), np.eye(m) + 0.3 * rng.normal(size=(m, m))
    T = np.eye(A.shape[0]) + 0.2 * rng.normal(size=A.shape)
    Ti = np.linalg.inv(T)
    return T @ A @ Ti, T @ B @ V, U @ C @ Ti, np.zeros((m, m))


def _control_zeros(A, B, C, D):
    z = control.ss(A, B, C, D).zeros()
    scale = np.linalg.norm(np.block([[A, B], [C, D]]), 2)
    return z[np.isfinite(z) & (np.abs(z) < SPURIOUS * scale)]


def _same(a, b, rtol=1e-9):
    """Equal as multisets: optimal pairing, then |a - b| <= rtol max(1, |b|)."""
    a, b = np.asarray(a, complex).ravel(), np.asarray(b, complex).ravel()
    assert a.size == b.size, (a, b)
    ia, ib = linear_sum_assignment(np.abs(a[:, None] - b[None, :]))
    assert np.all(np.abs(a[ia] - b[ib]) <= rtol * np.maximum(1.0, np.abs(b[ib]))), (a, b)


# --------------------------------------------------------- known zeros by construction
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_zeros_of_mixed_siso_blocks(seed):
    """Relative degrees 1, 2 and 3 in one square system: the zeros are those of the blocks
    (det G = prod G_i det U det V)."""
    rng = np.random.default_rng(seed)
    blocks = [([1, 2.0], [1, 3, 5, 1]),                       # zero -2, relative degree 2
              ([1.0], [1, 1, 4, 2]),                          # no zero, relative degree 3
              ([1, -1.5, 2.0], [1, 6, 11, 6])]                # zeros 0.75 +- 1.2j, relative degree 1
    A, B, C, D = _mixed_system(blocks, rng)
    expected = np.concatenate([np.roots(b[0]) for b in blocks if len(b[0]) > 1])
    _same(invariant_zeros((A, B, C, D)), expected)
    _same(transmission_zeros((A, B, C, D)), expected)
    _same(_control_zeros(A, B, C, D), expected)


def test_zeros_with_feedthrough_and_no_zeros():
    rng = np.random.default_rng(5)
    A, B = rng.normal(size=(4, 4)), rng.normal(size=(4, 2))
    C, D = rng.normal(size=(2, 4)), np.eye(2) + 0.1 * rng.normal(size=(2, 2))
    _same(invariant_zeros((A, B, C, D)), np.linalg.eigvals(A - B @ np.linalg.solve(D, C)))   # D invertible
    A, B, C = _companion([1.0], [1, 2, 3, 4, 5])
    assert invariant_zeros((A, B, C, 0)).size == 0


# -------------------------------------------------------------- Kalman structure
def _structured(rng, extra_uncontrollable_at_2=False):
    """Minimal part (s - 2)/((s + 1)(s + 3)); uncontrollable-observable -4, controllable-unobservable -5,
    neither -6 (and optionally an uncontrollable mode at 2 = the transmission zero)."""
    Am, Bm, Cm = _companion([-2.0, 1.0][::-1], [1, 4, 3])
    k = 6 if extra_uncontrollable_at_2 else 5
    A = np.zeros((k, k))
    A[:2, :2] = Am
    A[2, 2], A[3, 3], A[4, 4] = -4, -5, -6
    A[0, 2] = 1.0          # the uncontrollable mode drives the minimal part: observable through it
    A[3, 0] = 1.0          # the minimal part drives mode -5, which the output does not see
    C = np.zeros((1, k))
    C[0, :2], C[0, 2] = Cm, 0.5
    if extra_uncontrollable_at_2:
        A[5, 5], C[0, 5] = 2.0, 1.0
    B = np.zeros((k, 1))
    B[:2] = Bm
    T = np.eye(k) + 0.3 * rng.normal(size=(k, k))
    Ti = np.linalg.inv(T)
    return T @ A @ Ti, T @ B, C @ Ti, np.zeros((1, 1))


def test_classification_of_a_prescribed_kalman_structure():
    A, B, C, D = _structured(np.random.default_rng(0))
    rep = classify_statespace((A, B, C, D))
    kinds = dict(zip(np.round(rep.invariant.real, 9), rep.kinds))
    assert kinds == {2.0: "transmission", -4.0: "input decoupling", -5.0: "output decoupling",
                     -6.0: "input-output decoupling"}
    _same(rep.transmission, [2.0])
    _same(rep.input_decoupling, [-4.0, -6.0])
    _same(rep.output_decoupling, [-5.0, -6.0])
    assert not rep.minimum_phase and rep.unstable.size == 1
    # python-control's ranks agree: two uncontrollable (-4, -6) and two unobservable (-5, -6) modes
    assert np.linalg.matrix_rank(control.ctrb(A, B), tol=1e-8 * np.linalg.norm(control.ctrb(A, B))) == 3
    assert np.linalg.matrix_rank(control.obsv(A, C), tol=1e-8 * np.linalg.norm(control.obsv(A, C))) == 3
    assert np.all(rep.pbh_input[[k != "transmission" and "input" in k for k in rep.kinds]] < 1e-12)
    assert "decoupling zeros: -6 (input-output decoupling), -5 (output decoupling), -4 (input decoupling)" \
        in rep.describe()


def test_value_that_is_both_transmission_and_decoupling_zero():
    """A double invariant zero at 2: one from the transfer function, one from an uncontrollable mode at 2."""
    rep = classify_statespace(_structured(np.random.default_rng(1), extra_uncontrollable_at_2=True))
    at2 = [k for z, k in zip(rep.invariant, rep.kinds) if abs(z - 2) < 1e-6]
    assert sorted(at2) == ["input decoupling", "transmission"]
    _same(rep.transmission, [2.0])


def test_bad_systems_are_reported():
    rng = np.random.default_rng(3)
    A, B, C = rng.normal(size=(3, 3)), rng.normal(size=(3, 1)), rng.normal(size=(2, 3))
    with pytest.raises(ZeroError, match="square system"):
        invariant_zeros((A, B, C, np.zeros((2, 1))))
    B2 = rng.normal(size=(3, 2))
    with pytest.raises(ZeroError, match="rank deficient for every s"):
        invariant_zeros((A, B2, np.vstack([C[0], C[0]]), np.zeros((2, 2))))   # two equal outputs
    with pytest.raises(DimensionError, match="inconsistent"):
        invariant_zeros((A, B, C[:, :2], 0))
    with pytest.raises(DimensionError, match="state-space system"):
        invariant_zeros("not a system")


# ------------------------------------------------- scenes: internal dynamics = zeros
def _check_scene(model, q, lin, expected=None):
    pl = plant_linearization(model, q)
    sys = pl.to_statespace()
    z = invariant_zeros(sys)
    _same(z, lin.eigenvalues)
    _same(_control_zeros(sys.A, sys.B, sys.C, sys.D), lin.eigenvalues)
    if expected is not None:
        _same(z, expected)
    return classify_zeros(model, q, lin=lin)


@pytest.mark.parametrize("D", [0.0, 0.3])
def test_cartpole_zeros_are_the_closed_form_zero_dynamics(D):
    model = cartpole.build(D=D)
    s3 = internal_dynamics(model, "sect3", point=[0.0, 0.0])
    s2 = internal_dynamics(model, "sect2", s3.phi_expr, point=[0.0, 0.0])
    for idyn in (s3, s2):
        lin = linearize_internal(model, idyn, [([[0.0], [0.0]], [0.0, 0.0])])
        rep = _check_scene(model, [0.0, 0.0], lin, cartpole.zero_dynamics_eigenvalues(model))
    assert rep.kinds == ("transmission", "transmission") and not rep.minimum_phase and rep.unstable.size == 1


@pytest.mark.parametrize("q1", [0.0, 0.4])
def test_two_link_arm_minimal_and_redundant_same_zeros(q1):
    mini, red = arm.build(), arm.build_redundant()
    q2 = arm.zero_dynamics_equilibrium(mini, q1)
    closed = arm.zero_dynamics_eigenvalues(mini, q1)
    for model, q in ((mini, np.array([q1, q2])), (red, arm.redundant_configuration(red, q1, q2))):
        idyn = internal_dynamics(model, "sect3", point=q)
        eta = np.array(idyn.eta(q, np.zeros(model.n), model.theta_values)).ravel()
        lin = linearize_internal(model, idyn, [([[q1], [0.0]], eta)])
        rep = _check_scene(model, q, lin, closed)
        assert rep.minimum_phase and rep.kinds == ("transmission", "transmission")


def test_manipulator_zeros_at_start_and_end_equilibria():
    model = manip.build(**manip.PRESETS["guess"])
    ref = manip.reference(model)
    ops = operating_points(model, ref, 2, guess_q=manip.initial_configuration(model))
    idyn = internal_dynamics(model, "sect3", manip.paper_internal_coordinates,
                             point=manip.initial_configuration(model))
    for k, q in enumerate(ops):
        eta = np.array(idyn.eta(q, np.zeros(model.n), model.theta_values)).ravel()
        lin = linearize_internal(model, idyn, [([ops.y[k], np.zeros(2)], eta)])
        rep = _check_scene(model, q, lin)
        assert rep.kinds == ("transmission", "transmission") and rep.unstable.size == 1
    # 003 Sect. 6 ('guess' parameters, docs/analysis.md): -19.64, 24.44
    _same(rep.transmission, [-19.6399637, 24.4399637], rtol=1e-8)


def test_knife_edge_zero_at_the_origin_is_a_decoupling_zero():
    model = knife.build()
    q = [0.3, -0.2, 0.3]
    idyn = internal_dynamics(model, "sect3", point=q)
    lin = linearize_internal(model, idyn, [([[0.3, 0.3], [0.0, 0.0]], [-0.2])])
    rep = _check_scene(model, q, lin, [0.0])
    assert rep.kinds == ("input-output decoupling",)
    assert rep.transmission.size == 0 and rep.minimum_phase          # judged on transmission zeros
    assert not lin.minimum_phase                                    # the internal eigenvalue 0 alone says otherwise
    assert rep.pbh_input[0] < 1e-14 and rep.pbh_output[0] < 1e-14
    pl = plant_linearization(model, q)
    # independent: python-control's controllability/observability matrices lose one rank each
    assert np.linalg.matrix_rank(control.ctrb(pl.A, pl.B)) == 4 == np.linalg.matrix_rank(control.obsv(pl.A, pl.C))
    assert "0 (input-output decoupling)" in rep.describe() and "minimum phase (no transmission zeros)" in rep.describe()


def test_linearization_from_another_point_is_rejected():
    model = arm.build()
    idyn = internal_dynamics(model, "sect3", point=[0.0, 0.0])
    lin0 = linearize_internal(model, idyn, [([[0.0], [0.0]], [0.0, 0.0])])
    q2 = arm.zero_dynamics_equilibrium(model, 0.4)
    with pytest.raises(ZeroError, match="not the invariant zeros") as err:
        classify_zeros(model, [0.4, q2], lin=lin0)
    assert err.value.partial.transmission.size == 2


# --------------------------------------- imaginary-axis zeros, analysis without a region
def cartpole_sine_output(c_over_l: float = 2.0) -> Model:
    """Cart-pole with output y = x + c sin(theta) and no declared region.  Zero dynamics (y = 0, linearized):
    x = -c theta, (J - c mp l) theta'' = mp g l theta; with c = 2 l, J - 2 mp l^2 = -2/3 mp l^2 < 0, so
    theta'' = -(3 g / (2 l)) theta: zeros +-j sqrt(3 g / (2 l)).  Gamma = (J - c mp l cos^2 theta) / det M
    changes sign at cos^2 theta = 2/3 (|theta| = 0.615), inside the default box |q_i| <= 1."""
    base = cartpole.build()
    c = c_over_l * base.values["l"]
    return Model(f"cartpole_sine_{c_over_l:g}l", base.q, base.v, base.params, base.values, M=base.M, f=base.f,
                 B=base.B, h=base.q[0] + c * ca.sin(base.q[1]), q_names=["x", "theta"], u_names=["F"],
                 y_names=["x+c sin(theta)"])


def test_cartpole_sine_output_zeros_on_the_imaginary_axis():
    model = cartpole_sine_output()
    p = model.values
    w = np.sqrt(3 * p["g"] / (2 * p["l"]))
    rep = classify_zeros(model, [0.0, 0.0])         # internal dynamics around the point: no region needed
    _same(rep.invariant, [-1j * w, 1j * w])
    _same(rep.internal_eigenvalues, [-1j * w, 1j * w])
    assert rep.imaginary_axis.size == 2 and rep.unstable.size == 0 and not rep.minimum_phase
    assert "2 on the imaginary axis" in rep.describe()


def test_relative_degree_around_operating_points_without_a_region():
    model = cartpole_sine_output()
    assert model.region is None
    with pytest.raises(RelativeDegreeError, match="changes sign on the box.*pass the operating points"):
        relative_degree(model, samples=200)
    t = ca.SX.sym("t")
    ref = Reference(t, 0.8 * poly9_timing_law(t, 0.0, 1.0), 0.0, 1.0, smoothness=4)
    ops = operating_points(model, ref, 5)
    np.testing.assert_allclose(ops.q, np.c_[ref(ops.t).ravel(), np.zeros(5)], atol=1e-12)   # theta = 0 holds y
    rd = relative_degree(model, samples=200, points=ops)
    assert "neighbourhood |dq_i| <= 0.1" in rd.region and rd.samples == 205
    # Gamma = (J - 2 mp l^2 cos^2 theta) / det M < 0 for |theta| <= 0.1: check the sampled range
    q = rd.diagnostics["q"]
    assert np.all(np.abs(q[:, 1]) <= 0.1 + 1e-15) and q[:, 0].min() >= -0.1 and q[:, 0].max() <= 0.9
    assert rd.det_range[1] < 0
    with pytest.raises(RelativeDegreeError, match="smaller neighbourhood"):
        relative_degree(model, samples=200, points=ops, radius=1.0)


def test_check_A1_without_a_region_samples_the_neighbourhood():
    """(A1) for the sine output: k = 2 (both zeros on the axis), K_1 P~ = 0, and rho K_1 Q~ P~ S(w) > 0 holds
    where S = Gamma keeps the sign it has at theta = 0, i.e. for |theta| < 0.615, not on a neighbourhood of radius 1."""
    model = cartpole_sine_output()
    idyn = internal_dynamics(model, "sect3", point=[0.0, 0.0], samples=50)
    lin = linearize_internal(model, idyn, [([[0.0], [0.0]], [0.0, 0.0])])
    assert lin.k == 2
    K1 = np.array([lin.P_tilde[1, 0], -lin.P_tilde[0, 0]])
    near = lin.check_A1([K1], k_i=[2], samples=100)
    assert near.passed and near.fraction_satisfied == 1.0 and "neighbourhood" in near.domain
    far = lin.check_A1([K1], k_i=[2], rho=near.rho, samples=100, radius=1.0)
    assert not far.passed and 0 < far.fraction_satisfied < 1


def test_declared_region_sampling_is_unchanged(manipulator):
    rd = relative_degree(manipulator, samples=30, rng=4)
    np.testing.assert_array_equal(rd.diagnostics["q"], manipulator.region.sample(30, 4)[0])
    # an explicit radius samples the neighbourhood inside the region
    q0 = manip.initial_configuration(manipulator)
    rd = relative_degree(manipulator, samples=40, points=[q0], radius=0.05)
    q = rd.diagnostics["q"][:40]
    assert np.all(np.abs(q - q0) <= 0.05 + 1e-15) and all(manipulator.region.contains(qk) for qk in q)
    assert "within U_q" in rd.region


def test_neighbourhood_is_the_tube_around_the_polyline():
    model = cartpole.build()
    pts = [np.array([0.0, 0.0]), np.array([1.0, 0.0]), np.array([1.0, 0.5])]
    q, v = neighbourhood_samples(model, pts, 2000, rng=1, radius=[0.1, 0.05], v_radius=0.2)
    # distance (per coordinate, scaled by the radius) to the polyline <= 1
    s = np.linspace(0, 1, 2001)[:, None]
    line = np.vstack([(1 - s) * pts[0] + s * pts[1], (1 - s) * pts[1] + s * pts[2]])
    d = np.min(np.max(np.abs(q[:, None, :] - line[None]) / [0.1, 0.05], axis=2), axis=1)
    assert d.max() <= 1 + 1e-3 and np.abs(v).max() <= 0.2
    assert q[:, 0].max() > 1.05 and q[:, 1].max() > 0.5        # both segments and the ends are covered


def test_operating_points_follow_the_branch_and_report_failures():
    model = manip.build()
    ref = manip.reference(model)
    ops = operating_points(model, ref, 7, guess_q=manip.initial_configuration(model))
    np.testing.assert_allclose(ops.start, manip.initial_configuration(model), atol=1e-10)
    for k, q in enumerate(ops):
        assert np.max(np.abs(model.evaluate("g", q))) < 1e-12
        np.testing.assert_allclose(model.evaluate("h", q).ravel(), ops.y[k], atol=1e-12)
        # force balance with the returned multipliers and inputs
        bal = model.evaluate("f", q).ravel() + model.evaluate("G", q).T @ ops.lam[k] + model.evaluate("B", q) @ ops.u[k]
        assert np.max(np.abs(bal)) < 1e-10
    assert ops.in_region.all() and len(ops) == 7
    np.testing.assert_allclose(manip.end_effector_approx(model, ops.y[-1]).ravel(), manip.R_APP_F, atol=1e-12)
    t = ca.SX.sym("t")
    away = Reference(t, ca.vertcat(5 * t, 0.6435011087932844), 0.0, 1.0, smoothness=4)
    with pytest.raises(ReferenceSignalError, match="no equilibrium") as err:
        operating_points(model, away, 5, guess_q=manip.initial_configuration(model))
    assert 1 <= len(err.value.partial) < 5
    with pytest.raises(ReferenceSignalError, match="count >= 2"):
        operating_points(model, ref, 1)
