"""Trajectory libraries: stable inverses over a grid of end points, durations and parameters.

``generate(scene, {"rf[0]": [...], "m3": [...]})`` (``invctl generate <scene> --grid NAME=START:STOP:COUNT``)
solves the scene's stable inversion at every grid point.  A grid axis is

* a **scene parameter** (``m3``): the point's model is the scene's model with that value (derived
  parameters follow, as with ``--set``);
* a **reference argument**: a keyword argument with a numeric default of the scene's reference
  function, e.g. ``reference(model, *, t0=0.0, tf=1.0, r0=(1.6, -0.6), rf=(0.9, -0.9))`` makes
  ``t0``, ``tf`` and the components ``r0[0]``, ``r0[1]``, ``rf[0]``, ``rf[1]`` grid-able.  A scene
  makes anything grid-able by adding such an argument.  ``param:NAME`` / ``ref:NAME`` resolve a name
  that is both.

Every point is solved on the transcription of one base solve (the scene's default point, with
``N``/``scheme``/``tol``): same number of intervals, the mesh carried over to the point's
transition with the base's pre- and post-actuation spans
(:meth:`~invctl.inversion.sensitivity.ParametricInverse.mesh_for`).  Points are solved in a
wavefront from the grid point nearest the base, each by Newton's method started from the solution
of an adjacent solved point (continuation; ``continuation=False``: from the quasi-static guess).
A point whose warm start fails is retried cold; one that still fails is reported with the reason,
never dropped, and never stops the others.

Work runs on any ``concurrent.futures.Executor`` (a local process pool by default; a
``dask.distributed.Client`` is used through its ``get_executor()``; ``"serial"`` in this process).
With ``out`` every solved point is written as it arrives, so an interrupted run resumes where it
stopped: the points already solved for the same settings are read back, not solved again.
"""
from __future__ import annotations

import hashlib
import heapq
import json
import math
import sys
import time
from concurrent.futures import FIRST_COMPLETED, wait
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..errors import INTERRUPT_LIKE, InvctlError, ParameterError, RunInterrupted, check_interrupt, is_interrupt
from .library_data import Axis, Library, LibraryStore, grid_counts, reference_arguments, resolve_axes
from .sweep import executor_slots, open_executor


# ------------------------------------------------------------------ the work of one point
@dataclass(frozen=True)
class _Context:
    """What a worker needs (picklable): scene, base settings and the base solution's arrays."""

    key: str
    scene: str
    params: tuple
    ref_kwargs: tuple
    axes: tuple
    base: dict
    backend: str
    tol: float | None
    compiled: bool | str = "auto"


#: per process, the library being generated: a pool's workers are separate processes that receive each point as
#: a pickled task, so the held solvers of a worker cannot travel with the tasks; the calling process drops its
#: entry when the library is done (nothing outlives the run there), a worker keeps one library at a time
_STATE: dict = {}


def _state(ctx: _Context, scene=None, model=None):
    """Per process: the scene, the base model and the base solution with its collocation system (built
    here from ``ctx``, or from the ``scene`` and ``model`` of the calling process: a process pool forked
    afterwards inherits them)."""
    st = _STATE.get(ctx.key)
    if st is None:
        from ..inversion import Inverse
        from ..inversion.sensitivity import ParametricInverse
        from ..scenes import load_scene
        from .tracking import tracking_model

        if scene is None or model is None:
            scene = load_scene(ctx.scene)
            model, _ = tracking_model(scene, dict(ctx.params))
        ref = scene.tracking.reference(model, **dict(ctx.ref_kwargs))
        b = ctx.base
        inv = Inverse(b["scheme"], b["t_mesh"], b["X_mesh"], b["dX_mesh"], b["X_col"], b["sizes"], b["t0"], b["tf"],
                      b["names"], dict(b["diagnostics"]), y_ref_fn=ref)
        base = ParametricInverse.from_inverse(model, ref, inv) if ctx.backend == "newton" else None
        _STATE.clear()  # one library at a time per process
        st = _STATE[ctx.key] = {"scene": scene, "model": model, "base": base, "inverse": inv}
    if st["base"] is not None:
        st["base"].compiled = ctx.compiled
    return st


