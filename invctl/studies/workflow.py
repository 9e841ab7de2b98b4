"""The workflow of each scene kind, behind one protocol, and the registry that picks it.

A scene's kind (``scene.kind``: what it declares) selects a :class:`Workflow`: the module whose verbs
(:class:`Verbs`: ``analyze``, ``design``, ``invert``, ``simulate``, and the pipeline's ``Session``) run the kind's
computations, and what the commands must know about the kind (which options apply to it, what a
recorded sample costs, what to check after a run).  The commands (:mod:`.commands`) ask the workflow;
nothing else compares ``scene.kind`` with a kind's name.  A new scene kind is one :class:`Workflow` entry
in :data:`WORKFLOWS` and one module implementing :class:`Verbs`.
"""
from __future__ import annotations

import importlib
import math
import os
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Protocol

from ..errors import OptionError, ParameterError, ResourceLimitError

if TYPE_CHECKING:
    from ..scenes import BoundScene, CommandResult, Scene
    from .pipeline import Session


class Verbs(Protocol):
    """What a workflow module provides for the commands its kind offers (each returns a
    :class:`~invctl.scenes.CommandResult` whose ``result`` is the typed object: an inverse, a run's trajectory,
    the runs of a pipeline, a design); each takes the :class:`~invctl.scenes.BoundScene` and the verb's options
    (:meth:`Workflow.prepare`)."""

    def analyze(self, bound: BoundScene, *, samples: int = 200) -> CommandResult: ...

    def invert(self, bound: BoundScene, **options: Any) -> CommandResult: ...

    def design(self, bound: BoundScene, *, plot: Any = None) -> CommandResult: ...

    def simulate(self, bound: BoundScene, **options: Any) -> CommandResult: ...

    #: the kind's pipeline session (:class:`~invctl.studies.pipeline.Session`), made with
    #: ``Session(bound, **options)``; the pipeline itself is
    #: :func:`~invctl.studies.pipeline.run_pipeline`, the same for every kind
    Session: Callable[..., Session]


#: options that apply to one kind only (the others reject them, naming the kind they apply to)
KIND_OPTIONS = {
    "contact": ("record_every", "record"),
    "tracking": ("dt", "rtol", "atol", "max_steps", "inverse", "bound", "weight", "minimum_time"),
}


