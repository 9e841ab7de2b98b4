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


def test_held_bounded_resolve_builds_nothing_and_equals_a_fresh_invert(held, monkeypatch):
    solver, first = held
    assert not first.diagnostics["tracking"]["exact"]  # the relaxed problem, not the exact inverse
    built = _counting(monkeypatch)
    inv = solver.solve()  # the model as given, after the fixture's re-solve at m3 = 0.505
    assert built == []  # nothing built: plan, exact inverse, relaxed solve, result and checks
    info = solver.info
    assert info["route"] == "bounded" and info["rebuilt"] is None
    assert "last optimum (primal-dual)" in info["reused"] and inv.diagnostics["held"]
    monkeypatch.undo()
    fresh = first  # the solver's first solve is a fresh invert (invert is InversionSolver(...).solve())
    d, f = inv.diagnostics, fresh.diagnostics
    assert d["objective"] == pytest.approx(f["objective"], rel=OBJ_RTOL)
    assert np.max(np.abs(inv.X_mesh - fresh.X_mesh)) <= X_RTOL * np.max(np.abs(fresh.X_mesh))
    # from the last optimum: fewer iterations than the cold start (measured 24 cold, 7-10 held at N = 20, 40)
    assert d["iterations"] < f["iterations"]


def test_held_bound_change_moves_the_active_bound(model, ref, q0, held):
    solver, _first = held
    inv = solver.solve(bounds=Bounds(u={"u2": 7.0}))
    assert "last optimum (primal-dual)" in solver.info["reused"] and solver.info["rebuilt"] is None
    # from the last optimum moved by the predictor (bounded.predicted_start): measured 7 iterations (8.0 -> 7.0 N,
    # N = 20), 14-15 from the last optimum itself, 17 cold
    assert "predicted start" in solver.info["reused"] and inv.diagnostics["iterations"] <= 10
    u2 = inv._slice("u").start + 1
    assert np.max(np.abs(inv.X_mesh[u2])) == pytest.approx(7.0, abs=1e-6)  # the bound is active at 7, not 8
    assert [e["value"] for e in inv.diagnostics["bounds"]["active"] if e["bound"] == "u[u2]"] == [-7.0, 7.0]
    # warm=False: the cold start of a fresh invert (not from the last optimum), to the same optimum
    cold = solver.solve(bounds=Bounds(u={"u2": 7.0}), warm=False)
    assert "last optimum (primal-dual)" not in solver.info["reused"]
    assert cold.diagnostics["iterations"] > inv.diagnostics["iterations"]
    assert inv.diagnostics["objective"] == pytest.approx(cold.diagnostics["objective"], rel=OBJ_RTOL)
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


class _NoDerivatives(ca.Callback):
    """``fn`` evaluated numerically, without derivatives: a compiled function as ``casadi.external`` loads it."""

    def __init__(self, fn):
        ca.Callback.__init__(self)
        self.fn = fn
        self.construct(fn.name() + "_numeric", {})

    def get_n_in(self):
        return self.fn.n_in()

    def get_n_out(self):
        return self.fn.n_out()

    def get_sparsity_in(self, i):
        return self.fn.sparsity_in(i)

    def get_sparsity_out(self, i):
        return self.fn.sparsity_out(i)

    def eval(self, arg):
        return self.fn.call(arg)


RELAXED = dict(relaxed=True, bounded=(13,))
FREE_TIME = dict(relaxed=False, free_time=True, bounded=(13,), interior="points")
ELASTIC = dict(relaxed=True, bounded=(13,), rated=(1,), elastic=True)


@pytest.mark.parametrize("scheme, structure", [("hermite-simpson", RELAXED), ("hermite-simpson", FREE_TIME),
                                               ("hermite-simpson", ELASTIC), ("legendre2", ELASTIC)],
                         ids=["HS relaxed", "HS free time", "HS elastic", "legendre2 elastic"])