def point_setup(scene, model, params: dict, ref_kwargs: dict, axes, values):
    """The model and reference of one grid point (``values`` in the order of ``axes``)."""
    pv, rk = {}, {k: (list(v) if isinstance(v, tuple) else v) for k, v in ref_kwargs.items()}
    for ax, v in zip(axes, values):
        if ax.kind == "param":
            pv[ax.key] = float(v)
        elif ax.index is None:
            rk[ax.key] = float(v)
        else:
            rk[ax.key][ax.index] = float(v)
    rk = {k: (tuple(v) if isinstance(v, list) else v) for k, v in rk.items()}
    if pv:
        scene.split({**params, **pv})  # the scene's checks (positive, validate)
        if set(pv) <= set(model.values):
            model = model.with_params(**pv)
        else:  # a parameter the model does not carry as a symbol: build it
            model = scene.model({**params, **pv})
    return model, scene.tracking.reference(model, **rk)


def solve_point(ctx: _Context, index: int, values: tuple, warm: dict | None, verify: bool) -> dict:
    """Solve one grid point (runs in a worker); never raises for a failed point (``status``)."""
    t_start, c_start = time.perf_counter(), time.process_time()
    rec: dict[str, Any] = {"index": index, "status": "failed", "message": "", "initial_guess": "",
                           "error": math.nan, "source": -2 if warm is None else int(warm["source"])}
    try:
        st = _state(ctx)
        model, ref = point_setup(st["scene"], st["model"], dict(ctx.params), dict(ctx.ref_kwargs), ctx.axes, values)
        inv, how = _solve(ctx, st, model, ref, warm)
        d = inv.diagnostics
        if not inv.success:  # a failed solve comes back as data: its error (the record stays "failed")
            rec.update({"message": str(d.get("error", inv.solver_status)), "initial_guess": how})
        else:
            if verify:
                from ..inversion.verify import forward_check

                rec["error"] = float(forward_check(model, inv, ref)["error"])
            rec.update({"status": "solved", "initial_guess": how, "t_mesh": inv.t_mesh, "X_mesh": inv.X_mesh,
                        "dX_mesh": inv.dX_mesh, "X_col": inv.X_col, "t0": inv.t0, "tf": inv.tf,
                        "iterations": int(d.get("iterations", -1)),
                        "factorizations": int(d.get("factorizations", -1)),
                        "residual": float(d.get("residuals", {}).get("position", math.nan))})
            if ctx.tol is not None and verify and not rec["error"] <= ctx.tol:
                rec["status"] = "inaccurate"
                rec["message"] = (f"forward-check error {rec['error']:.3g} > tol {ctx.tol:.3g}: refine the mesh "
                                  "(--N larger or a higher-order --scheme)")
    except InvctlError as exc:  # a point the Newton continuation or the setup could not solve
        rec["message"] = f"{type(exc).__name__}: {exc}"
    rec["wall_s"], rec["cpu_s"] = time.perf_counter() - t_start, time.process_time() - c_start
    return rec


def _solve(ctx, st, model, ref, warm):
    """The point's inverse: warm start from the neighbour, then cold; returns ``(Inverse, how)``."""
    from ..errors import InversionFailed

    if ctx.backend == "newton" and _same_structure(model, st["model"]):
        base = st["base"]
        first = None
        if warm is not None:
            try:
                out = base.resolve(model, ref, x0=warm["x"], guess=(warm["E0"], warm["Ef"]))
                base._lu = out._lu  # keep the factorization for the next point of this worker
                return out.inverse, "continuation"
            except (InversionFailed, ValueError) as exc:
                first = f"warm start failed ({exc}); "
        try:
            out = base.resolve(model, ref, warm=False)
        except InversionFailed as exc:
            raise InversionFailed(f"{first or ''}{exc}") from None
        base._lu = out._lu
        return out.inverse, "quasi-static" if first is None else "quasi-static after a failed warm start"
    return _solve_invert(ctx, st, model, ref, warm)


