"""Mass-matrix solves without a symbolic inverse (invctl.model.linalg) and the formulations built on them:
the servo-constraint ODE and its Jacobian by the implicit-function rule, the constrained acceleration with
its custom Jacobian, the momentum internal coordinates.  Each is checked against a second method (numpy
solves, full AD through ``ca.solve``, finite differences, the (27) coordinates)."""
from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import invctl_scenes.cartpole as cartpole
import invctl_scenes.flexible_arm as flexible_arm
import invctl_scenes.manipulator as manipulator
import invctl_scenes.two_link_arm as two_link_arm
from invctl.analysis import internal_dynamics, linearize_internal
from invctl.analysis.internal import coordinate_form
from invctl.inversion.servo import ServoModel
from invctl.model.linalg import SymmetricSolver, solve_derivative
from invctl.simulate.closed_loop import plant_acceleration


@pytest.mark.parametrize("n", [1, 3, 12])
def test_symmetric_solver_against_numpy(n):
    """LDL^T solves of random SPD matrices (condition ~1e2): round-off only, 1e-12 relative."""
    rng = np.random.default_rng(n)
    Ms, Bs = ca.SX.sym("M", n, n), ca.SX.sym("B", n, 3)
    f = ca.Function("f", [Ms, Bs], [SymmetricSolver(0.5 * (Ms + Ms.T)).solve(Bs)])
    A = rng.normal(size=(n, n))
    A = A @ A.T + n * np.eye(n)
    B = rng.normal(size=(n, 3))
    np.testing.assert_allclose(np.array(f(A, B)), np.linalg.solve(A, B), rtol=1e-12, atol=1e-14)


def test_symmetric_solver_keeps_structure():
    """A diagonal M factorizes into nothing: M^-1 b is b_i / m_i, no fill-in terms."""
    m, b = ca.SX.sym("m", 4), ca.SX.sym("b", 4)
    x = SymmetricSolver(ca.diag(m)).solve(b)
    assert ca.Function("f", [m, b], [x]).n_instructions() <= 3 * 4 + 4


def test_solve_derivative_against_ad_through_ca_solve():
    """d(M(x)^-1 b(x))/dx by the implicit rule equals AD through CasADi's symbolic solve: 1e-12."""
    x = ca.SX.sym("x", 3)
    M = ca.vertcat(ca.horzcat(2 + ca.sin(x[0]) ** 2, x[1], 0.1), ca.horzcat(x[1], 3 + x[2] ** 2, 0.2 * x[0]),
                   ca.horzcat(0.1, 0.2 * x[0], 4))
    b = ca.vertcat(ca.cos(x[2]), x[0] * x[1], 1)
    A = ca.SX.sym("A", 3)
    solver = SymmetricSolver(M)
    mine = solve_derivative(solver, b - ca.mtimes(M, A), A, solver.solve(b), x)
    ref = ca.jacobian(ca.solve(M, b), x)
    f = ca.Function("f", [x], [mine, ref])
    for xv in np.random.default_rng(0).uniform(-1, 1, (5, 3)):
        a, r = (np.array(v) for v in f(xv))
        np.testing.assert_allclose(a, r, rtol=1e-12, atol=1e-13)


