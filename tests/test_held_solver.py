"""The held solver's re-solve is the solve: it builds no CasADi Function (the result, its checks, the
re-plan and the reference samples reuse what the first solve built), still refuses a wrong answer, and
the sensitivities work on the held transcription."""
from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import invctl_scenes.manipulator as scene
from invctl.errors import InversionFailed
from invctl.inversion import InversionSolver, invert
from invctl.inversion import collocation as coll
from invctl.inversion import square
from invctl.inversion.cache import servo_model
from invctl.inversion.sensitivity import ParametricInverse


KW = dict(N=40, backend="newton", newton_tol=1e-12, compiled=False)


@pytest.fixture
def built(monkeypatch):
    """Every CasADi Function and Transcription constructed from Python while the test runs."""
    out = []
    init, fmap = ca.Function.__init__, ca.Function.map
    tinit = coll.Transcription.__init__

    def counting_init(self, *args, **kwargs):
        out.append("Function")
        init(self, *args, **kwargs)

    def counting_map(self, *args, **kwargs):
        out.append("map")
        return fmap(self, *args, **kwargs)

    def counting_tr(self, *args, **kwargs):
        out.append("Transcription")
        tinit(self, *args, **kwargs)

    monkeypatch.setattr(ca.Function, "__init__", counting_init)
    monkeypatch.setattr(ca.Function, "map", counting_map)
    monkeypatch.setattr(coll.Transcription, "__init__", counting_tr)
    return out


@pytest.mark.parametrize("given", [False, True], ids=["automatic horizon", "horizon given"])
def test_resolve_builds_no_casadi_function_and_equals_a_fresh_invert(model, ref, built, given):
    opts = {k: scene.INVERSION[k] for k in ("T0", "Tf", "start", "end")} if given else {}
    solver = InversionSolver(model, ref, q_guess=scene.initial_configuration(model), **KW, **opts)
    solver.solve()
    solver.solve(m3=0.52)
    assert built  # the hook sees what a solve builds
    del built[:]
    for m3 in (0.55, 0.49):
        inv = solver.solve(m3=m3)
    assert built == []  # nothing built: not the result, its checks, the plan, nor the reference samples
    fresh = invert(model.with_params(m3=0.49), ref, q_guess=scene.initial_configuration(model), **KW, **opts)
    # the re-plan is warm-started from the last path: the horizon agrees to round-off
    assert np.max(np.abs(inv.t_mesh - fresh.t_mesh)) < 1e-12
    assert np.max(np.abs(inv.X_mesh - fresh.X_mesh)) <= 1e-10 * np.max(np.abs(fresh.X_mesh))
    for key, val in fresh.diagnostics["residuals"].items():
        assert inv.diagnostics["residuals"][key] == pytest.approx(val, rel=1e-6, abs=1e-13)


def test_wrong_resolve_still_fails_its_residual_check(model, ref, monkeypatch):
    """A solver that returns its start unchanged as converged: the re-solve for a longer link (the
    last solution misses the new position constraints) raises, with the failed iterate."""
    solver = InversionSolver(model, ref, q_guess=scene.initial_configuration(model), **KW)
    solver.solve()
    real = square._solve

    def lying(tr, x0, p, **kw):
        x, info, s, b = real(tr, x0, p, **{**kw, "max_iter": 0})
        return x0, {**info, "success": True, "status": "converged (claimed)"}, s, b

    monkeypatch.setattr(square, "_solve", lying)
    with pytest.raises(InversionFailed, match="position-level constraints") as exc:
        solver.solve(L2=1.1, warm_start=solver.last)
    res = exc.value.partial.diagnostics["residuals"]
    # the same residuals as the check in CasADi's virtual machine, without the transcription
    vm = square.residuals(exc.value.partial, servo_model(model), ref, model.with_params(L2=1.1).theta_values)
    assert res["position"] > 1e-3
    for key, val in vm.items():
        assert res[key] == pytest.approx(val, rel=1e-12, abs=1e-15)


def test_reference_samples_outside_the_transition_are_its_rest_values(model, ref):
    servo = servo_model(model)
    inside = np.linspace(ref.t0, ref.tf, 7)
    for tails in ([-3.0, -0.5], [-1.25, -0.01]):
        t = np.r_[tails, inside, ref.tf + 0.2, ref.tf + 4.0]
        direct = np.vstack([np.array(o) for o in ref.function(3).map(t.size)(t[None, :])])
        assert np.array_equal(servo.reference_samples(ref, t), direct)


def test_reference_samples_of_a_reference_moving_outside_are_evaluated(model):
    """A reference that is not constant outside [t0, tf] (against its contract) is sampled as it is."""
    from invctl.reference import Reference

    servo = servo_model(model)
    t = ca.SX.sym("t")
    # the second is periodic with period tf - t0 (fmod: bit-equal samples at one and two transition lengths
    # outside, its derivatives there not zero)
    periodic = ca.sin(2 * np.pi * ca.fmod(t + 10.0, 1.0))
    for moving in (Reference(t, ca.vertcat(ca.sin(3 * t), 0.1 * t ** 4), 0.0, 1.0, 4),
                   Reference(t, ca.vertcat(periodic, 0.5 * periodic), 0.0, 1.0, 4)):
        tt = np.linspace(-2.0, 3.0, 41)
        direct = np.vstack([np.array(o) for o in moving.function(3).map(tt.size)(tt[None, :])])
        assert np.array_equal(servo.reference_samples(moving, tt), direct)