def _same_structure(a, b) -> bool:
    from ..inversion.cache import model_key

    return a is b or model_key(a) == model_key(b)


def _solve_invert(ctx, st, model, ref, warm):
    """A point through the process's held :class:`~invctl.inversion.InversionSolver` (IPOPT, or a model of
    another structure: the solver builds its transcription then); a failed solve is the point's data."""
    from ..inversion import Inverse, InversionSolver
    from ..inversion.sensitivity import mapped_mesh

    b, base = ctx.base, st["inverse"]
    src = [base.T0, base.t0, base.tf, base.Tf]
    mesh = mapped_mesh(base.t_mesh, src, [ref.t0 - (base.t0 - base.T0), ref.t0, ref.tf, ref.tf + (base.Tf - base.tf)])
    ws = None
    if warm is not None:
        wt = mapped_mesh(warm["t_mesh"], [warm["t_mesh"][0], warm["t0"], warm["tf"], warm["t_mesh"][-1]],
                         [mesh[0], ref.t0, ref.tf, mesh[-1]])
        ws = Inverse(b["scheme"], wt, warm["X_mesh"], warm["dX_mesh"], warm["X_col"], b["sizes"], ref.t0, ref.tf)
    if st.get("solver") is None:
        st["solver"] = InversionSolver(model, ref, T0=float(mesh[0]), Tf=float(mesh[-1]), start=b["start"],
                                       end=b["end"], mesh=mesh, scheme=b["scheme"],
                                       formulation=b["diagnostics"]["formulation"], omega=b["diagnostics"]["omega"],
                                       backend=ctx.backend, q_guess=base.X_mesh[:model.n, 0])
    inv = st["solver"].solve(model=model, reference=ref, mesh=mesh, warm=False, warm_start=ws, throw=False)
    return inv, "continuation" if ws is not None else "quasi-static"


_ARRAYS = ("t_mesh", "X_mesh", "dX_mesh", "X_col", "t0", "tf")


def _warm(rec: dict, source: int, before: dict | None = None) -> dict:
    """Warm-start data of a solved point: its solution vector and equilibria as guesses, or, with the
    solution ``before`` it on the same grid line, the linear extrapolation ``2 x_rec - x_before``
    (a secant predictor: an O(h^2) start instead of O(h))."""
    arr = {k: np.asarray(rec[k], float) for k in _ARRAYS}
    if before is not None:
        arr = {k: 2 * arr[k] - np.asarray(before[k], float) for k in _ARRAYS}
    x = arr["X_mesh"].ravel(order="F")
    if arr["X_col"].size:
        x = np.concatenate([x, arr["X_col"].ravel(order="F")])
    return {"x": x, "E0": arr["X_mesh"][:, 0], "Ef": arr["X_mesh"][:, -1], "source": source,
            "extrapolated": before is not None, **arr}


# ------------------------------------------------------------------ scheduling
class _Progress:
    """A one-line progress bar on stderr (a line per 10 % when stderr is not a terminal)."""

    def __init__(self, total: int, label: str, enabled: bool):
        self.total, self.label, self.enabled = total, label, enabled and total > 0
        self.t0 = time.perf_counter()
        self.tty = sys.stderr.isatty()
        self.last = -1

    def update(self, done: int, failed: int, resumed: int = 0) -> None:
        if not self.enabled:
            return
        frac = done / self.total
        step = int(frac * 10)
        if not self.tty and step == self.last and done != self.total:
            return
        self.last = step
        el = time.perf_counter() - self.t0
        new = done - resumed
        rate = new / el if el > 0 else 0.0
        eta = (self.total - done) / rate if rate > 0 else math.inf
        bar = "#" * int(frac * 30) + "." * (30 - int(frac * 30))
        left = f", {eta:.0f} s left" if math.isfinite(eta) and done < self.total else ""
        text = (f"{self.label} [{bar}] {done}/{self.total}" + (f" ({failed} failed)" if failed else "")
                + f"  {rate:.1f} points/s{left}")
        print(("\r" + text) if self.tty else text, end="" if self.tty and done < self.total else "\n",
              file=sys.stderr, flush=True)