def _reference_servo(model, formulation, omega=10.0):
    """The servo-constraint ODE by AD through ca.solve (the formulation before the LDL^T rewrite):
    ``(X, Y, theta) -> (F, dF/dX, A_z)``."""
    n, l, p, m = model.n, model.ell, model.p, model.m
    X, Y = ca.SX.sym("X", 2 * n + l + p + m), ca.SX.sym("Y", 4 * m)
    q, v, z = X[:n], X[n:2 * n], X[2 * n:]
    lam, mu, u = z[:l], z[l:l + p], z[l + p:]

    def s(e):
        return ca.substitute([ca.SX(e)], [model.q, model.v], [q, v])[0]

    M, f, B, G, J, j, h = (s(e) for e in (model.M, model.f, model.B, model.G, model.J, model.j, model.h))
    yr, yd, ydd, yddd = (Y[k * m:(k + 1) * m] for k in range(4))
    H = ca.jacobian(h, q)
    force = f + ca.mtimes(B, u)
    if l:
        force += ca.mtimes(G.T, lam)
    if p:
        force += ca.mtimes(J.T, mu)
    a = ca.solve(M, force)
    phi_p = ca.vertcat(s(model.g), h - yr)
    phi_v = ca.vertcat(ca.mtimes(G, v), ca.mtimes(J, v) + j, ca.mtimes(H, v) - yd)
    vel = ca.vertcat(ca.mtimes(G, v), ca.mtimes(J, v) + j, ca.mtimes(H, v))
    phi_a = (ca.mtimes(ca.jacobian(vel, q), v) + ca.mtimes(ca.jacobian(vel, v), a)
             - ca.vertcat(ca.SX.zeros(l + p), ydd))
    Az = ca.jacobian(phi_a, z)
    rest = (ca.mtimes(ca.jacobian(phi_a, q), v) + ca.mtimes(ca.jacobian(phi_a, v), a)
            + ca.mtimes(ca.jacobian(phi_a, Y), ca.vertcat(yd, ydd, yddd, ca.SX.zeros(m))))
    if formulation == "baumgarte":
        w = omega
        parts = [3 * w * phi_a[:l] + 3 * w**2 * phi_v[:l] + w**3 * phi_p[:l]] if l else []
        parts += [2 * w * phi_a[l:l + p] + w**2 * phi_v[l:l + p]] if p else []
        parts += [3 * w * phi_a[l + p:] + 3 * w**2 * phi_v[l + p:] + w**3 * phi_p[l:]]
        rest += ca.vertcat(*parts)
    F = ca.vertcat(v, a, -ca.solve(Az, rest))
    return ca.Function("ref", [X, Y, model.theta], [F, ca.jacobian(F, X), Az])


MODELS = [("manipulator", manipulator.build, manipulator.initial_configuration), ("cartpole", cartpole.build, None),
          ("two_link_redundant", two_link_arm.build_redundant, None),
          ("flexible_arm_4", lambda: flexible_arm.build(n=4), None)]


@pytest.mark.parametrize("name, build, q_of", MODELS, ids=[m[0] for m in MODELS])
@pytest.mark.parametrize("formulation", ["jerk", "baumgarte"])
def test_servo_ode_and_jacobian_equal_full_ad(name, build, q_of, formulation):
    """F, dF/dX (symbolic and numeric solves) and A_z of the rewritten servo model equal the full-AD
    formulation at random states: 1e-11 relative (round-off of two different factorizations)."""
    model = build()
    ref = _reference_servo(model, formulation)
    servo = ServoModel(model, formulation, 10.0)
    rng = np.random.default_rng(3)
    K = 8
    X = rng.normal(size=(servo.layout.nx, K)) * 0.3
    if q_of is not None:
        X[:model.n] += np.asarray(q_of(model))[:, None]
    Y = rng.normal(size=(4 * model.m, K))
    th = np.tile(model.theta_values[:, None], (1, K))
    F0, J0, A0 = (np.array(o) for o in ref.map(K)(X, Y, th))
    for fn in (servo.rhs_jac, servo.rhs_jac_numeric):
        F1, J1 = (np.array(o) for o in fn.map(K)(X, Y, th))
        np.testing.assert_allclose(F1, F0, rtol=1e-11, atol=1e-11 * np.max(np.abs(F0)))
        np.testing.assert_allclose(J1, J0, rtol=1e-11, atol=1e-11 * np.max(np.abs(J0)))
    np.testing.assert_allclose(np.array(servo.decoupling.map(K)(X, Y, th)), A0, rtol=1e-11,
                               atol=1e-13 * np.max(np.abs(A0)))