def test_sensitivities_use_the_held_transcription(model, ref, built):
    # N = 36: no other test of this module holds a transcription of that size (nothing cached to reuse)
    solver = InversionSolver(model, ref, q_guess=scene.initial_configuration(model), N=36, backend="newton")
    inv = solver.solve()
    pi = ParametricInverse.from_inverse(model, ref, inv)
    assert pi.transcription() is solver.transcription
    del built[:]
    sens = pi.sensitivities(["m3"])
    assert "Transcription" not in built
    # against a central difference of re-solves (same mesh and y_ref; step and tolerance as in
    # tests/test_sensitivity.py: truncation and rounding ~1e-8 relative)
    t = np.linspace(inv.T0, inv.Tf, 301)
    h = 1e-4 * 0.5
    up, dn = (pi.resolve(model.with_params(m3=0.5 + s), tol=1e-12).inverse.X(t) for s in (h, -h))
    an = sens.derivative("m3").X(t)
    assert np.max(np.abs((up - dn) / (2 * h) - an)) <= 1e-6 * np.max(np.abs(an))


def test_background_worker_is_not_waited_for(tmp_path, monkeypatch):
    """The compile worker is a child of the caller that the caller does not wait for: it is still
    running (held by a gate) when ``compile_in_background`` returns, and is reaped once done."""
    import os
    import time

    from invctl.inversion import compiled

    if compiled.compiler() is None or not hasattr(os, "fork"):
        pytest.skip("no C compiler or no fork")
    monkeypatch.setenv("INVCTL_CACHE", str(tmp_path))
    monkeypatch.setenv("INVCTL_BACKGROUND_COMPILE", "1")
    gate, build = tmp_path / "gate", compiled._build

    def gated(fn, name, flags):
        while not gate.exists():
            time.sleep(0.01)
        build(fn, name, flags)

    monkeypatch.setattr(compiled, "_build", gated)
    x = ca.SX.sym("x", 2)
    fn = ca.Function("gated", [x], [ca.cos(x) * x[1]])
    try:
        lock = compiled.compile_in_background([fn], key="gate-test")
        assert lock is not None and lock.exists() and len(compiled._WORKERS) == 1
        assert os.waitpid(compiled._WORKERS[0], os.WNOHANG) == (0, 0)  # this process's child, running
    finally:
        gate.write_text("go")  # never leave a worker waiting
    for _ in range(1200):
        compiled._reap()
        if not compiled._WORKERS:
            break
        time.sleep(0.1)
    assert compiled._WORKERS == [] and not lock.exists() and compiled.is_cached(fn, key="gate-test")


def test_linearizations_use_the_compiled_jacobian_once_a_transcription_has_it(tmp_path, monkeypatch):
    """A compiled transcription hands its ``rhs_jac`` to the servo model: the plan's and the dichotomy
    check's linearizations run in C and equal the virtual machine's (the same operations)."""
    from invctl.inversion import compiled
    from invctl.model import Model, ParamSet
    from invctl.reference import Reference, poly9_timing_law

    if compiled.compiler() is None:
        pytest.skip("no C compiler")
    monkeypatch.setenv("INVCTL_CACHE", str(tmp_path))
    P = ParamSet(["m", "c"])
    q, v = ca.SX.sym("q", 1), ca.SX.sym("v", 1)
    md = Model.from_lagrangian("mass", q, v, P, {"m": 2.0, "c": 0.5}, T=0.5 * P["m"] * v[0] ** 2, Q=-P["c"] * v,
                               B=ca.DM([[1.0]]), h=q)
    t = ca.SX.sym("t")
    yr = Reference(t, poly9_timing_law(t, 0.0, 1.0), 0.0, 1.0, 4)
    servo = servo_model(md)
    X, Y = np.array([0.3, -0.2, 0.7]), np.array([0.3, 0.1, -0.4, 2.0])
    vm = servo.linearization(X, Y, md.theta_values)
    solver = InversionSolver(md, yr, N=30, backend="newton", compiled=True)
    assert "servo_rhs_jac" in solver.solve().diagnostics["compiled_pieces"]
    assert servo.__dict__["_compiled_rhs_jac"].is_a("External")
    for a, b in zip(servo.linearization(X, Y, md.theta_values), vm):
        assert np.max(np.abs(a - b)) <= 1e-14 * max(1.0, np.max(np.abs(b)))
    assert np.allclose(vm[0], np.array(servo.rhs_jac(X, Y, md.theta_values)[1]), rtol=1e-14, atol=1e-14)
