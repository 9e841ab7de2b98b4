"""Every object the inversion derives lives on the object it is derived from: no module of ``invctl`` keeps a
model alive after one-shot inversions, the same model (or a ``with_params`` copy) builds nothing twice, and no
module-level memo is left in the inversion (AST check, with the justified exceptions named)."""
from __future__ import annotations

import ast
import gc
import weakref
from pathlib import Path

import numpy as np

import invctl_scenes.manipulator as scene
from invctl.analysis import equilibrium
from invctl.inversion import InversionSolver, cache, collocation, forward_check, invert, servo
from invctl.inversion.schemes import get_scheme
from invctl.inversion.sensitivity import ParametricInverse

KW = dict(N=20, backend="newton", compiled=False, residual_tol=1e-2)  # a coarse mesh: quick


def _counting(monkeypatch):
    built: list = []
    for cls in (servo.ServoModel, collocation.Transcription, equilibrium.EquilibriumSolver):
        real = cls.__init__
        monkeypatch.setattr(cls, "__init__", lambda self, *a, _r=real, _n=cls.__name__, **k:
                            built.append(_n) or _r(self, *a, **k))
    return built


def test_one_shot_inversions_leave_no_reference_to_their_models():
    """Two models inverted one-shot, forward-checked and re-solved with other parameters: once the caller drops
    them, nothing in ``invctl`` holds them (the old module-level caches kept up to 16 of each)."""
    refs = []
    for m3 in (3.4, 3.0):
        model = scene.build(m3=m3)
        ref = scene.reference(model)
        inv = invert(model, ref, q_guess=scene.initial_configuration(model), **KW)
        assert forward_check(model, inv, ref)["error"] < 1e-2  # builds the forward integrator (kept by the model)
        ParametricInverse.from_inverse(model, ref, inv).resolve(model.with_params(m3=1.01 * m3), residual_tol=1e-2)
        refs.append(weakref.ref(model))
        del model, ref, inv
    gc.collect()
    assert [r() for r in refs] == [None, None]


def test_the_same_model_builds_nothing_twice_a_rebuilt_one_its_symbolic_pieces(monkeypatch):
    model = scene.build()
    ref = scene.reference(model)
    q0 = scene.initial_configuration(model)
    built = _counting(monkeypatch)
    first = invert(model, ref, q_guess=q0, **KW)
    assert sorted(built) == ["EquilibriumSolver", "ServoModel", "Transcription"]
    built.clear()
    invert(model, ref, q_guess=q0, **KW)
    sel = {k: first.diagnostics["plan"][k] for k in ("start", "end")}  # the plan may pick another one for m3 = 3
    invert(model.with_params(m3=3.0), ref, q_guess=q0, **sel, **KW)  # a copy shares the symbols, what they derive
    assert built == []
    other = scene.build()  # the same structure rebuilt: its own servo model, transcription, equilibrium solver
    again = invert(other, ref, q_guess=q0, **KW)
    assert sorted(built) == ["EquilibriumSolver", "ServoModel", "Transcription"]
    assert np.max(np.abs(again.X_mesh - first.X_mesh)) <= 1e-12 * np.max(np.abs(first.X_mesh))
    # ... whose compiled pieces are found on disk under the same name (the key is the structure, not the object)
    hs = get_scheme("hermite-simpson")
    assert cache.compiled_key(cache.servo_model(other), hs) == cache.compiled_key(cache.servo_model(model), hs)


def test_a_held_solver_keeps_its_pieces_for_a_rebuilt_model_of_its_structure(monkeypatch):
    """``solve(model=...)`` with the model rebuilt by the scene (other parameter values, the same structure) reuses
    the held servo model and transcription, and equals a fresh solve of that model."""
    model = scene.build()
    ref = scene.reference(model)
    hand = {k: scene.INVERSION[k] for k in ("T0", "Tf", "start", "end")}
    solver = InversionSolver(model, ref, q_guess=scene.initial_configuration(model), **hand, **KW)
    solver.solve()
    tr = solver.transcription
    built = _counting(monkeypatch)
    other = scene.build(m3=3.0)
    inv = solver.solve(model=other)
    assert built == ["EquilibriumSolver"]  # the rebuilt model's own (cheap); no servo model, no transcription
    assert solver.transcription is tr and solver.info["rebuilt"] is None
    fresh = invert(scene.build(m3=3.0), ref, q_guess=scene.initial_configuration(model), **hand, **KW)
    assert np.max(np.abs(inv.X_mesh - fresh.X_mesh)) <= 1e-10 * np.max(np.abs(fresh.X_mesh))


