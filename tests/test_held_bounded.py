"""The held bounded inversion and the held mesh refinement of :class:`InversionSolver`: a re-solve
after a parameter or bound change starts from the last primal-dual optimum, builds no CasADi
Function and reaches the optimum a fresh ``invert`` finds; a structure change says why it
rebuilds; a refinement re-solve starts on the last refined mesh and still meets ``tol``."""
from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import invctl_scenes.manipulator as scene
from invctl.inversion import Bounds, InversionSolver, invert
from invctl.inversion import ocp
from invctl.inversion.verify import forward_check

# IPOPT stops at a KKT error of 1e-10 (ipopt.tol, constr_viol_tol): two solves of the same strictly convex
# Gauss-Newton subproblem agree to a few times that in the objective; the states, of size ~10, to 1e-7
# relative leaves three orders of margin for the conditioning of the least-squares problem
OBJ_RTOL, X_RTOL = 1e-8, 1e-7
KW = dict(N=20, compiled=False)


@pytest.fixture(scope="module")
def model():
    return scene.build(**scene.PRESETS["guess"])


@pytest.fixture(scope="module")
def ref(model):
    return scene.reference(model)


@pytest.fixture(scope="module")
def q0(model):
    return scene.initial_configuration(model)


@pytest.fixture(scope="module")
def held(model, ref, q0):
    """A held solver under |u2| <= 8 N (the exact inverse needs 9.7 N): solved once, and once re-solved."""
    solver = InversionSolver(model, ref, q_guess=q0, bounds=Bounds(u={"u2": 8.0}), **KW)
    first = solver.solve()
    solver.solve(m3=0.505)
    return solver, first


def _counting(monkeypatch):
    out = []
    init, fmap, nlpsol, tinit = ca.Function.__init__, ca.Function.map, ca.nlpsol, ocp.OCPTranscription.__init__

    def counting(name, fn):
        def wrapped(*a, **k):
            out.append(name)
            return fn(*a, **k)
        return wrapped

    monkeypatch.setattr(ca.Function, "__init__", counting("Function", init))
    monkeypatch.setattr(ca.Function, "map", counting("map", fmap))
    monkeypatch.setattr(ca, "nlpsol", counting("nlpsol", nlpsol))
    monkeypatch.setattr(ocp.OCPTranscription, "__init__", counting("OCPTranscription", tinit))
    return out


def test_held_bounded_resolve_builds_nothing_and_equals_a_fresh_invert(model, ref, q0, held, monkeypatch):
    solver, first = held
    assert not first.diagnostics["tracking"]["exact"]  # the relaxed problem, not the exact inverse
    built = _counting(monkeypatch)
    inv = solver.solve(m3=0.51)
    assert built == []  # nothing built: plan, exact inverse, relaxed solve, result and checks
    info = solver.info
    assert info["route"] == "bounded" and info["rebuilt"] is None
    assert "last optimum (primal-dual)" in info["reused"] and inv.diagnostics["held"]
    monkeypatch.undo()
    fresh = invert(model.with_params(m3=0.51), ref, q_guess=q0, bounds=Bounds(u={"u2": 8.0}), **KW)
    d, f = inv.diagnostics, fresh.diagnostics
    assert d["objective"] == pytest.approx(f["objective"], rel=OBJ_RTOL)
    assert np.max(np.abs(inv.X_mesh - fresh.X_mesh)) <= X_RTOL * np.max(np.abs(fresh.X_mesh))
    # from the last optimum: fewer iterations than the cold start (measured 24 cold, 7-10 held at N = 20, 40)
    assert d["iterations"] < f["iterations"]


def test_held_bound_change_moves_the_active_bound(model, ref, q0, held):
    solver, _first = held
    inv = solver.solve(bounds=Bounds(u={"u2": 7.0}))
    assert "last optimum (primal-dual)" in solver.info["reused"] and solver.info["rebuilt"] is None
    u2 = inv._slice("u").start + 1
    assert np.max(np.abs(inv.X_mesh[u2])) == pytest.approx(7.0, abs=1e-6)  # the bound is active at 7, not 8
    assert [e["value"] for e in inv.diagnostics["bounds"]["active"] if e["bound"] == "u[u2]"] == [-7.0, 7.0]
    fresh = invert(model, ref, q_guess=q0, bounds=Bounds(u={"u2": 7.0}), **KW)
    assert inv.diagnostics["objective"] == pytest.approx(fresh.diagnostics["objective"], rel=OBJ_RTOL)
    # the bound is this solve's: the next solve is the solver's own (8 N) again
    again = solver.solve()
    assert np.max(np.abs(again.X_mesh[u2])) == pytest.approx(8.0, abs=1e-6)


def test_held_structure_change_rebuilds_and_says_why(held):
    solver, _first = held
    inv = solver.solve(bounds=Bounds(u={"u1": 60.0, "u2": 8.0}))
    assert "bounded entries" in solver.info["rebuilt"] and "transcription" not in solver.info["reused"]
    u2 = inv._slice("u").start + 1
    assert np.max(np.abs(inv.X_mesh[u2])) == pytest.approx(8.0, abs=1e-6)


def test_held_refinement_starts_on_the_last_mesh(model, ref, q0):
    tol = 5e-5
    solver = InversionSolver(model, ref, q_guess=q0, N=20, tol=tol, backend="newton", compiled=False)
    first = solver.solve()
    assert len(first.diagnostics["meshes"]) > 1  # N = 20 misses tol (1.1e-4): refined
    inv = solver.solve(m3=0.51)
    meshes = inv.diagnostics["meshes"]
    assert meshes[0]["N"] == first.N and solver.info["held_mesh"]  # started on the last refined mesh
    assert len(meshes) == 1  # which still meets tol: not refined further
    fc = forward_check(model.with_params(m3=0.51), inv, ref)
    assert fc["error"] <= tol