@dataclass(frozen=True)
class Workflow:
    """One scene kind's workflow: its verbs' module and the facts the commands need.

    ``doubles(n, gaps, m, ny)``: recorded doubles per output sample (memory estimates); ``sample_cost``:
    ``(s per sample, s per sample with region constraints, bytes per sample / n^2)`` of ``analyze --samples``;
    ``plant_mismatch``: whether a simulated plant may differ from the model (``--plant-set``); ``csv``: whether
    a run can be written as CSV; ``after_run``: a check of a simulate/pipeline result (may raise, may add
    warnings); ``run_size(command, bound, options)``: the size of the record a command will keep
    (``None``: small, or estimated by the run itself, as Moreau-Jean does)."""

    kind: str
    module: str
    doubles: Callable[[int, int, int, int], float]
    sample_cost: tuple | None = None
    plant_mismatch: bool = True
    csv: bool = True
    after_run: Callable[[Any, Any], Any] | None = None
    builds_model: bool = True
    run_size: Callable[..., tuple | None] | None = None
    jobs: str = ""

    def tradeoff_jobs(self, scene: Scene) -> dict:
        """The kind's speed-versus-accuracy jobs for ``scene`` (``invctl study tradeoff --job``), default first."""
        if not self.jobs:
            return {}
        return getattr(importlib.import_module("invctl.studies.tradeoff_specs"), self.jobs)(scene)

    @property
    def verbs(self) -> Verbs:
        return importlib.import_module(self.module)

    def check_options(self, scene: Scene, given: dict) -> None:
        """Kind-specific options given to a scene of another kind: an :class:`OptionError` naming them."""
        bad = [k for k, v in given.items() if v not in (None, False, [], ())
               and any(k in opts and kind != self.kind for kind, opts in KIND_OPTIONS.items())]
        if bad:
            owner = next(kind for kind, opts in KIND_OPTIONS.items() if bad[0] in opts)
            names = ", ".join("--" + k.replace("_", "-") for k in bad)
            raise OptionError(f"{names}: applies to {owner} scenes only; {scene.name!r} is a {self.kind} scene")

    def prepare(self, bound: BoundScene, command: str, o: dict) -> dict:
        """The checks of ``command``'s options ``o`` (checked by :func:`~.commands.check_options`) that depend on
        the scene, before any work: options of other kinds, ``--plant-set``, ``--inverse``, the time and memory
        of the run (:class:`~invctl.errors.ResourceLimitError` naming the option that fits).  Returns the
        keywords of the kind's verb (output paths aside)."""
        if command == "analyze":
            self._check_samples(bound, o["samples"])
            return {"samples": o["samples"]}
        if command == "invert":
            check_inversion(bound, o)
            _check_dt(bound, o)
            return {k: o[k] for k in ("N", "scheme", "tol", "backend", "dt", "quiet", "max_wall_time")}
        if command not in ("simulate", "pipeline"):
            self.check_resources(command, bound, o)
            return {}
        given = {k: o.get(k) for k in ("record_every", "record", "dt", "rtol", "atol", "max_steps", "inverse")
                 if o.get(k) is not None}
        self.check_options(bound.scene, given)
        kw: dict[str, Any] = {k: given[k] for k in ("record_every", "record", "dt") if k in given}
        integrator = {"max_num_steps" if k == "max_steps" else k: given[k] for k in ("rtol", "atol", "max_steps")
                      if k in given}
        if integrator:
            kw["integrator"] = integrator
        kw.update(t_end=o["t_end"], quiet=o["quiet"], plant_params=self._plant_params(bound, o["plant_set"]))
        if command == "simulate":
            kw["controller"] = o["controller"]
        if "inverse" in given:
            kw["inverse"] = self.verbs.load_inverse(given["inverse"], bound)  # type: ignore[attr-defined]
        self.check_resources(command, bound, o)
        return kw

    def _plant_params(self, bound: BoundScene, items) -> dict:
        """``--plant-set`` values, checked against the scene before any work (names, applicability)."""
        from ..model.params import parse_assignments

        plant = dict(items) if isinstance(items, dict) else parse_assignments(items, option="--plant-set")
        scene = bound.scene
        if plant and not self.plant_mismatch:
            raise OptionError(f"scene {scene.name!r}: the controller (3) uses no plant model, so plant and model "
                              "parameters coincide; --plant-set is not applicable (use --set)")
        unknown = sorted(set(plant) - set(scene.params))
        if unknown:
            raise ParameterError(f"--plant-set: unknown plant parameter(s) {unknown}; known: {sorted(scene.params)}")
        return plant

    def _check_samples(self, bound: BoundScene, samples: int) -> None:
        """``analyze --samples``: time and memory of the sampled checks (switched scenes use at most 720)."""
        if self.sample_cost is None or samples <= 1000:
            return
        model = bound.model
        per_s, per_s_constrained, per_b = self.sample_cost
        if model.region is not None and model.region.constraints:
            per_s = per_s_constrained
        check_budget(f"{bound.scene.name}: analyze --samples {samples}", samples, per_s, per_b * model.n * model.n,
                     "use --samples {fit} or less (the default, 200, samples the region well)")

    def check_resources(self, command: str, bound: BoundScene, o: dict) -> None:
        """The memory the runs of ``command`` record, estimated before they start.

        Raises
        ------
        ResourceLimitError
            The estimate exceeds :func:`usable_memory`; the message names the horizon (and step) that fit.
        """
        size = self.run_size(command, bound, o) if self.run_size else None
        if size is None:
            return
        samples, runs, step, t_end, t_opt, h_opt = size
        if not samples * runs > _SMALL:
            return
        n = gaps = m = ny = 0
        if self.builds_model:
            model = bound.model
            n, gaps, m, ny = model.n, len(model.gaps), model.m, model.ny
        per = 8.0 * self.doubles(n, gaps, m, ny)
        need = samples * runs * per
        limit = usable_memory()
        if need <= limit:
            return
        fit_t = limit / (runs * per) * step
        fits = f"use {t_opt}{fit_t:.3g} or less"
        if h_opt:
            fits += f", or {h_opt}{step * need / limit:.3g} or more"
        raise ResourceLimitError(
            f"{bound.scene.name}: {command} would record {samples:.3g} samples (t_end = {t_end:g} s at a step of "
            f"{step:g} s" + (f", {runs} runs" if runs > 1 else "") + f"): about {_gib(need)} of memory, but "
            f"{_gib(limit)} is usable ({int(100 * _MEMORY_SHARE)} % of the available memory or INVCTL_MAX_MEMORY); "
            f"{fits}", diagnostics={"samples": samples, "runs": runs, "bytes_needed": need, "bytes_usable": limit,
                                    "t_end_that_fits": fit_t})


