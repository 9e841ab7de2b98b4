"""Ready-made robustness and parameter sweeps of any scene on :func:`invctl.studies.sweep.sweep`.

Each sweep runs on any ``concurrent.futures.Executor`` (a local process pool by default) or a
``dask.distributed.Client`` unchanged, reports failed points with their exception instead of
dropping them, and returns a :class:`~invctl.studies.sweep.SweepResult` whose ``plot`` draws a
heat map.  Scenes are passed by name or path (workers load them themselves).

* :func:`plant_mismatch` -- a tracking scene's closed loop over a grid of plant mismatches
  (factors on the plant's parameters): cumulative errors, the largest funnel ratio, input peaks;
  a run that leaves its funnel is a failed point (``FunnelViolation``).
* :func:`switched_lambda_map` -- the return-map factor Lambda of a switched scene (002) over two of
  its parameters by the closed form (14)-(16) *and* the numerical return map, with the GUAS verdict
  and visible eigenvectors.
* :func:`contact_grid` -- a contact scene's run over a grid of parameters/settings: impacts,
  penetration, the largest Lyapunov increase at impacts (must not be positive, 000 Prop. 2), the
  final regulation error.

What the points of a sweep share (the scene, a tracking scene's inverse and funnel design) is built once by
each process that runs points and kept by the sweep's :class:`Study` (no module state): a process pool gets
one chunk of points per worker, so a point costs one simulation, not one build.
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from ..errors import ParameterError, RunInterrupted
from ..plot import finish
from ..scenes import load_scene, scene_reference
from .sweep import SweepResult, _call, executor_slots, grid, sweep
from .workflow import scene_of_kind


class Study:
    """One sweep's point function ``point(scene=..., study=self, **fixed, **values)`` with what its points share,
    built on first use and kept here (:meth:`kept`).  Pickled without it: a worker builds its own, once per
    chunk of points (:func:`_run_chunk`)."""

    def __init__(self, point, scene_ref: str, fixed: dict):
        self.point, self.scene_ref, self.fixed = point, scene_ref, dict(fixed)
        self._made: dict[Any, Any] = {}

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_made": {}}

    def kept(self, key, build):
        """``build()``, once per key."""
        if key not in self._made:
            self._made[key] = build()
        return self._made[key]

    def scene(self):
        return self.kept(("scene",), lambda: load_scene(self.scene_ref))

    def __call__(self, **values) -> dict:
        return self.point(scene=self.scene_ref, study=self, **self.fixed, **values)


def _study(study: Study | None, scene: str) -> Study:
    """``study``, or one for a point called on its own."""
    return Study(None, scene, {}) if study is None else study


def _run_chunk(*, study: Study, points: list) -> dict:
    """The points of one chunk (in a worker), each failed point with its error."""
    out = [_call(study, p) for p in points]
    return {"values": [v for v, _ in out], "errors": [e for _, e in out]}


def _run_sweep(point, sc, grids: dict, run: tuple, label: str, meta: dict, **fixed) -> SweepResult:
    """``point(scene=..., **fixed, **values)`` over the grid of ``grids`` (``run``: executor, max_workers,
    progress), workers loading scene ``sc`` by its reference.  In this process all points run on one
    :class:`Study`; on an executor each worker gets one chunk of points (interleaved) and one study."""
    study = Study(point, scene_reference(sc), fixed)
    executor, max_workers, progress = run
    pts, shape = grid(**{k: list(v) for k, v in grids.items()})
    slots = executor_slots(executor, max_workers)
    label = f"{sc.name} {label}"
    if executor == "serial" or (executor is None and slots <= 1) or len(pts) <= 1:
        res = sweep(study, (pts, shape), executor="serial", progress=progress, label=label)
    else:
        k = min(len(pts), slots)
        chunks = [list(range(i, len(pts), k)) for i in range(k)]
        jobs = [{"study": study, "points": [pts[i] for i in c]} for c in chunks]
        try:
            res = _points_of(sweep(_run_chunk, jobs, executor=executor, max_workers=max_workers, progress=progress,
                                   label=f"{label} ({k} chunks of points)"), chunks, pts, shape)
        except RunInterrupted as exc:
            raise RunInterrupted(str(exc), partial=_points_of(exc.partial, chunks, pts, shape)) from None
    res.meta.update({"scene": sc.name, **meta})
    return res


def _points_of(res: SweepResult, chunks: list, pts: list, shape: tuple) -> SweepResult:
    """The sweep of chunks ``res`` as the sweep of the points (a chunk that did not run: its error for each point)."""
    values: list = [None] * len(pts)
    errors: list = [None] * len(pts)
    for c, v, e in zip(chunks, res.values, res.errors):
        for j, i in enumerate(c):
            values[i], errors[i] = (v["values"][j], v["errors"][j]) if v is not None else (None, e)
    return SweepResult(pts, values, errors, shape, res.wall_s, dict(res.meta))


def _known(names, known, what: str) -> None:
    bad = sorted(set(names) - set(known))
    if bad or not names:
        raise ParameterError(f"{what}; unknown {bad}; known: {sorted(known)}")


def _two(grids: dict, what: str):
    if len(grids) != 2:
        raise ParameterError(f"{what} sweeps exactly two parameters, got {sorted(grids)}")
    return grids


# ------------------------------------------------------------------- funnel
def _tracking_setup(study: Study, controller: str, t_end, params: tuple):
    from .tracking import NEEDS_INVERSE, setup_tracking

    return setup_tracking(study.scene(), dict(params), invert=controller in NEEDS_INVERSE, t_end=t_end,
                          plant_factors={})


def mismatch_point(*, scene: str, controller: str = "C1", t_end=None, params=(), study: Study | None = None,
                   **factors) -> dict:
    """One closed-loop run of ``scene`` with the plant's parameters scaled by ``factors`` (``study``: where the
    inverse and funnel design the points share are kept)."""
    study = _study(study, scene)
    setup = study.kept(("tracking", controller, t_end, tuple(params)),
                       lambda: _tracking_setup(study, controller, t_end, tuple(params)))
    plant = setup.model.scaled(**factors)
    from .tracking import equilibrium_configuration

    q0 = equilibrium_configuration(setup.scene, plant, setup.reference(0.0))
    res = setup.loop(controller).run(q0, theta=plant.theta_values, controller_label=controller)
    out = {f"cumulative_{k.replace(' ', '_')}_error": v for k, v in res.cumulative_errors.items()}
    out.update({"max_constraint_drift": res.max_constraint_drift, "wall_s": res.wall_s})
    if res.ratios.size:
        out["max_funnel_ratio"] = res.max_funnel_ratio
    out.update({f"input_peak_{i + 1}": float(p) for i, p in enumerate(res.input_peaks)})
    return out


def plant_mismatch(scene: str, *, controller: str = "C1", t_end=None, params=None, executor=None,
                   max_workers: int | None = None, progress: bool = True, **factors) -> SweepResult:
    """A tracking scene's closed loop over plant mismatches: plant = reference model (``params``) with
    its parameters multiplied by the grid's factors, e.g. ``plant_mismatch("manipulator", m3=[1, 1.2],
    m2=[0.8, 1.2])`` (derived parameters follow)."""
    sc = scene_of_kind(scene, "tracking", "plant_mismatch")
    sc.require("simulate")
    from .tracking import check_controller

    controller = check_controller(controller)
    model = sc.model(params)
    _known(factors, model.values, "plant_mismatch: give factors of the plant's parameters, e.g. m3=[1.0, 1.2]")
    return _run_sweep(mismatch_point, sc, factors, (executor, max_workers, progress), f"plant mismatch {controller}",
                      {"study": "plant_mismatch", "controller": controller,
                       "labels": {k: f"{k} factor (plant / model)" for k in factors}},
                      controller=controller, t_end=t_end, params=tuple(sorted(dict(params or {}).items())))


# ------------------------------------------------------------ switched (002)
def lambda_map_point(*, scene: str, params=(), study: Study | None = None, **values) -> dict:
    """Lambda of a switched scene at parameter ``values`` by the closed form and the numerical return map."""
    from .switched import lambda_point

    study = _study(study, scene)
    p = study.kept(("switched", tuple(params)), lambda: dict(study.scene().model(dict(params)).params))
    p = {**p, **{k: float(v) for k, v in values.items()}}
    closed = lambda_point(p, method="closed")
    out = {"visible": float(closed.visible), "guas": float(closed.guas)}
    if closed.visible:
        out.update({"Lambda": np.nan, "Lambda_numerical": np.nan, "log10_Lambda": np.nan})
    else:
        num = lambda_point(p, method="numerical")
        out.update({"Lambda": closed.Lambda, "Lambda_numerical": num.Lambda,
                    "log10_Lambda": float(np.log10(closed.Lambda)),
                    "closed_vs_numerical": abs(closed.Lambda - num.Lambda) / max(abs(num.Lambda), 1e-300)})
    return out


def switched_lambda_map(scene: str, *, params=None, executor=None, max_workers: int | None = None,
                        progress: bool = True, **grids) -> SweepResult:
    """Lambda of a switched scene over a grid of two of its parameters (others: the scene's, updated by
    ``params``), e.g. ``switched_lambda_map("compliant_wrist", kt=[...], bt=[...])``; ``Lambda`` is NaN
    where a visible eigenvector exists (no rotation)."""
    sc = scene_of_kind(scene, "switched", "switched_lambda_map")
    _known(_two(grids, "switched_lambda_map"), sc.params, f"{sc.name}: give grids of its parameters")
    return _run_sweep(lambda_map_point, sc, grids, (executor, max_workers, progress), "Lambda map",
                      {"study": "switched_lambda_map", "labels": {k: k for k in grids}},
                      params=tuple(sorted(dict(params or {}).items())))


# ----------------------------------------------------------------- contact
def contact_point(*, scene: str, controller=None, t_end=None, base=(), study: Study | None = None, **values) -> dict:
    """One run of a contact scene with parameters/settings ``values`` (on top of ``base``)."""
    from .contact import contact_setup, law_report, run_contact

    sc = _study(study, scene).scene()
    params, settings = sc.split({**dict(base), **values})
    run = run_contact(contact_setup(sc, params, settings, controller=controller), t_end=t_end, progress=False)
    from ..stability.lyapunov import lyapunov_report

    tr = run.result
    jumps = lyapunov_report(tr).impact_jumps
    _, law = law_report(run)
    out = {"n_impacts": float(tr.impact_times.size), "max_gap_violation": tr.max_gap_violation,
           "max_V_jump_at_impacts": float(jumps.max()) if jumps.size else 0.0,
           "steps_per_s": float(tr.stats["steps_per_s"])}
    if "regulation_error_final" in law:
        out["regulation_error_final"] = float(np.max(np.abs(law["regulation_error_final"])))
    if "tracking_error_last_half" in law:
        out["tracking_error_last_half"] = law["tracking_error_last_half"]
    return out


def contact_grid(scene: str, *, controller=None, t_end=None, base=None, executor=None,
                 max_workers: int | None = None, progress: bool = True, **grids) -> SweepResult:
    """A contact scene's run over a grid of its parameters and settings, e.g.
    ``contact_grid("prismatic_clearance", e=[0, 0.5, 1], L=[0.1 + 1e-6, 0.11])``."""
    sc = scene_of_kind(scene, "contact", "contact_grid")
    _known(grids, {**sc.params, **sc.settings}, f"{sc.name}: give grids of parameters or settings")
    return _run_sweep(contact_point, sc, grids, (executor, max_workers, progress), "grid",
                      {"study": "contact_grid", "controller": controller, "t_end": t_end, "labels": {k: k for k in grids}},
                      controller=controller, t_end=t_end, base=tuple(sorted(dict(base or {}).items())))


# ------------------------------------------------------------------- figure
def plot_sweep(res: SweepResult, keys: Sequence[str], path=None, *, log: Sequence[str] = (), contour=None):
    """Heat maps of several outputs side by side (one figure); ``log`` lists keys drawn as
    log10, ``contour`` maps a key to a level drawn as a black line (e.g. ``{"Lambda": 1}``)."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(keys), figsize=(5.2 * len(keys), 4.2), squeeze=False)
    for ax, key in zip(axes[0], keys):
        res.plot(key, ax=ax, log=key in log, contour=(contour or {}).get(key))
    return finish(fig, path)