def _neighbours(shape):
    """Grid neighbours (one step along one axis) of every flat index."""
    idx = np.arange(int(np.prod(shape))).reshape(shape)
    out: list[list[int]] = [[] for _ in range(idx.size)]
    for ax in range(len(shape)):
        a = np.moveaxis(idx, ax, 0)
        for lo, hi in zip(a[:-1].ravel(), a[1:].ravel()):
            out[lo].append(int(hi))
            out[hi].append(int(lo))
    return out


def _run(ctx, points, norm, seed_pos, done: dict, todo: list, *, continuation, verify_mask, executor, max_workers,
         on_record: Callable, shape):
    """Solve ``todo`` (flat indices) in a wavefront from the base; ``done`` holds solved records."""
    ex, owned, slots = open_executor(executor, max_workers)
    nbrs = _neighbours(shape)
    pending = set(todo)
    ready: list = []
    dist = np.linalg.norm(norm - seed_pos, axis=1)

    def push_neighbours(i):
        for j in nbrs[i]:
            if j in pending:
                heapq.heappush(ready, (float(dist[j]), j, i))

    for i in done:
        push_neighbours(i)
    solved_pos = {i: norm[i] for i in done}

    order = iter(sorted(todo))

    def pick():
        """Next point and its warm start: an adjacent solved point, else the nearest solved one (or the base)."""
        if not continuation:
            return next(i for i in order if i in pending), None
        while ready:
            _, j, src = heapq.heappop(ready)
            if j in pending:
                s2 = done[src].get("source", -2)
                s2 = int(s2) if s2 is not None and np.isfinite(s2) else -2
                line = s2 in done and np.allclose(norm[j] - norm[src], norm[src] - norm[s2], atol=1e-9)
                return j, _warm(done[src], src, done[s2] if line else None)
        cand = sorted(pending, key=lambda j: dist[j])
        if not solved_pos:
            return cand[0], dict(ctx.base["warm"])
        keys = np.array(list(solved_pos))
        P = np.array([solved_pos[k] for k in keys])
        best = min(cand[:64], key=lambda j: float(np.min(np.linalg.norm(P - norm[j], axis=1))))
        d_src = np.linalg.norm(P - norm[best], axis=1)
        src = int(keys[int(np.argmin(d_src))])
        if dist[best] < float(d_src.min()):  # the base is nearer than any solved point
            return best, dict(ctx.base["warm"])
        return best, _warm(done[src], src)

    def record(rec):
        i = rec["index"]
        pending.discard(i)
        if rec["status"] != "failed":
            done[i] = rec
            solved_pos[i] = norm[i]
            push_neighbours(i)
        on_record(rec)

    inflight: dict = {}
    try:
        while pending or inflight:
            while pending and len(inflight) < slots:
                if continuation and not ready and inflight:
                    break  # wait: a running point will open its neighbours
                i, warm = pick()
                pending.discard(i)
                args = (ctx, i, tuple(points[i]), warm, bool(verify_mask[i]))
                if ex is None:
                    record(solve_point(*args))
                    continue
                inflight[ex.submit(solve_point, *args)] = i
            if not inflight:
                continue
            finished, _ = wait(list(inflight), return_when=FIRST_COMPLETED)
            for fut in finished:
                i = inflight.pop(fut)
                try:
                    rec = fut.result()
                except Exception as exc:  # the worker died, pickling failed, ...
                    rec = {"index": i, "status": "failed", "message": f"{type(exc).__name__}: {exc}", "wall_s": 0.0,
                           "error": math.nan, "initial_guess": "", "source": -2}
                record(rec)
    finally:
        if owned:
            ex.shutdown(wait=True, cancel_futures=True)
        elif ex is not None:
            for fut in inflight:
                fut.cancel()