def _check_contact(scene, result):
    from .contact import check_contact_result

    return check_contact_result(scene, result)


def _tracking_run_size(command, bound, o) -> tuple | None:
    """``(samples, runs, step, t_end, horizon option, step option)`` of the closed-loop runs a command records
    (with ``--t-end`` or ``--dt`` given), or None."""
    t_opt = o.get("t_end")
    if command not in ("simulate", "pipeline") or (t_opt is None and o.get("dt") is None):
        return None
    import inspect

    from .tracking import setup_tracking, tracking_model

    scene = bound.scene
    dt = float(o.get("dt") or inspect.signature(setup_tracking).parameters["dt"].default)
    if t_opt is None:  # the scene's horizon (as setup_tracking takes it)
        ref = tracking_model(scene, bound.params, model=bound.model)[1]
        t_opt = scene.tracking.t_end or (ref.tf + (ref.tf - ref.t0))
    runs = 1 if command == "simulate" else len(scene.tracking.controllers)
    return float(t_opt) / dt, runs, dt, float(t_opt), "--t-end ", "--dt "


def _switched_run_size(command, bound, o) -> tuple | None:
    """The same for a switched run (and the trade-off's reference run at 1e-5 s)."""
    p = {**bound.scene.params, **bound.params}
    if command not in ("simulate", "pipeline", "study") or "h_max" not in p or "t_end" not in p:
        return None
    t_opt = o.get("t_end")
    t_end = float(t_opt if t_opt is not None else p["t_end"])
    if command == "study":  # the trade-off's reference run (invctl.studies.tradeoff_specs.switched)
        return t_end / 1e-5, 1, 1e-5, t_end, "--set t_end=", None
    return t_end / float(p["h_max"]), 2, float(p["h_max"]), t_end, "--t-end ", "--set h_max="


#: Recorded doubles per output sample or step (measured: growth of the peak RSS between a default
#: run and one with ten times the samples, then rounded up by 10-30 %):
#: Moreau-Jean ``40 + 80 n + 40 n_gaps + 20 m`` (bouncing_ball 133 measured / 160 estimated,
#: prismatic_clearance 232 / 300, slider_crank_clearance 304 / 340, gear_backlash 412 / 500);
#: closed loop ``120 + 15 (n + m + n_y)`` per output step (cartpole 167 / 180, manipulator 220 / 255)
#: plus the funnel's reference grid at half the step; switched runs 100 (stiff_wall 44, wrist 78).
#: ``analyze --samples`` cost per sample point: measured 48 us and 0.8 KB (cartpole, n = 2, no constraints,
#: 1e5 samples), 0.46 ms and 4.4 KB (manipulator, n = 5, one constraint, 2e4 samples); ``6e-5 s``, ``6e-4 s``
#: and ``260 n^2`` bytes stay above both.  Contact scenes (vectorized reports): gear_backlash (n = 4) 1e6
#: samples in less than 0.5 s and 43 MB.
WORKFLOWS = {
    "tracking": Workflow("tracking", "invctl.studies.tracking_report",
                         lambda n, gaps, m, ny: 120 + 15 * (n + m + ny) + 2 * 4 * n, (6e-5, 6e-4, 260.0),
                         run_size=_tracking_run_size, jobs="tracking_jobs"),
    "contact": Workflow("contact", "invctl.studies.contact", lambda n, gaps, m, ny: 40 + 80 * n + 40 * gaps + 20 * m,
                        (2e-7, 2e-7, 2.5), csv=False, after_run=_check_contact, jobs="contact_jobs"),
    "switched": Workflow("switched", "invctl.studies.switched_report", lambda n, gaps, m, ny: 100.0,
                         plant_mismatch=False, builds_model=False, run_size=_switched_run_size,
                         jobs="switched_jobs"),
}


