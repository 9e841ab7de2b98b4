"""The gallery of systems from the literature (docs/gallery.md), each against an independent reference.

* mass chain: the feedforward of ``invert`` equals the exact stable inverse of the transfer function
  (partial fractions of 1/G(s), numpy polynomials and Gauss-Legendre quadrature);
* passive-elbow arm: zeros against the closed form of the elbow equation;
* flexible arm: the closed-form model against the passive arm (n = 2) and against the Lagrangian
  (n = 4), its zeros against a numpy linear model;
* every gallery scene: internal-dynamics eigenvalues = python-control's transmission zeros, the
  automatic inversion passes its forward check, and C1/C2/C3 stay inside their funnels.
"""
from __future__ import annotations

import math

import casadi as ca
import control
import numpy as np
import pytest
import scipy.linalg as sla

import invctl_scenes.cartpole as cartpole
import invctl_scenes.flexible_arm as flexible_arm
import invctl_scenes.mass_chain as mass_chain
import invctl_scenes.passive_arm as passive_arm
import invctl_scenes.two_link_arm as two_link_arm
from invctl.analysis import internal_dynamics, linearize_internal, plant_statespace
from invctl.inversion import EquilibriumSolver, forward_check, invert
from invctl.model import Model
from invctl.scenes import load_scene
from invctl.studies.tracking import run_tracking_study


# ------------------------------------------------------------------ helpers
def poly9(t, t0, tf, y0, yf, order):
    """The C^4 timing law of 003 Sect. 6 and its derivatives in numpy (independent of CasADi)."""
    law = np.polynomial.Polynomial([0, 0, 0, 0, 0, 126, -420, 540, -315, 70])
    s = np.clip((np.asarray(t, float) - t0) / (tf - t0), 0.0, 1.0)
    inside = (np.asarray(t) > t0) & (np.asarray(t) < tf)
    if order == 0:
        return y0 + (yf - y0) * law(s)
    return np.where(inside, (yf - y0) * law.deriv(order)(s) / (tf - t0) ** order, 0.0)


def exact_stable_inverse(Z, D, t, t0, tf, y0, yf):
    """u(t) of the bounded (non-causal) inverse of G = Z/D for the rest-to-rest y_ref.

    ``D/Z = c2 s^2 + c1 s + c0 + sum_j r_j/(s - z_j)`` (simple zeros): the polynomial part acts on
    y_ref'', y_ref', y_ref; ``r/(s - z)`` is the causal convolution with exp(z t) for Re z < 0 and the
    anti-causal one for Re z > 0.  Constant tails are integrated in closed form; the transition by
    60-point Gauss-Legendre (the integrand is smooth, |z| (tf - t0) < 15: machine precision)."""
    Qp, R = np.polydiv(D.coeffs, Z.coeffs)
    Qp = np.poly1d(Qp)
    assert Qp.order == 2
    zs = Z.roots
    res = np.poly1d(R)(zs) / Z.deriv()(zs)
    u = sum(Qp.coeffs[::-1][k] * poly9(t, t0, tf, y0, yf, k) for k in range(3)).astype(complex)
    xg, wg = np.polynomial.legendre.leggauss(60)
    for z, r in zip(zs, res):
        w = np.zeros(t.size, complex)
        for i, ti in enumerate(t):
            a, b = (t0, ti) if z.real < 0 else (ti, tf)
            tau = 0.5 * (b - a) * xg + 0.5 * (a + b)
            integral = 0.5 * (b - a) * np.sum(wg * np.exp(z * (ti - tau)) * poly9(tau, t0, tf, y0, yf, 0))
            if z.real < 0:
                w[i] = -y0 * np.exp(z * (ti - t0)) / z + integral
            else:
                w[i] = -yf * np.exp(z * (ti - tf)) / z - integral
        u += r * w
    assert np.max(np.abs(u.imag)) < 1e-9 * np.max(np.abs(u.real))
    return u.real