# ------------------------------------------------------------------ front door
def generate(scene, grid, *, params=None, out=None, executor=None, max_workers: int | None = None,
             backend: str = "newton", N: int | None = None, scheme: str | None = None, tol: float | None = None,
             continuation: bool = True, verify: str = "corners", force: bool = False, progress: bool = True,
             callback: Callable | None = None, compiled: bool | None = None) -> Library:
    """Solve the scene's stable inversion on a grid (module doc) and return the :class:`Library`.

    Parameters
    ----------
    scene : Scene, name or path
    grid : dict name -> values, or list of ``NAME=START:STOP:COUNT`` strings (:func:`parse_grid`)
    params : dict, optional
        Scene parameter overrides for the whole library (``--set``).
    out : path, optional
        ``*.npz``: one file (points are kept in ``<out>.parts/`` until the end); otherwise a folder
        with one :class:`~invctl.inversion.Inverse` file per point and ``library.json``.  An existing
        output of the same settings is resumed; of other settings it is refused.  ``force``: discard
        what the output holds and start over.
    executor : Executor, dask.distributed.Client or "serial", optional
        Where points are solved (default: a process pool of ``max_workers``).
    backend : {"newton", "ipopt"}
        ``newton``: Newton's method on the base transcription (fast continuation);
        ``ipopt``: :func:`~invctl.inversion.invert` per point, warm-started.
    N, scheme, tol
        The base solve's mesh: ``tol`` refines it (from ``N``, default 50) until the forward-check
        error is below ``tol``; without ``tol`` the scene's declared inversion settings.
    continuation : bool
        Warm-start every point from an adjacent solved one (``False``: each from its quasi-static guess).
    verify : {"all", "corners", "none"}
        Forward-check every point, the grid's corners only, or none; with ``tol`` a point above it is
        marked ``inaccurate`` (kept, listed among the failures).
    callback : callable, optional
        ``callback(record)`` after every point (``record["index"]``, ``["status"]``, ...).
    compiled : bool, optional
        Newton backend: evaluate the collocation residual and Jacobian through C code generated and
        compiled once (cached on disk; ``info["compile_s"]``).  Default: when a C compiler is found;
        a failed compilation falls back to CasADi's virtual machine (``info["compiled"]`` says why).
    """
    from ..scenes import Scene, load_scene, scene_reference

    t_start = time.perf_counter()
    scene = scene if isinstance(scene, Scene) else load_scene(scene)
    scene.require("invert")
    if backend not in ("newton", "ipopt"):
        raise ParameterError(f"backend must be 'newton' or 'ipopt', got {backend!r}")
    if verify not in ("all", "corners", "none"):
        raise ParameterError(f"verify must be 'all', 'corners' or 'none', got {verify!r}")
    params, _ = scene.split(params)
    slots = executor_slots(executor, max_workers)
    check_library_size(scene, params, grid_counts(grid), N, scheme, slots)  # before any value is materialized
    axes = resolve_axes(scene, grid)
    shape = tuple(len(a.values) for a in axes)
    mesh = np.meshgrid(*[np.array(a.values) for a in axes], indexing="ij")
    points = np.stack([m.ravel() for m in mesh], axis=1)
    ref_kwargs = reference_arguments(scene)
    settings = {"scene": scene_reference(scene), "source": _source_hash(scene), "params": params,
                "axes": [[a.name, a.kind, list(a.values)] for a in axes], "backend": backend, "N": N,
                "scheme": scheme, "tol": tol}
    key = hashlib.sha1(json.dumps(settings, sort_keys=True, default=str).encode()).hexdigest()[:16]
    kw = dict(executor=executor, max_workers=max_workers, backend=backend, N=N, scheme=scheme, tol=tol,
              continuation=continuation, verify=verify, progress=progress, callback=callback, compiled=compiled)
    store = LibraryStore(out, key, force=force) if out is not None else None
    if store is None:
        return _generate(scene, params, axes, shape, points, ref_kwargs, key, None, {}, t_start, slots, **kw)
    store.acquire()
    try:
        return _generate(scene, params, axes, shape, points, ref_kwargs, key, store, store.existing(), t_start,
                         slots, **kw)
    finally:
        store.release()