def test_compiled_derivative_assembly_equals_ad(model, scheme, structure, monkeypatch):
    """With compiled pieces (here: numeric functions without derivatives, no C compiler needed) the objective
    gradient comes from the assembled residual Jacobian and the Gauss-Newton Hessian from per-interval blocks:
    against CasADi's reverse AD of the uncompiled objective and the sparse product of the assembled Jacobian;
    the plain NLP (AD of the whole graph, hessian="ad") is still differentiable."""
    from invctl.inversion.boundary import Selection
    from invctl.inversion.cache import servo_model
    from invctl.inversion.schemes import get_scheme

    sv = servo_model(model)
    nx = sv.layout.nx
    sel = Selection(tuple(i for i in range(nx) if i != 8), (9,), tuple(str(i) for i in range(nx)))
    plain = ocp.OCPTranscription(sv, sel, get_scheme(scheme), 5, compiled=False, **structure)
    keep = []  # the callbacks must outlive the functions that call them
    monkeypatch.setattr(ocp, "_compile", lambda f: keep.append(_NoDerivatives(f)) or keep[-1])
    comp = ocp.OCPTranscription(sv, sel, get_scheme(scheme), 5, compiled=True, **structure)
    assert comp.compiled and not plain.compiled
    rng = np.random.default_rng(1)
    x, p, lam_g = rng.standard_normal(plain.nX), rng.random(plain.np), rng.standard_normal(plain.ng)
    if plain.free_time:
        x[plain.i_tau], p[plain._p_slices["tau_ref"]] = 1.2, 1.0
    f_ad = ca.Function("f", [plain._x, plain._p], [plain.f, ca.gradient(plain.f, plain._x)])
    f1, g1 = (np.array(v).ravel() for v in f_ad(x, p))
    f2, g2 = (np.array(v).ravel() for v in comp._grad_f(x, p))
    g3 = np.array(ca.Function("g", [comp._x, comp._p], [ca.gradient(comp.f, comp._x)])(x, p)).ravel()
    H1 = np.array(plain._hess_gn(x, p, 0.7, lam_g))
    H2 = np.array(comp._hess_gn(x, p, 0.7, lam_g))
    assert np.max(np.abs(H1)) > 0 and np.max(np.abs(g1)) > 0
    # the same sums in another order: round-off of the largest terms
    assert f2 == pytest.approx(f1, rel=1e-13)
    assert np.max(np.abs(g2 - g1)) <= 1e-11 * np.max(np.abs(g1))
    assert np.max(np.abs(g3 - g1)) <= 1e-11 * np.max(np.abs(g1))  # AD through the compiled route's custom Jacobian
    assert np.max(np.abs(H2 - H1)) <= 1e-12 * np.max(np.abs(H1))
    f_plain = comp._plain[0]
    g4 = np.array(ca.Function("g", [comp._x, comp._p], [ca.gradient(f_plain, comp._x)])(x, p)).ravel()
    assert np.max(np.abs(g4 - g1)) <= 1e-13 * np.max(np.abs(g1))


def test_ocp_pieces_compile_in_the_background_after_the_solve(model, monkeypatch):
    """compiled="auto" with the pieces not in the disk cache: evaluated in the virtual machine, their
    compile deferred until the solve has returned; once they are cached the transcription is upgradable
    (a held solver rebuilds on it)."""
    from invctl.inversion import collocation, compiled
    from invctl.inversion.boundary import Selection
    from invctl.inversion.cache import servo_model
    from invctl.inversion.schemes import get_scheme

    cached, started = set(), []
    monkeypatch.setattr(compiled, "is_cached", lambda f, *a, **k: f.name() in cached)
    monkeypatch.setattr(compiled, "compile_in_background", lambda fns, *a, **k: started.append([f.name() for f in fns]))
    sv = servo_model(model)
    nx = sv.layout.nx
    sel = Selection(tuple(i for i in range(nx) if i != 8), (9,), tuple(str(i) for i in range(nx)))
    tr = ocp.OCPTranscription(sv, sel, get_scheme("hermite-simpson"), 4, relaxed=True, bounded=(13,), compiled="auto")
    assert not tr.compiled and started == [] and tr in collocation.DEFERRED
    collocation.start_deferred_compiles()
    names = started[0]
    assert {"ocp_point", "ocp_point_jac", "ocp_gn_block"} <= set(names) and len(names) == 5
    assert not tr.upgradable()
    cached.update(names)
    assert tr.upgradable()