def equilibrium_point(model, y, guess=None):
    """q of the rest state with output y (the library's solver; its residual is checked by it)."""
    X, _ = EquilibriumSolver(model).solve(np.atleast_1d(float(y)), guess_q=guess)
    return X[:model.n]


def internal_eigenvalues_at(model, q0):
    """Eigenvalues of the internal dynamics (Sect. 3, default coordinates) linearized at the rest state q0."""
    idyn = internal_dynamics(model, "sect3", point=q0, samples=20)
    eta0 = np.array(idyn.eta(q0, np.zeros(model.n), model.theta_values)).ravel()
    y0 = model.evaluate("h", q0).ravel()
    lin = linearize_internal(model, idyn, [([y0, np.zeros(model.ny)], eta0)])
    return np.sort_complex(lin.eigenvalues)


def assert_same_zeros(a, b, rtol):
    """Equal as multisets up to ``rtol * max(1, |z|)`` (sorted pairing, checked both ways)."""
    a, b = np.sort_complex(np.asarray(a, complex)), np.sort_complex(np.asarray(b, complex))
    assert a.size == b.size, (a, b)
    for x in a:
        assert np.min(np.abs(b - x)) <= rtol * max(1.0, abs(x)), (x, b)
    for x in b:
        assert np.min(np.abs(a - x)) <= rtol * max(1.0, abs(x)), (x, a)


# ------------------------------------------------------------------ cart-pole
def test_cartpole_feedforward_equals_exact_stable_inverse_of_the_linearization():
    """Cart position output, pole upright: X(s)/F(s) = (J s^2 - mp g l) / (s^2 [((mc + mp) J - mp^2 l^2) s^2
    - (mc + mp) mp g l]), zeros +-sqrt(mp g l / J).  For a 1 mm move the pole angle stays ~1e-3 rad, so the
    nonlinear terms are ~theta^2/6 ~ 2e-7 of the linear ones (a 0.1 mm move gives the same error to 3
    digits: it is all discretization).  Hermite-Simpson's error is 1.5e-6 at N = 200 (the 2 s transition
    gets half of the graded mesh of [-4.8, 6.8]) and 9.5e-8 at N = 400: 1e-6 at N = 400, and order 4
    (error ratio >= 8) from N = 400 to 800."""
    model = cartpole.build()
    p = model.values
    J = p["I"] + p["mp"] * p["l"] ** 2
    mt = p["mc"] + p["mp"]
    Z = np.poly1d([J, 0.0, -p["mp"] * p["g"] * p["l"]])
    D = np.poly1d([mt * J - (p["mp"] * p["l"]) ** 2, 0.0, -mt * p["mp"] * p["g"] * p["l"], 0.0, 0.0])
    np.testing.assert_allclose(np.sort(Z.roots.real), cartpole.zero_dynamics_eigenvalues(model), rtol=1e-12)
    ref = cartpole.reference(model, xf=1e-3)
    t = np.linspace(ref.t0, ref.tf, 81)
    u_exact = exact_stable_inverse(Z, D, t, ref.t0, ref.tf, 0.0, 1e-3)
    errors = [np.max(np.abs(invert(model, ref, q_guess=[0.0, 0.0], N=N).u(t).ravel() - u_exact))
              / np.max(np.abs(u_exact)) for N in (400, 800)]
    assert errors[0] <= 1e-6 and errors[0] / errors[1] >= 8.0


# ------------------------------------------------------------------ mass chain
@pytest.mark.parametrize("n", [2, 3])
def test_mass_chain_feedforward_equals_exact_stable_inverse(n):
    """invert() with the automatic selection and horizon against partial fractions of 1/G(s), to 1e-6
    relative on [t0, tf].  Error budget: the neglected tails (plan tol 1e-8) and Hermite-Simpson's
    O(h^4) error at the default N = 200 (measured 2e-8 for n = 2, 2e-7 for n = 3); 1e-6 leaves a
    factor 5 to 50.  Refining to N = 400 must reduce the error ~16x (order 4; at least 8x asserted)."""
    model = mass_chain.build(n=n)
    ref = mass_chain.reference(model)
    t = np.linspace(ref.t0, ref.tf, 81)
    Z, D = mass_chain.polynomials(n, model.values)
    u_exact = exact_stable_inverse(Z, D, t, ref.t0, ref.tf, 0.0, 0.1)
    errors = []
    for N in (200, 400):
        inv = invert(model, ref, N=N)
        assert set(inv.diagnostics["plan"]["derived"]) == {"start", "end", "T0", "Tf"}
        errors.append(np.max(np.abs(inv.u(t).ravel() - u_exact)) / np.max(np.abs(u_exact)))
    assert errors[0] <= 1e-6
    assert errors[0] / errors[1] >= 8.0


