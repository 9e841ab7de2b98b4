"""The held inversion solver: a re-solve after a parameter change builds nothing new, remaps the mesh
when the automatic horizon moves, and equals a fresh ``invert`` with the changed parameter to round-off;
compiled pieces from the background worker are picked up."""
from __future__ import annotations

import time

import casadi as ca
import numpy as np
import pytest

import invctl_scenes.manipulator as scene
from invctl.errors import InversionFailed, ParameterError
from invctl.inversion import InversionSolver, invert
from invctl.inversion import collocation as coll
from invctl.results import Status

#: Newton to 1e-12 in max |g|: two converged solves of the same problem agree to round-off
KW = dict(N=60, backend="newton", newton_tol=1e-12, compiled=False)


def _rel(a, b):
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


@pytest.fixture
def count_transcriptions(monkeypatch):
    built = []
    init = coll.Transcription.__init__

    def counting(self, *args, **kwargs):
        built.append(self)
        init(self, *args, **kwargs)

    monkeypatch.setattr(coll.Transcription, "__init__", counting)
    return built


def test_resolve_after_parameter_change_reuses_problem_and_equals_fresh_solve(model, ref, count_transcriptions):
    q0 = scene.initial_configuration(model)
    solver = InversionSolver(model, ref, q_guess=q0, **KW)
    first = solver.solve()
    tr = solver.transcription
    n_built = len(count_transcriptions)
    again = solver.solve(m3=0.56)
    # nothing rebuilt: the same transcription object, no Transcription constructed
    assert solver.transcription is tr and len(count_transcriptions) == n_built
    assert "transcription" in solver.info["reused"] and solver.info["rebuilt"] is None
    # the automatic horizon moves with m3: the same transcription on the remapped mesh, reported
    assert solver.info["remapped"] is not None and again.T0 != first.T0
    assert solver.info["remapped"]["T0"] == [first.T0, again.T0]
    fresh = invert(model.with_params(m3=0.56), ref, q_guess=q0, **KW)
    assert abs(again.T0 - fresh.T0) < 1e-12 and abs(again.Tf - fresh.Tf) < 1e-12
    assert _rel(again.X_mesh, fresh.X_mesh) < 1e-10
    # warm-started: the factorization of the last solve still contracts (simplified Newton)
    assert again.diagnostics["factorizations"] < fresh.diagnostics["factorizations"]
    # back to the model as given: equals the first solve
    assert _rel(solver.solve().X_mesh, first.X_mesh) < 1e-10
    assert solver.last is not None and solver.last.diagnostics["solver"]["held"]


def test_given_horizon_reuses_the_last_solution_vector(model, ref):
    hand = {k: scene.INVERSION[k] for k in ("T0", "Tf", "start", "end")}
    solver = InversionSolver(model, ref, **hand, **KW)
    solver.solve()
    inv = solver.solve(c=5.5)
    assert solver.info["remapped"] is None and "last solution" in solver.info["reused"]
    fresh = invert(model.with_params(c=5.5), ref, **hand, **KW)
    assert _rel(inv.X_mesh, fresh.X_mesh) < 1e-10
    cold = solver.solve(warm=False, c=5.5)
    assert _rel(cold.X_mesh, fresh.X_mesh) < 1e-10


def test_other_reference_that_moves_the_selection_rebuilds_and_says_so(model, ref):
    q0 = scene.initial_configuration(model)
    solver = InversionSolver(model, ref, q_guess=q0, **KW)
    solver.solve()
    tr = solver.transcription
    other = scene.reference(model, rf=(0.95, -0.85))  # the automatic selection at T0 takes v:beta_dot, not q:beta
    inv = solver.solve(reference=other)
    assert solver.transcription is not tr and solver.info["rebuilt"].startswith("boundary selection at T0: ")
    assert "v:beta_dot" in solver.info["rebuilt"].split("->")[1]
    assert solver.info["remapped"] is None  # the same horizon (to round-off): not reported as moved
    fresh = invert(model, other, q_guess=q0, **KW)
    assert _rel(inv.X_mesh, fresh.X_mesh) < 1e-10 and np.allclose(inv.t_mesh, fresh.t_mesh, rtol=0, atol=1e-12)