def _generate(scene, params, axes, shape, points, ref_kwargs, key, store, done, t_start, slots, *, executor,
              max_workers, backend, N, scheme, tol, continuation, verify, progress, callback, compiled):
    from ..scenes import scene_reference
    from .tracking import invert_tracking, tracking_model

    resumed = len(done)
    # the base solve: the scene's default point
    model, ref = tracking_model(scene, params)
    opts = {"backend": backend, "scheme": scheme, "tol": tol, "N": (N or 50) if tol is not None else N}
    base = invert_tracking(scene, model, ref, **{k: v for k, v in opts.items() if v is not None})
    if store is not None:
        store.layout = {"scheme": base.scheme, "sizes": base.sizes, "names": base.names}
    cfg = dict(scene.tracking.inversion)
    plan = base.diagnostics.get("plan") or {}
    ctx_base = {"scheme": base.scheme, "t_mesh": base.t_mesh, "X_mesh": base.X_mesh, "dX_mesh": base.dX_mesh,
                "X_col": base.X_col, "sizes": base.sizes, "t0": base.t0, "tf": base.tf, "names": base.names,
                "diagnostics": {k: base.diagnostics[k] for k in ("selection", "formulation", "omega")},
                "start": cfg.get("start", plan.get("start")), "end": cfg.get("end", plan.get("end"))}
    ctx_base["warm"] = _warm(dict(ctx_base), -1)
    base_t = time.perf_counter() - t_start
    use_c, compile_s, compiled_note = _compile_choice(compiled, backend), 0.0, None
    ctx = _Context(key, scene_reference(scene), tuple(sorted(params.items())), tuple(ref_kwargs.items()),
                   tuple(axes), ctx_base, backend, tol, use_c)
    st = _state(ctx, scene, model)
    if use_c is True:  # compile now (once per machine: the cache is on disk), not inside the first point
        t_c = time.perf_counter()
        try:
            st["base"].transcription()
        except RuntimeError as exc:
            compiled_note = f"not compiled ({str(exc).splitlines()[0]}); CasADi's virtual machine instead"
            st["base"].compiled = "auto"
            ctx = replace(ctx, compiled="auto")
        compile_s = time.perf_counter() - t_c
    check_library_size(scene, params, shape, base.N, base.scheme, slots, nc=base.X_col.shape[1],
                       sizes=base.sizes)  # again with the base solve's mesh
    # where the base lies in the grid (normalized by the axis spans)
    span = np.array([max(a.values) - min(a.values) or 1.0 for a in axes])
    lo = np.array([min(a.values) for a in axes])
    norm = (points - lo) / span
    seed = np.array([_default(a, scene, ref_kwargs, model) for a in axes])
    seed_pos = (seed - lo) / span
    corners = np.zeros(len(points), bool)
    for i, idx in enumerate(np.ndindex(*shape)):
        corners[i] = all(k in (0, n - 1) for k, n in zip(idx, shape))
    verify_mask = {"all": np.ones(len(points), bool), "corners": corners, "none": np.zeros(len(points), bool)}[verify]
    records: dict[int, dict] = {}
    bar = _Progress(len(points), f"generate {scene.name}", progress)
    todo = [i for i in range(len(points)) if i not in done]
    n_failed = 0

    def on_record(rec):
        nonlocal n_failed
        records[rec["index"]] = rec
        n_failed += rec["status"] == "failed"
        if store is not None and rec["status"] != "failed":
            store.write(rec, _meta(ctx, axes, points[rec["index"]], rec))
        bar.update(resumed + len(records), n_failed, resumed)
        if callback is not None:
            callback(rec)
        check_interrupt()  # a Ctrl-C a compiled solve swallowed stops here, with this point saved

    bar.update(resumed, 0, resumed)
    t_solve = time.perf_counter()
    try:
        _run(ctx, points, norm, seed_pos, done, todo, continuation=continuation, verify_mask=verify_mask,
             executor=executor, max_workers=max_workers, on_record=on_record, shape=shape)
    except INTERRUPT_LIKE as _exc:
        if not is_interrupt(_exc):
            raise
        raise _interrupted(store, axes, points, done) from None
    finally:
        _STATE.pop(ctx.key, None)  # the held solvers of this library: not kept after it in this process
    solve_wall = time.perf_counter() - t_solve
    for i, rec in done.items():
        records.setdefault(i, rec)
    lib = Library.assemble(axes, shape, points, records, info={
        "scene": scene.name, "scene_ref": scene_reference(scene), "params": params, "key": key,
        "backend": backend, "tol": tol, "verify": verify, "continuation": continuation,
        "base": {"N": base.N, "scheme": base.scheme, "T0": base.T0, "Tf": base.Tf, "t0": base.t0, "tf": base.tf,
                 "selection": base.diagnostics.get("selection"),
                 "max_output_error": base.diagnostics.get("max_output_error")},
        "reference_arguments": {k: list(v) if isinstance(v, tuple) else v for k, v in ref_kwargs.items()},
        "resumed": resumed, "solved_now": sum(r["status"] != "failed" for r in records.values()) - resumed,
        "wall_s": time.perf_counter() - t_start, "base_s": base_t, "solve_wall_s": solve_wall,
        "compiled": compiled_note or ("yes" if ctx.compiled is True else "no"), "compile_s": compile_s,
        "points_per_s": (len(todo) / solve_wall) if solve_wall > 0 and todo else None,
        "names": base.names, "sizes": base.sizes})
    if store is not None:
        lib.info["out"] = str(store.finish(lib))
    return lib