def test_mass_chain_zeros_closed_form_and_nonminimum_phase():
    """n = 2: Z(s) = m s^2 + c (1 - lam) s + k (1 - lam); lam > 1 puts one real zero in the right half
    plane for every n (Z(0) = k^(n-1) (1 - lam) < 0).  Roots of a quadratic: 1e-12."""
    model = mass_chain.build(n=2)
    p = model.values
    a, b, c = p["m"], p["c"] * (1 - p["lam"]), p["k"] * (1 - p["lam"])
    closed = np.array([(-b - math.sqrt(b * b - 4 * a * c)) / (2 * a), (-b + math.sqrt(b * b - 4 * a * c)) / (2 * a)])
    np.testing.assert_allclose(mass_chain.exact_zeros(model).real, closed, rtol=1e-12)
    np.testing.assert_allclose(closed, [(5 - math.sqrt(425)) / 2, (5 + math.sqrt(425)) / 2], rtol=1e-12)
    for n in (2, 3, 4, 5):
        z = mass_chain.exact_zeros(mass_chain.build(n=n))
        assert np.sum(z.real > 0) >= 1 and np.any((z.real > 0) & (np.abs(z.imag) < 1e-12))


# ------------------------------------------------------------------ passive arm
@pytest.mark.parametrize("w, y", [(None, 0.0), (None, 0.3), (0.8, 0.2), (1.0, -0.2)])
def test_passive_arm_zeros_closed_form(w, y):
    """Internal-dynamics eigenvalues at the rest state with output y equal the roots of the closed-form
    zero polynomial alpha s^2 + D2 s + kappa (module doc of invctl_scenes/passive_arm.py): 1e-9 relative
    (AD-exact Jacobians, equilibria to 1e-12)."""
    model = passive_arm.build(**({} if w is None else {"w": w}))
    q1, q2 = passive_arm.equilibrium(model, y)
    q0 = equilibrium_point(model, y, guess=[q1, q2])
    np.testing.assert_allclose(q0, [q1, q2], atol=1e-10)
    assert_same_zeros(internal_eigenvalues_at(model, q0), np.roots(passive_arm.zero_polynomial(model, q1, q2)),
                      rtol=1e-9)
    zs = passive_arm.zeros(model, y)
    assert np.sum(zs.real > 0) == 1  # non-minimum phase for w > b / (b + c0)


def test_passive_arm_relative_degree_lost_where_closed_form_says():
    """Gamma = (b - w (b + c0 cos q2)) / det M vanishes at the elbow angle of singular_elbow_angle."""
    model = passive_arm.build()
    q2s = passive_arm.singular_elbow_angle(model.values)
    gamma = ca.Function("g", [model.q, model.theta],
                        [ca.mtimes(ca.jacobian(model.h, model.q), ca.solve(model.M, model.B))])
    for q1 in (-0.5, 0.0, 0.7):
        assert abs(float(gamma([q1, q2s], model.theta_values))) < 1e-12
        assert float(gamma([q1, 0.0], model.theta_values)) * float(gamma([q1, q2s + 0.1], model.theta_values)) < 0


# ------------------------------------------------------------------ flexible arm
def _passive_twin(**flex):
    """The passive arm with the parameters of a 2-link flexible arm (homogeneous equal links, alpha = 0)."""
    f = {**flexible_arm.PARAMS, **flex}
    return passive_arm.build(m1=f["m"], m2=f["m"], L1=f["l"], L2=f["l"], c2=f["k"], D2=f["d"], g=f["g"], w=f["w"])


