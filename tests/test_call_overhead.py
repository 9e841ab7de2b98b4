"""Per-call overhead of the inversion: what a library point builds, the map memos (least recently used
entry evicted, not the whole memo), and the fast paths against their plain forms."""
from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from invctl.inversion import servo as servo_mod
from invctl.studies import library
from invctl.studies.library import generate


def _scalar_functions(k):
    x = ca.SX.sym("x")
    return [ca.Function(f"f{i}", [x], [x * (i + 1)]) for i in range(k)]


@pytest.mark.parametrize("memo, get", [
    ("maps", lambda m, f: m.mapped(f, 3)),
    ("buffered", lambda m, f: m.buffered_map(f, 3))], ids=["mapped", "buffered_map"])
def test_map_memos_evict_the_least_recently_used_entry(memo, get):
    maps = servo_mod.MapMemo(maps_kept=3, buffered_kept=3)
    f0, f1, f2, f3 = _scalar_functions(4)
    first = [get(maps, f) for f in (f0, f1, f2)]
    assert get(maps, f0) is first[0]  # f0 used again: f1 is now the least recently used
    get(maps, f3)  # one entry too many: f1 goes, f0 and f2 stay (the whole memo was cleared before)
    assert get(maps, f0) is first[0] and get(maps, f2) is first[2]
    assert get(maps, f1) is not first[1]
    assert len(getattr(maps, memo)) == 3


def test_buffered_map_equals_the_plain_map():
    """Dense outputs are mapped as they are (shared inputs by the map's reduced inputs); sparse ones through
    the densifying wrapper: the values of the plain map either way."""
    x, p = ca.SX.sym("x", 2), ca.SX.sym("p", 2)
    dense = ca.Function("dense", [x, p], [ca.vertcat(x[0] * p[0], x[1] + p[1]), ca.densify(ca.jacobian(x * x[0], x))])
    sparse = ca.Function("sparse", [x, p], [ca.jacobian(x * p[0], x)])
    rng = np.random.default_rng(0)
    X, P = rng.normal(size=(2, 5)), rng.normal(size=2)
    for fn in (dense, sparse):
        plain = [np.array(ca.densify(o)) for o in fn.map(5).call([X, np.tile(P[:, None], 5)])]
        got = servo_mod.MapMemo().buffered_map(fn, 5, once=(1,))(X, P)
        for a, b in zip(got, plain):
            assert np.array_equal(a, b)


def test_a_library_point_builds_only_its_reference(monkeypatch):
    """A warm-started library point builds one CasADi Function and one map: its new reference's derivatives
    and their map over the sample times (the held transcription, equilibria, checks and result reuse what the
    first points of the run built)."""
    grid = {"rf[0]": [0.88, 0.89, 0.9, 0.91, 0.92]}
    kw = dict(executor="serial", N=60, verify="none", progress=False)
    built: list = []  # per point, what it built
    init, fmap = ca.Function.__init__, ca.Function.map
    point = library.solve_point
    on = [False]

    def counting_init(self, *args, **kwargs):
        if on[0]:
            built[-1].append(("Function", str(args[0]) if args else ""))
        init(self, *args, **kwargs)

    def counting_map(self, *args, **kwargs):
        if on[0]:
            built[-1].append(("map", self.name()))
        return fmap(self, *args, **kwargs)

    def counting_point(*args, **kwargs):
        on[0] = True
        built.append([])
        try:
            return point(*args, **kwargs)
        finally:
            on[0] = False

    monkeypatch.setattr(ca.Function, "__init__", counting_init)
    monkeypatch.setattr(ca.Function, "map", counting_map)
    monkeypatch.setattr(library, "solve_point", counting_point)
    lib = generate("manipulator", grid, **kw)
    assert lib.counts()["solved"] == 5 and set(lib.stats["initial_guess"]) == {"continuation"}
    assert len(built) == len(lib.status)
    # the first points meet the sizes of the run's maps (the second one the equilibria's mode check from a
    # continuation): maps of the held functions, no new function besides the reference's
    assert [f for f in built[1] if f[0] == "Function"] == [("Function", "y_ref_d3")]
    for b in built[2:]:
        assert sorted(b) == [("Function", "y_ref_d3"), ("map", "y_ref_d3")]