def _interrupted(store, axes, points, done) -> RunInterrupted:
    """The Ctrl-C of a library run: what is kept (the solved points, their files) in ``diagnostics`` and
    ``saved`` (the files the command line lists as ``"partial"``)."""
    kept = []
    for i in sorted(done):
        f = store.parts / f"point_{i:05d}.npz" if store is not None else None
        if f is not None and not f.exists():  # read back from a finished .npz library, or cut off
            f = store.path if store.file and store.path.exists() else None
        kept.append({"index": int(i), "values": {a.name: float(v) for a, v in zip(axes, points[i])},
                     "file": None if f is None else str(f)})
    saved = list(dict.fromkeys(k["file"] for k in kept if k["file"]))
    if store is not None:
        n_saved = sum(k["file"] is not None for k in kept)
        msg = (f"the library stopped with {n_saved} of {len(points)} grid points solved and saved in {store.parts}; "
               "run the same command again to resume")
    else:
        msg = f"the library stopped with {len(kept)} of {len(points)} grid points solved (not saved: no output given)"
    exc = RunInterrupted(msg, diagnostics={"points": len(points), "solved": len(kept), "kept": kept,
                                           "out": None if store is None else str(store.path)})
    exc.saved = [str(s) for s in saved]
    return exc


#: Lower bounds of a point's cost, per collocation interval: the Newton continuation measured 0.13 ms
#: (manipulator, HS N = 82, compiled: 90 points/s) and 0.2 ms (cartpole, HS N = 200) per interval and
#: point; the estimate takes half of the fastest.  Memory: the point's collocation data is held twice
#: (its record and the assembled library; measured 35 KB per cartpole point at N = 200, as computed)
#: plus the bookkeeping of a point (records, neighbours, progress), about 2 KB
_POINT_SECONDS_PER_INTERVAL = 5e-5
_POINT_BYTES = 2048.0