def test_flexible_arm_n2_is_the_passive_arm():
    """Absolute angles theta = T q (T = [[1, 0], [1, 1]]) of the closed-form model against the Lagrangian
    passive arm in relative angles: M_rel = T^T M_abs T, f_rel = T^T f_abs, B_rel = T^T B_abs,
    h_rel(q) = h_abs(T q).  Same physics by two constructions: round-off only (1e-12 relative)."""
    flex = flexible_arm.build(n=2, alpha=0.0, w=0.7)
    arm = _passive_twin(alpha=0.0, w=0.7)
    T = np.array([[1.0, 0.0], [1.0, 1.0]])
    rng = np.random.default_rng(0)
    for _ in range(10):
        q, v = rng.uniform(-1, 1, 2), rng.uniform(-2, 2, 2)
        th, om = T @ q, T @ v
        M_rel = T.T @ flex.evaluate("M", th) @ T
        f_rel = T.T @ flex.evaluate("f", th, om).ravel()
        np.testing.assert_allclose(arm.evaluate("M", q), M_rel, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(arm.evaluate("f", q, v).ravel(), f_rel, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(arm.evaluate("B", q), T.T @ flex.evaluate("B", th), atol=0)
        np.testing.assert_allclose(arm.evaluate("h", q), flex.evaluate("h", th), rtol=1e-14)


def test_flexible_arm_closed_form_equals_lagrangian():
    """n = 4: M and f of the closed form (mu_ij cos(theta_i - theta_j)) against Model.from_lagrangian with
    the kinetic energy of the link centres (AD: Hessian and Coriolis terms), the same potential, springs,
    dampers and Rayleigh damping as generalized force.  Round-off only: 1e-12 relative."""
    n = 4
    flex = flexible_arm.build(n=n)
    p = flex.params
    l, m, k, d, alpha, g = (p[s] for s in ("l", "m", "k", "d", "alpha", "g"))
    th, v = ca.SX.sym("th", n), ca.SX.sym("v", n)
    pos, T, V = ca.SX.zeros(2), 0, 0
    for i in range(n):
        e = ca.vertcat(ca.sin(th[i]), -ca.cos(th[i]))
        centre = pos + 0.5 * l * e
        vel = ca.jtimes(centre, th, v)
        T += 0.5 * m * ca.sumsqr(vel) + 0.5 * (m * l**2 / 12) * v[i] ** 2
        V += m * g * centre[1]
        pos = pos + l * e
    rel, relv = th[1:] - th[:-1], v[1:] - v[:-1]
    V += 0.5 * k * ca.sumsqr(rel)
    R = 0.5 * d * ca.sumsqr(relv)
    lag = Model.from_lagrangian("lagrange_arm", th, v, flex.params, flexible_arm.PARAMS, T=T, V=V,
                                Q=-ca.gradient(R, v), B=ca.DM([[1], [0], [0], [0]]), h=th[1])
    Mf = ca.Function("M", [th, flex.theta], [lag.M])
    damp = ca.Function("f", [th, v, flex.theta], [lag.f - alpha * ca.mtimes(lag.M, v)])
    rng = np.random.default_rng(1)
    for _ in range(10):
        q, qd = rng.uniform(-1, 1, n), rng.uniform(-2, 2, n)
        np.testing.assert_allclose(flex.evaluate("M", q), np.array(Mf(q, flex.theta_values)), rtol=1e-12,
                                   atol=1e-14)
        np.testing.assert_allclose(flex.evaluate("f", q, qd).ravel(),
                                   np.array(damp(q, qd, flex.theta_values)).ravel(), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("n", [3, 6])
def test_flexible_arm_zeros_against_numpy_linear_model(n):
    """At the hanging arm the internal-dynamics eigenvalues equal the zeros of the numpy linear model
    (M, K, D of flexible_arm.linear_matrices, Rosenbrock pencil by scipy's QZ): 1e-8 relative (simple
    zeros of a pencil of norm ~1e3 are accurate to ~1e-12 in both routes)."""
    model = flexible_arm.build(n=n)
    M, K, D = flexible_arm.linear_matrices(n, model.values)
    A = np.block([[np.zeros((n, n)), np.eye(n)], [-np.linalg.solve(M, K), -np.linalg.solve(M, D)]])
    B = np.concatenate([np.zeros(n), np.linalg.solve(M, np.eye(n)[0])])
    w = model.values["w"]
    C = np.zeros(2 * n)
    C[:2] = [1 - w, w]
    R = np.block([[A, B[:, None]], [C[None, :], np.zeros((1, 1))]])
    E = np.diag(np.r_[np.ones(2 * n), 0.0])
    z = sla.eigvals(R, E)
    z = z[np.isfinite(z) & (np.abs(z) < 1e8)]
    assert_same_zeros(internal_eigenvalues_at(model, np.zeros(n)), z, rtol=1e-8)
    assert np.sum(z.real > 0) == 1 and np.all(np.abs(z.imag[z.real > 0]) < 1e-9)  # one real unstable zero


# ------------------------------------------------------------------ python-control interop
GALLERY = [
    ("cartpole", cartpole.build, {}),
    ("two_link_arm", two_link_arm.build, {}),
    ("mass_chain", mass_chain.build, {"n": 2}),
    ("mass_chain", mass_chain.build, {"n": 4}),
    ("passive_arm", passive_arm.build, {}),
    ("flexible_arm", flexible_arm.build, {}),
    ("flexible_arm", flexible_arm.build, {"n": 6}),
]


@pytest.mark.parametrize("name, build, params", GALLERY, ids=[f"{g[0]}-{g[2].get('n', 'default')}" for g in GALLERY])
def test_internal_eigenvalues_equal_python_control_zeros(name, build, params):
    """At the rest state on y_ref(t0) of every gallery scene, the eigenvalues of the linearized internal
    dynamics (003 Sect. 3) are python-control's transmission zeros of the plant linearization
    (invctl.analysis.statespace): 1e-7 relative (python-control's pencil QZ without slycot; the largest
    zero moduli are ~1e2, so this is ~1e-9 absolute per unit of |z|)."""
    model = build(**params)
    ref = load_scene(name).tracking.reference(model)
    q0 = equilibrium_point(model, ref(ref.t0).ravel()[0], guess=np.zeros(model.n))
    zeros_pc = control.zeros(plant_statespace(model, q0))
    assert_same_zeros(internal_eigenvalues_at(model, q0), zeros_pc, rtol=1e-7)


# ------------------------------------------------------------------ automatic setup and closed loop
@pytest.mark.parametrize("name, params", [("cartpole", {}), ("two_link_arm", {}), ("mass_chain", {}),
                                          ("passive_arm", {}), ("flexible_arm", {}), ("acrobot", {})])
def test_automatic_inversion_and_funnel_pipeline(name, params):
    """The pipeline of every gallery scene with nothing declared but the reference and the plant
    mismatch: invert() chooses selection and horizon and passes the forward check (output error
    < 1e-6 of the transition); C1 and C2 stay inside their funnels on the mismatched plant and C1 beats
    the feedforward alone (C3) on the cumulative output error."""
    scene = load_scene(name)
    assert not scene.tracking.inversion and not scene.tracking.feedback
    model = scene.model(params)
    ref = scene.tracking.reference(model)
    inv = invert(model, ref, q_guess=scene.tracking.initial_configuration(model))
    fc = forward_check(model, inv, ref)
    amplitude = float(np.max(np.abs(ref(np.linspace(ref.t0, ref.tf, 11)))))
    assert fc["error"] < 1e-6 * amplitude
    study = run_tracking_study(scene, params, progress=False, inverse=inv)
    for c in ("C1", "C2"):
        run = study.runs[c]
        assert run.success and run.max_funnel_ratio < 1.0, (c, run.status, run.max_funnel_ratio)
    assert study.runs["C1"].cumulative_errors["output"] < study.runs["C3"].cumulative_errors["output"]