def test_other_model_and_mesh_reuse_the_transcription_and_equal_a_fresh_solve(model, ref, count_transcriptions):
    hand = {k: scene.INVERSION[k] for k in ("T0", "Tf", "start", "end")}
    solver = InversionSolver(model, ref, **hand, **KW)
    solver.solve()
    tr, n_built = solver.transcription, len(count_transcriptions)
    mesh = hand["T0"] + (hand["Tf"] - hand["T0"]) * np.linspace(0.0, 1.0, KW["N"] + 1) ** 1.1  # graded, same N
    other = model.with_params(c=5.5)
    inv = solver.solve(model=other, mesh=mesh)
    assert solver.transcription is tr and len(count_transcriptions) == n_built
    assert np.array_equal(inv.t_mesh, mesh) and solver.info["rebuilt"] is None
    fresh = invert(other, ref, mesh=mesh, **hand, **KW)
    assert _rel(inv.X_mesh, fresh.X_mesh) < 1e-10


def test_a_failed_solve_is_data_with_throw_false(model, ref):
    hand = {k: scene.INVERSION[k] for k in ("T0", "Tf", "start", "end")}
    solver = InversionSolver(model, ref, **hand, **dict(KW, max_iter=1))
    with pytest.raises(InversionFailed) as err:
        solver.solve()
    inv = solver.solve(throw=False)
    assert inv.status is Status.FAILED and inv.diagnostics["error"].startswith("InversionFailed: ")
    assert np.array_equal(inv.X_mesh, err.value.partial.X_mesh)  # the same last iterate as the exception's
    assert solver.last is None  # a failed solve is not a solution to warm-start from


def test_unknown_parameter_is_a_parameter_error(model, ref):
    solver = InversionSolver(model, ref, **KW)
    with pytest.raises(ParameterError, match="mass3.*m3"):
        solver.solve(mass3=0.6)


@pytest.mark.parametrize("fork", [True, False], ids=["fork", "new-interpreter"])
def test_background_compile_lands_in_the_cache(tmp_path, monkeypatch, fork):
    from invctl.inversion import compiled

    if compiled.compiler() is None or (fork and not hasattr(compiled.os, "fork")):
        pytest.skip("no C compiler or no fork")
    if not fork:
        monkeypatch.delattr(compiled.os, "fork", raising=False)
    monkeypatch.setenv("INVCTL_CACHE", str(tmp_path))
    monkeypatch.setenv("INVCTL_BACKGROUND_COMPILE", "1")
    x = ca.SX.sym("x", 3)
    fn = ca.Function("tiny", [x], [ca.sin(x) * x[0]])
    lock = compiled.compile_in_background([fn], key="test-key")
    assert lock is not None and lock.parent == tmp_path
    for _ in range(1200):  # the worker removes its lock file when done
        if not lock.exists():
            break
        time.sleep(0.1)
    assert compiled.is_cached(fn, key="test-key") and not list(tmp_path.glob("*.lock"))
    assert compiled.compile_in_background([fn], key="test-key") is None  # nothing missing
    c = compiled.compile_cached(fn, key="test-key")
    v = np.array([0.3, -1.2, 2.0])
    assert np.allclose(np.array(c(v)).ravel(), np.array(fn(v)).ravel(), rtol=1e-15, atol=0)


def test_transcription_picks_up_compiled_pieces(model, ref, tmp_path, monkeypatch):
    from invctl.inversion import compiled
    from invctl.inversion.cache import compiled_key, transcription

    if compiled.compiler() is None:
        pytest.skip("no C compiler")
    monkeypatch.setenv("INVCTL_CACHE", str(tmp_path))
    monkeypatch.setenv("INVCTL_BACKGROUND_COMPILE", "0")
    solver = InversionSolver(model, ref, N=30, backend="newton", compiled="auto")
    vm = solver.solve()
    tr = solver.transcription
    assert vm.diagnostics["compiled_pieces"] == [] and not tr.upgradable()
    compiled.compile_cached(tr.servo.rhs, key=compiled_key(tr.servo, tr.scheme))  # what the worker does first
    assert tr.upgradable()
    assert transcription(tr.servo, tr.selection, tr.scheme, tr.N, compiled="auto") is not tr
    inv = solver.solve(warm=False)
    assert solver.info["rebuilt"] == "functions compiled in the background are ready"
    assert inv.diagnostics["compiled_pieces"] == ["servo_rhs"]
    assert _rel(inv.X_mesh, vm.X_mesh) < 1e-10
    solver.solve()  # nothing new in the cache: nothing rebuilt
    assert solver.info["rebuilt"] is None