def test_exact_hessian_pieces_compile_in_the_background_once_asked_for(model, monkeypatch):
    """hessian="exact" (minimum time's default) on compiled="auto": the structured Hessian's pieces missing from
    the disk cache run in the virtual machine and compile in the background after that solve; once cached the
    transcription is upgradable, and the Hessian assembled from the compiled pieces (numeric functions without
    derivatives here) equals the virtual machine's."""
    from invctl.inversion import collocation, compiled
    from invctl.inversion.boundary import Selection
    from invctl.inversion.cache import servo_model
    from invctl.inversion.schemes import get_scheme

    cached, started, keep = set(), [], []
    monkeypatch.setattr(compiled, "is_cached", lambda f, *a, **k: f.name() in cached)
    monkeypatch.setattr(compiled, "compile_in_background", lambda fns, *a, **k: started.append([f.name() for f in fns]))
    monkeypatch.setattr(ocp, "_compile", lambda f: keep.append(_NoDerivatives(f)) or keep[-1])
    sv = servo_model(model)
    nx = sv.layout.nx
    sel = Selection(tuple(i for i in range(nx) if i != 8), (9,), tuple(str(i) for i in range(nx)))

    def build():
        return ocp.OCPTranscription(sv, sel, get_scheme("hermite-simpson"), 4, relaxed=True, free_time=True,
                                    bounded=(13,), compiled="auto")

    build()
    collocation.start_deferred_compiles()
    cached.update(started.pop())  # the first solve's pieces are on disk now
    tr = build()
    assert tr.compiled and not tr.upgradable() and tr not in collocation.DEFERRED
    h_vm = ocp.structured_hessian(tr)
    assert tr in collocation.DEFERRED and started == []  # not while the solve that asked for it runs
    collocation.start_deferred_compiles()
    names = started.pop()
    assert len(names) == 3 and "ocp_point_hess" in names
    assert not tr.upgradable()
    cached.update(names)
    assert tr.upgradable()
    n_numeric = len(keep)
    h_c = ocp.structured_hessian(tr)
    assert len(keep) == n_numeric + 3  # the three pieces loaded as compiled functions
    rng = np.random.default_rng(2)
    x, p, lam_g = rng.standard_normal(tr.nX), rng.random(tr.np), rng.standard_normal(tr.ng)
    x[tr.i_tau], p[tr._p_slices["tau_ref"]] = 1.2, 1.0
    H1, H2 = np.array(h_vm(x, p, 0.7, lam_g)), np.array(h_c(x, p, 0.7, lam_g))
    assert np.max(np.abs(H1)) > 0
    assert np.max(np.abs(H2 - H1)) <= 1e-13 * np.max(np.abs(H1))


@pytest.mark.parametrize("scheme", ["hermite-simpson", "legendre3"])
def test_extrema_of_all_intervals_at_once_equal_np_roots_per_interval(model, ref, q0, scheme):
    """:meth:`Inverse.extrema` (the bounds checks between the nodes) finds every interval's roots at once;
    the same roots one interval at a time by ``np.roots``."""
    inv = invert(model, ref, q_guess=q0, N=20, scheme=scheme, compiled=False)
    h = np.diff(inv.t_mesh)
    for row in range(inv.X_mesh.shape[0]):
        for derivative in (False, True):
            C = inv._scheme.coefficients(inv.X_mesh, inv.dX_mesh, inv.X_col, row, h)
            want = []
            for k in range(inv.N):
                p = np.polyder(np.poly1d(C[:, k]), 2 if derivative else 1)
                want += [inv.t_mesh[k] + z.real * h[k] for z in np.atleast_1d(p.roots)
                         if abs(z.imag) < 1e-9 and 0 < z.real < 1]
            got = inv.extrema(row, derivative)
            assert got.size == len(want)
            assert np.allclose(np.sort(got), np.sort(want), rtol=0, atol=1e-12)  # round-off of the eigenvalues