def workflow(scene: Scene) -> Workflow:
    """The workflow of ``scene``'s kind (``scene.require(command)`` has said the kind offers the command)."""
    return WORKFLOWS[scene.kind]


def scene_of_kind(ref: str, kind: str, what: str) -> Scene:
    """The scene ``ref`` (a shipped name or a path), refused with ``SceneError`` unless it is of ``kind`` (the
    study ``what`` needs one)."""
    from ..errors import SceneError
    from ..scenes import load_scene

    sc = load_scene(ref)
    if sc.kind != kind:
        raise SceneError(f"{what} needs a {kind} scene; {sc.name!r} is a {sc.kind} scene")
    return sc


# ---------------------------------------------------------------- time and memory of a run
#: below this many samples a run is never large (no model is built to estimate it)
_SMALL = 2e5
#: share of the available memory a run may plan to use
_MEMORY_SHARE = 0.75


def usable_memory() -> float:
    """Bytes a run may plan to use: 75 % of the available memory (``MemAvailable``), or
    ``INVCTL_MAX_MEMORY`` (bytes, e.g. ``4e9``) when that is smaller."""
    from ..simulate.contact_record import available_memory

    limit = _MEMORY_SHARE * available_memory()
    env = os.environ.get("INVCTL_MAX_MEMORY")
    if env:
        try:
            limit = min(limit, float(env))
        except ValueError:
            raise ParameterError(f"INVCTL_MAX_MEMORY={env!r}: expected a number of bytes (e.g. 4e9)") from None
    return limit


def _gib(b: float) -> str:
    return f"{b / 2**30:.3g} GiB"


#: seconds a run may plan to take unless ``INVCTL_MAX_TIME`` says otherwise
MAX_TIME_S = 1800.0


def usable_time() -> float:
    """Seconds a run may plan to take: ``INVCTL_MAX_TIME`` (seconds), default :data:`MAX_TIME_S`."""
    env = os.environ.get("INVCTL_MAX_TIME")
    if not env:
        return MAX_TIME_S
    try:
        t = float(env)
    except ValueError:
        t = math.nan
    if not (math.isfinite(t) and t > 0):
        raise ParameterError(f"INVCTL_MAX_TIME={env!r}: expected a positive number of seconds (e.g. 7200)")
    return t


def _duration(s: float) -> str:
    return f"{s:.3g} s" if s < 120 else f"{s / 60:.3g} min" if s < 7200 else f"{s / 3600:.3g} h"


def check_budget(what: str, count: int, seconds_each: float, bytes_each: float, fits: str, *,
                 diagnostics: dict | None = None) -> None:
    """Refuse ``count`` units of work before it starts when ``count * seconds_each`` exceeds
    :func:`usable_time` or ``count * bytes_each`` exceeds :func:`usable_memory`.

    ``what`` names the command and the option as typed; ``fits`` is the advice with ``{fit}``, the
    largest count within both budgets.

    Raises
    ------
    ResourceLimitError
    """
    limit_t, limit_m = usable_time(), usable_memory()
    secs, need = count * seconds_each, count * bytes_each
    if secs <= limit_t and need <= limit_m:
        return
    fit = int(min(limit_t / seconds_each if seconds_each > 0 else math.inf,
                  limit_m / bytes_each if bytes_each > 0 else math.inf))
    over = " and ".join(x for x, bad in ((f"{_duration(secs)} (budget {_duration(limit_t)}: INVCTL_MAX_TIME "
                                          "seconds)", secs > limit_t),
                                         (f"{_gib(need)} of memory (usable {_gib(limit_m)}: "
                                          f"{int(100 * _MEMORY_SHARE)} % of the available memory or "
                                          "INVCTL_MAX_MEMORY)", need > limit_m)) if bad)
    raise ResourceLimitError(f"{what} would take about {over}; {fits.format(fit=fit)}",
                             diagnostics={**(diagnostics or {}), "count": count, "seconds_estimated": secs,
                                          "seconds_budget": limit_t, "bytes_needed": need,
                                          "bytes_usable": limit_m, "count_that_fits": fit})