def test_servo_jacobian_size_is_polynomial_of_low_degree():
    """SX instructions of dF/dX for the n-link arm, n = 4, 8, 16: the fitted exponent stays below 2.6
    (O(n^2) per right-hand side of the mass-matrix solves, 2n + 1 of them, plus O(n^3) once; AD through
    a symbolic QR grew like n^3.6 here).  Instruction counts are deterministic (no timing)."""
    ns = np.array([4, 8, 16])
    sizes = [ServoModel(flexible_arm.build(n=int(n)), "baumgarte", 10.0).rhs_jac.n_instructions() for n in ns]
    assert np.polyfit(np.log(ns), np.log(sizes), 1)[0] < 2.6


def test_constrained_acceleration_and_its_custom_jacobian():
    """The manipulator's Baumgarte-stabilized acceleration: (a, lam) equal the numpy KKT solve (1e-12), and the
    Jacobian CVODES uses (custom, implicit rule) equals central differences (1e-7: step 1e-6, O(h^2) error)."""
    model = manipulator.build()
    acc = plant_acceleration(model)
    q0 = manipulator.initial_configuration(model)
    v0, u0 = np.array([0.1, -0.2, 0.3, 0.1, 0.5]), np.array([1.0, -2.0])
    th = model.theta_values
    a, lam = (np.array(o).ravel() for o in acc(q0, v0, u0, th))
    M, f = model.evaluate("M", q0), model.evaluate("f", q0, v0).ravel()
    G, B = model.evaluate("G", q0), model.evaluate("B", q0)
    Gv = ca.mtimes(model.G, model.v)
    gdd = np.array(ca.Function("g", [model.q, model.v, model.theta], [ca.jtimes(Gv, model.q, model.v)])(q0, v0, th))
    bias = -gdd.ravel() - 2 * 20.0 * G @ v0 - 20.0**2 * model.evaluate("g", q0).ravel()
    sol = np.linalg.solve(np.block([[M, -G.T], [G, np.zeros((2, 2))]]), np.r_[f + B @ u0, bias])
    np.testing.assert_allclose(a, sol[:5], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(lam, sol[5:], rtol=1e-12, atol=1e-12)
    qs, vs, us = ca.MX.sym("q", 5), ca.MX.sym("v", 5), ca.MX.sym("u", 2)
    jac = ca.Function("J", [qs, vs, us], [ca.jacobian(ca.vertcat(*acc(qs, vs, us, th)), ca.vertcat(qs, vs, us))])
    Jv = np.array(jac(q0, v0, u0))
    x0, h = np.r_[q0, v0, u0], 1e-6

    def F(x):
        return np.concatenate([np.array(o).ravel() for o in acc(x[:5], x[5:10], x[10:], th)])

    Jfd = np.column_stack([(F(x0 + h * e) - F(x0 - h * e)) / (2 * h) for e in np.eye(12)])
    np.testing.assert_allclose(Jv, Jfd, rtol=1e-7, atol=1e-7 * np.max(np.abs(Jv)))


def test_momentum_coordinates_give_the_same_internal_dynamics():
    """n = 4 (eta2 of dimension 3): the (27) coordinates and the momentum form phi2 = T2^T M (proof of
    Lemma 3.1) linearize to the same eigenvalues (1e-10 relative: both are the zeros of the plant), the
    momentum rows satisfy L_K phi = 0, and "auto" picks (27) up to dimension 3 and the momentum form beyond."""
    model = flexible_arm.build(n=4)
    q0 = np.zeros(4)
    eigs = []
    for form in ("lemma32", "momentum"):
        idyn = internal_dynamics(model, "sect3", point=q0, form=form, samples=10)
        assert idyn.checks["LK_max"] < 1e-12
        eta0 = np.array(idyn.eta(q0, np.zeros(4), model.theta_values)).ravel()
        eigs.append(np.sort_complex(linearize_internal(model, idyn, [([[0.0], [0.0]], eta0)]).eigenvalues))
    np.testing.assert_allclose(eigs[0], eigs[1], rtol=1e-10)
    assert coordinate_form(model) == "lemma32" and coordinate_form(flexible_arm.build(n=5)) == "momentum"
    assert coordinate_form(manipulator.build()) == "lemma32"  # q-dependent constraint directions