def check_library_size(scene, params, counts, N, scheme, slots: int = 1, *, nc: int | None = None,
                       sizes: dict | None = None) -> None:
    """Time and memory of a library of ``prod(counts)`` points before it is set up (budgets of
    :func:`invctl.studies.workflow.check_budget`): the base solve's ``N`` (``invert --N``'s estimate) and
    every point at the rates above, ``slots`` points at a time.  Without ``N`` (automatic, or ``--tol``
    from 50) the smallest mesh the base solve starts from, 50 intervals, is assumed; ``generate`` checks
    again with the base solve's mesh.

    Raises
    ------
    ResourceLimitError
        Naming ``--grid`` (and the number of points that fit) or ``--N``.
    """
    from ..inversion.schemes import get_scheme
    from ..scenes import BoundScene
    from .workflow import check_budget, check_inversion

    counts = [int(c) for c in counts]
    if not counts:
        return
    if nc is None:  # before the base solve
        check_inversion(BoundScene(scene, dict(params), {}, scene.name), {"N": N, "scheme": scheme}, "generate")
    P = math.prod(counts)
    n_int = int(N or 50)
    if sizes is None:
        model = scene.model(params)
        sizes = {"n": model.n, "l": model.ell, "p": model.p, "m": model.m}
    nx = 2 * sizes["n"] + sizes["l"] + sizes["p"] + sizes["m"]
    if nc is None:
        sch = get_scheme(scheme or "hermite-simpson")
        nc = sch.n_col(n_int)
    per_b = 16.0 * ((2 * nx + 1) * (n_int + 1) + nx * nc) + _POINT_BYTES
    per_s = _POINT_SECONDS_PER_INTERVAL * n_int / max(1, slots)
    shown = " x ".join(str(c) for c in counts) + f" = {P}" if len(counts) > 1 else str(P)
    check_budget(f"{scene.name}: generate --grid ({shown} points, N = {n_int}, {slots} worker(s))", P, per_s,
                 per_b, "use --grid axes with {fit} points or fewer in all (fewer points per axis, or a library per "
                 "part of the range), a smaller --N, or more --workers / a --dask cluster",
                 diagnostics={"counts": counts, "N": n_int, "workers": slots})


def _compile_choice(compiled, backend):
    """``True`` (compile), or ``"auto"`` (only what the disk cache already holds)."""
    if compiled is False:
        return False
    if backend != "newton":  # only the Newton backend uses the base transcription's evaluators
        return "auto"
    if compiled is None:
        from ..inversion.compiled import compiler

        return True if compiler() is not None else "auto"
    return True


def _default(axis: Axis, scene, ref_kwargs, model) -> float:
    if axis.kind == "param":
        return float(model.values.get(axis.key, scene.params[axis.key]))
    v = ref_kwargs[axis.key]
    return float(v if axis.index is None else v[axis.index])


def _source_hash(scene) -> str:
    try:
        return hashlib.sha1(Path(scene.source).read_bytes()).hexdigest()[:16] if scene.source else ""
    except OSError:
        return ""


def _meta(ctx, axes, values, rec) -> dict:
    pv = {a.key: float(v) for a, v in zip(axes, values) if a.kind == "param"}
    return {"scene": ctx.scene, "params": {**dict(ctx.params), **pv},
            "library": {"key": ctx.key, "index": int(rec["index"]), "status": rec["status"],
                        "values": {a.name: float(v) for a, v in zip(axes, values)},
                        "stats": {k: rec.get(k) for k in ("iterations", "factorizations", "wall_s", "cpu_s", "residual",
                                                          "error", "initial_guess", "source", "message")}}}
