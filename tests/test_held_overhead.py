"""The held solver's setup without its overhead: the background compile starts after the first solve,
the remembered spectra follow the parameters, the batched pieces equal their one-by-one forms."""
from __future__ import annotations

import math

import numpy as np
import pytest

import invctl_scenes.manipulator as scene
from invctl.inversion import InversionSolver, square
from invctl.inversion.boundary import tangent_dynamics, tangent_spectra
from invctl.inversion.cache import equilibrium_solver, servo_model
from invctl.inversion.plan import _tail_span
from invctl.inversion.servo import _decoupling_scales


def test_background_compile_starts_after_the_first_solve(model, ref, tmp_path, monkeypatch):
    from invctl.inversion import compiled

    if compiled.compiler() is None:
        pytest.skip("no C compiler")
    monkeypatch.setenv("INVCTL_CACHE", str(tmp_path))
    monkeypatch.setenv("INVCTL_BACKGROUND_COMPILE", "1")
    events = []
    solve = square._solve

    def recording_solve(*args, **kwargs):
        events.append("solve")
        out = solve(*args, **kwargs)
        events.append("solved")
        return out

    monkeypatch.setattr(square, "_solve", recording_solve)
    monkeypatch.setattr(compiled, "compile_in_background", lambda fns, **kw: events.append(("compile", len(fns))))
    solver = InversionSolver(model, ref, N=20, backend="newton", compiled="auto")
    solver.solve()
    assert events == ["solve", "solved", ("compile", 7)]  # all seven pieces missing, compiled once solved
    solver.solve(m3=0.55)
    assert events[3:] == ["solve", "solved"]  # started once


def test_remembered_spectra_follow_the_parameters(model, ref):
    servo = servo_model(model)
    Y = servo.reference_samples(ref, np.array([ref.t0]))[:, 0]
    X, _ = equilibrium_solver(model).solve(Y[:model.m], guess_q=scene.initial_configuration(model))
    for m3 in (0.5, 0.6, 0.5):  # the same point, other parameter values: no stale spectra
        th = model.with_params(m3=m3).theta_values
        A, _T, AT = tangent_dynamics(servo, X, Y, th)
        ev, evt = tangent_spectra(servo, X, Y, th)
        fresh = np.linalg.eigvals(np.array(servo.linearization(X, Y, th)[0]))
        assert np.allclose(np.sort_complex(ev), np.sort_complex(fresh), rtol=1e-12, atol=1e-12)
        assert np.allclose(np.sort_complex(evt), np.sort_complex(np.linalg.eigvals(np.array(AT))), rtol=1e-12,
                           atol=1e-12)
    th5, th6 = model.with_params(m3=0.5).theta_values, model.with_params(m3=0.6).theta_values
    assert not np.allclose(np.sort_complex(tangent_spectra(servo, X, Y, th5)[1]),
                           np.sort_complex(tangent_spectra(servo, X, Y, th6)[1]), rtol=1e-6)


def test_batched_equilibria_equal_the_one_by_one_solves(model, ref):
    eq = equilibrium_solver(model)
    n = model.n
    ys = np.asarray(ref(np.linspace(ref.t0, ref.tf, 3)), float).reshape(model.m, 3)
    X0, _ = eq.solve(ys[:, 0], guess_q=scene.initial_configuration(model))
    W0 = np.repeat(np.concatenate([X0[:n], X0[2 * n:]])[:, None], 3, axis=1)
    W, res = eq.solve_many(ys, W0)
    assert np.all(res < 1e-12)
    for k in range(3):
        X, _ = eq.solve(ys[:, k], guess_w=W0[:, k])
        assert np.allclose(W[:, k], np.concatenate([X[:n], X[2 * n:]]), rtol=0, atol=1e-10)


def test_one_real_mode_tail_span_is_the_closed_form():
    for rate in (0.7, 24.44):
        s, r, kappa = _tail_span(np.array([[-rate]]), 1e-8, 1e3)
        assert r == rate and kappa == pytest.approx(1.0, rel=1e-5)
        assert s == pytest.approx(math.log(1e8) / rate, rel=1e-6)  # ||exp(-rate s)|| = tol


def test_decoupling_scales_are_the_product_of_the_two_norms(model):
    import casadi as ca

    Q = np.array([scene.initial_configuration(model) + 0.1 * k for k in range(4)]).T
    got = _decoupling_scales(model, Q)
    H = ca.jacobian(model.h, model.q)
    f = ca.Function("parts", [model.q, model.theta], [model.M, ca.vertcat(model.G, model.J, H),
                                                      ca.horzcat(model.G.T, model.J.T, model.B)])
    for k in range(Q.shape[1]):
        M, C, W = (np.array(a) for a in f(Q[:, k], model.theta_values))
        want = np.linalg.norm(C @ np.linalg.inv(M), 2) * np.linalg.norm(W, 2)
        assert got[k] == pytest.approx(want, rel=1e-12)
