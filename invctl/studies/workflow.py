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
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Protocol

from ..errors import OptionError

if TYPE_CHECKING:
    from ..scenes import CommandResult, Scene
    from .pipeline import Session


class Verbs(Protocol):
    """What a workflow module provides (each returns a :class:`~invctl.scenes.CommandResult` whose
    ``result`` is the typed object: an inverse, a run's trajectory, the runs of a pipeline, a design)."""

    def analyze(self, scene: Scene, params: dict, settings: dict, *, samples: int = 200) -> CommandResult: ...

    def simulate(self, scene: Scene, params: dict, settings: dict, **options: Any) -> CommandResult: ...

    #: the kind's pipeline session (:class:`~invctl.studies.pipeline.Session`), made with
    #: ``Session(scene, params, settings, **options)``; the pipeline itself is
    #: :func:`~invctl.studies.pipeline.run_pipeline`, the same for every kind
    Session: type[Session]


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
    warnings); ``run_size(command, scene, params, options)``: the size of the record a command will keep
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

    def accepts(self, option: str) -> bool:
        return all(option not in opts or kind == self.kind for kind, opts in KIND_OPTIONS.items())

    def check_options(self, scene: Scene, given: dict) -> None:
        """Kind-specific options given to a scene of another kind: an :class:`OptionError` naming them."""
        bad = [k for k, v in given.items() if v not in (None, False, [], ()) and not self.accepts(k)]
        if bad:
            owner = next(kind for kind, opts in KIND_OPTIONS.items() if bad[0] in opts)
            names = ", ".join("--" + k.replace("_", "-") for k in bad)
            raise OptionError(f"{names}: applies to {owner} scenes only; {scene.name!r} is a {self.kind} scene")


def _tracking_run_size(command, scene, params, o) -> tuple | None:
    """``(samples, runs, step, t_end, horizon option, step option)`` of the closed-loop runs a command records
    (with ``--t-end`` or ``--dt`` given), or None."""
    t_opt = o.get("t_end")
    if command not in ("simulate", "pipeline") or (t_opt is None and o.get("dt") is None):
        return None
    import inspect

    from .tracking import setup_tracking, tracking_model

    dt = float(o.get("dt") or inspect.signature(setup_tracking).parameters["dt"].default)
    if t_opt is None:  # the scene's horizon (as setup_tracking takes it)
        ref = tracking_model(scene, params)[1]
        t_opt = scene.tracking.t_end or (ref.tf + (ref.tf - ref.t0))
    runs = 1 if command == "simulate" else len(scene.tracking.controllers)
    return float(t_opt) / dt, runs, dt, float(t_opt), "--t-end ", "--dt "


def _switched_run_size(command, scene, params, o) -> tuple | None:
    """The same for a switched run (and the trade-off's reference run at 1e-5 s)."""
    p = {**scene.params, **params}
    if command not in ("simulate", "pipeline", "study") or "h_max" not in p or "t_end" not in p:
        return None
    t_opt = o.get("t_end")
    t_end = float(t_opt if t_opt is not None else p["t_end"])
    if command == "study":  # the trade-off's reference run (invctl.studies.tradeoff_specs.switched)
        return t_end / 1e-5, 1, 1e-5, t_end, "--set t_end=", None
    return t_end / float(p["h_max"]), 2, float(p["h_max"]), t_end, "--t-end ", "--set h_max="


def _check_contact(scene, result):
    from .commands import check_contact_result

    return check_contact_result(scene, result)


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