#: bytes per collocation interval of an inversion (transcription, IPOPT and MUMPS together):
#: ``600 (s nx)^1.7`` with ``s`` = 2 (Hermite-Simpson) or d + 1 (d-stage Legendre/Radau); measured peak RSS
#: growth per interval: manipulator (nx = 14) 108 KB (HS) and 490 KB (radau3), cartpole (nx = 5) 19 KB
#: (HS); the formula gives 172, 561 and 30 KB
_INVERSION_BYTES = (600.0, 1.7)
#: seconds per byte of that estimate: cartpole HS from N = 4000 to 20000 took 0.45 ms more per interval
#: (estimate 30 KB per interval)
_INVERSION_SECONDS_PER_BYTE = 1.5e-8


def check_inversion(bound: BoundScene, o: dict, command: str = "invert") -> None:
    """``--N`` of an inversion (``invert``, the base solve of ``generate``): time and memory of the
    transcription and its solver (:data:`_INVERSION_BYTES`) within the budgets (:func:`check_budget`)."""
    N = o.get("N")
    if N is None or N <= 2000:
        return
    from ..inversion.schemes import get_scheme

    sch = get_scheme(o.get("scheme") or "hermite-simpson")
    stages = sch.stages
    model = bound.model
    nx = 2 * model.n + model.ell + model.p + model.m
    per = _INVERSION_BYTES[0] * (stages * nx) ** _INVERSION_BYTES[1]
    check_budget(f"{bound.scene.name}: {command} --N {N} ({sch.name}, {nx} unknowns per node)", N,
                 per * _INVERSION_SECONDS_PER_BYTE, per,
                 "use --N {fit} or less (or --tol to refine only where needed)",
                 diagnostics={"N_that_fits": int(min(usable_memory() / per,
                                                     usable_time() / (per * _INVERSION_SECONDS_PER_BYTE)))})


def check_saved_samples(duration: float, dt: float, rows: int, *, more: str = "", partial=None) -> None:
    """A trajectory saved at step ``dt`` over ``duration`` (``rows`` signals) must fit in memory
    (``partial``: the solved inverse, kept in the error).

    Raises
    ------
    ResourceLimitError
        It would not; the message names the ``--dt`` that fits.
    """
    samples = duration / dt + 1
    per = 16.0 * rows  # the sampled signals and their interpolation temporaries
    need, limit = samples * per, usable_memory()
    if need <= limit:
        return
    fit = duration * per / limit
    raise ResourceLimitError(
        f"invert --dt {dt:g}: the saved trajectory would have {samples:.3g} samples ({duration:g} s{more}): about "
        f"{_gib(need)} of memory, but {_gib(limit)} is usable; use --dt {fit:.3g} or more, or leave out --dt (1000 "
        "samples over the horizon)", partial=partial,
        diagnostics={"samples": samples, "bytes_needed": need, "bytes_usable": limit, "dt_that_fits": fit})


def _check_dt(bound: BoundScene, o: dict) -> None:
    """``--dt`` against the memory before the solve, over the reference's transition (the horizon adds the
    pre- and post-actuation; :func:`check_saved_samples` checks it again after the solve)."""
    if o["dt"] is None:
        return
    from .tracking import tracking_model

    model, ref = tracking_model(bound.scene, bound.params, model=bound.model)
    duration = ref.tf - ref.t0
    if o["minimum_time"]:  # the transition is retimed; its shortest length is known only from --duration
        if o["duration"] is None:
            return
        duration = min(duration, float(o["duration"].partition(":")[0]))
    rows = 1 + 2 * model.n + model.ell + model.p + 2 * model.m + model.ny
    check_saved_samples(duration, o["dt"], rows, more=" of the reference's transition alone, before the pre- and "
                                                      "post-actuation")