def test_pieces_in_the_disk_cache_are_loaded_without_building_their_sx_functions(monkeypatch):
    """A piece the disk cache has is loaded by its name: the transcription does not build the SX block function
    (which inlines the right-hand side Jacobian) to look it up, and evaluates with the loaded piece."""
    import invctl_scenes.manipulator as scene
    from invctl.inversion import collocation, compiled
    from invctl.inversion.boundary import resolve_selection
    from invctl.inversion.cache import servo_model
    from invctl.inversion.schemes import get_scheme

    model = scene.build()
    sv = servo_model(model)
    sel = resolve_selection(sv, scene.BOUNDARY["start"], scene.BOUNDARY["end"])
    hs = get_scheme("hermite-simpson")
    plain = collocation.Transcription(sv, sel, hs, 12)  # CasADi's virtual machine: builds its block function
    on_disk = {hs.block_name: plain.block_function()}  # a stand-in for the compiled block function
    monkeypatch.setattr(compiled, "load_cached", lambda name, key, flags=("-O2",): on_disk.get(name))
    monkeypatch.setattr(compiled, "compile_in_background", lambda *a, **k: None)
    blocks = []
    real = type(hs).bvp_blocks
    monkeypatch.setattr(type(hs), "bvp_blocks", lambda self, tr: blocks.append(tr) or real(self, tr))
    tr = collocation.Transcription(sv, sel, hs, 12, compiled="auto", cache_key="test")
    assert tr.compiled_pieces == (hs.block_name,) and not tr.compiled
    rng = np.random.default_rng(0)
    x, p = rng.normal(size=tr.nX), np.abs(rng.normal(size=tr.np))
    g, J = tr.evaluators(buffered=True)[1](x, p)
    assert blocks == []  # looked up and evaluated without building it
    g0, J0 = plain.evaluators(buffered=True)[1](x, p)
    assert np.array_equal(g, g0) and abs(J - J0).max() <= 1e-14 * abs(J0).max()


def test_a_first_solve_with_the_pieces_on_disk_builds_no_sx_function_of_the_model(monkeypatch):
    """The plan linearizes and the quasi-static path is checked and solved through the pieces the disk cache has
    (as the transcription then solves with them): with all of them there, a first solve builds no SX function of
    the model (not even its symbolic right-hand side), and equals the solve in CasADi's virtual machine."""
    import invctl_scenes.manipulator as scene
    from invctl.inversion import cache, collocation, compiled, invert
    from invctl.inversion.boundary import resolve_selection
    from invctl.inversion.schemes import get_scheme

    model = scene.build()
    ref = scene.reference(model)
    kw = dict(N=20, backend="newton", q_guess=scene.initial_configuration(model))
    vm = invert(model, ref, compiled=False, **kw)
    other = servo_mod.ServoModel(model, "baumgarte", 10.0)  # stand-ins for the compiled pieces
    hs = get_scheme("hermite-simpson")
    sel = resolve_selection(other, vm.diagnostics["plan"]["start"], vm.diagnostics["plan"]["end"])
    on_disk = {"servo_rhs_jac": other.rhs_jac, "servo_residuals": other.residuals, "servo_rhs": other.rhs,
               "servo_Az": other.decoupling, "servo_constraint_jac": other.constraint_jacobian,
               hs.block_name: collocation.Transcription(other, sel, hs, 20).block_function(),
               hs.interval_name: collocation.Transcription(other, sel, hs, 20).interval_sx}
    monkeypatch.setattr(compiled, "load_cached", lambda name, key, flags=("-O2",): on_disk.get(name))
    monkeypatch.setattr(compiled, "compile_in_background", lambda *a, **k: None)
    model = scene.build()  # a fresh model object: a fresh servo model and transcription
    inv = invert(model, ref, compiled="auto", **kw)
    fresh = cache.servo_model(model)
    assert "_sym" not in fresh.__dict__  # no SX function of the model at all: every piece came from the disk
    assert set(inv.diagnostics["compiled_pieces"]) == set(on_disk)
    assert np.array_equal(inv.t_mesh, vm.t_mesh)
    assert np.max(np.abs(inv.X_mesh - vm.X_mesh)) <= 1e-10 * np.max(np.abs(vm.X_mesh))


def test_a_tracking_inversion_builds_one_equilibrium_solver(monkeypatch):
    """The scene's design configuration uses the inversion's equilibrium solver of the model's structure (at the
    model's own parameter values), not a second one."""
    import invctl_scenes.manipulator as scene
    from invctl.analysis import equilibrium
    from invctl.studies.tracking import equilibrium_configuration, invert_tracking

    model = scene.build()
    ref = scene.reference(model)
    made = []
    real = equilibrium.EquilibriumSolver.__init__
    monkeypatch.setattr(equilibrium.EquilibriumSolver, "__init__", lambda self, md: made.append(md) or real(self, md))
    invert_tracking(scene.SCENE, model, ref, N=20, backend="newton", compiled=False)
    assert len(made) == 1
    other = model.with_params(m3=0.7 * model.values["m3"], L2=1.1 * model.values["L2"])  # the cached solver's model
    y = ref(ref.t0)                                                                       # has other values
    fresh = equilibrium.EquilibriumSolver(other).solve(np.ravel(y), guess_q=scene.initial_configuration(other))[0]
    assert np.max(np.abs(equilibrium_configuration(scene.SCENE, other, y) - fresh[:other.n])) < 1e-10