#: module-level mutable state allowed in the inversion, and why
ALLOWED = {
    ("compiled.py", "_COMPILERS"): "the path of the C compiler named by $CC: the process's environment",
    ("compiled.py", "_WORKERS"): "pids of the compile workers this process forked, to reap: process state",
    ("collocation.py", "DEFERRED"): "transcriptions waiting for the end of the running solve to start their "
                                    "background compile; emptied after every solve (a queue, not a memo)",
}
_STORES = {"dict", "OrderedDict", "list", "set", "WeakKeyDictionary", "WeakValueDictionary", "defaultdict"}


def _module_stores(path: Path):
    """Module-level names bound to an empty container or a container constructor, module-level functions
    decorated with a cache, and names rebound by ``global`` (other than the one-time source hash of ``cache.py``)."""
    tree = ast.parse(path.read_text())
    for node in tree.body:
        value = getattr(node, "value", None)
        targets = node.targets if isinstance(node, ast.Assign) else [getattr(node, "target", None)]
        empty = isinstance(value, (ast.Dict, ast.List, ast.Set)) and not (
            getattr(value, "keys", None) or getattr(value, "elts", None))
        call = isinstance(value, ast.Call) and getattr(value.func, "id", getattr(value.func, "attr", "")) in _STORES
        if isinstance(node, (ast.Assign, ast.AnnAssign)) and (empty or call):
            yield from (t.id for t in targets if isinstance(t, ast.Name))
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and any(
                ast.unparse(d).split("(")[0].split(".")[-1] in ("lru_cache", "cache") for d in node.decorator_list):
            yield f"@cache on {node.name}"  # a module-level function's memo (cached_property is per instance)
    for node in ast.walk(tree):
        if isinstance(node, ast.Global):
            yield from (f"global {n}" for n in node.names if (path.name, n) != ("cache.py", "_SOURCE_KEY"))


def test_no_module_level_memo_in_the_inversion_and_the_robustness_studies():
    from invctl.studies import robustness

    root = Path(cache.__file__).parent
    found = {(p.name, name) for p in [*root.glob("*.py"), Path(robustness.__file__)] for name in _module_stores(p)}
    assert found == set(ALLOWED), found ^ set(ALLOWED)


def test_the_check_finds_the_old_caches(tmp_path):
    old = tmp_path / "old.py"
    old.write_text("from collections import OrderedDict\nfrom functools import lru_cache\n_TRANS_CACHE: dict = {}\n"
                   "_MAPS = OrderedDict()\n\n@lru_cache(maxsize=16)\ndef f(model):\n    return model\n")
    assert set(_module_stores(old)) == {"_TRANS_CACHE", "_MAPS", "@cache on f"}


def test_a_chunked_sweep_returns_every_point_in_place_with_its_error():
    """A sweep on an executor runs one chunk of points per worker (one build of what they share per chunk); the
    result is the serial sweep's, point by point, failures included (kt = 1e3: Theorem 1 does not apply)."""
    import pickle
    from concurrent.futures import ThreadPoolExecutor

    from invctl.studies.robustness import Study, lambda_map_point, switched_lambda_map

    grids = dict(kt=[1e3, 5e4], bt=[10.0, 171.0])
    serial = switched_lambda_map("compliant_wrist", **grids, executor="serial", progress=False)
    with ThreadPoolExecutor(2) as ex:
        chunked = switched_lambda_map("compliant_wrist", **grids, executor=ex, progress=False)
    assert chunked.points == serial.points and chunked.shape == serial.shape == (2, 2)
    assert chunked.errors == serial.errors and sum(e is not None for e in chunked.errors) == 2
    np.testing.assert_equal(chunked.values, serial.values)  # NaN where a visible eigenvector exists
    study = Study(lambda_map_point, "compliant_wrist", {})
    study(kt=5e4, bt=10.0)
    assert study._made and pickle.loads(pickle.dumps(study))._made == {}  # a worker builds its own
