"""``invctl pipeline``, written once for every scene kind.

The scene's workflow prepares a :class:`Session` (the analysis, design and setup the runs share); the
pipeline then runs each controller, writes ``run_<name>.npz`` as soon as the run is complete, draws its
figure and (on request) its animation, and lets the session compare the runs. A Ctrl-C keeps the complete runs on disk
and the simulated prefix of the run under way (:class:`~invctl.errors.RunInterrupted`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

from ..errors import RunInterrupted, check_interrupt
from ..scenes import CommandResult

if TYPE_CHECKING:
    from ..results import Trajectory
    from ..scenes import BoundScene


@dataclass
class Step:
    """One controller's run in a pipeline: the trajectory, its report lines and its JSON data."""

    trajectory: Trajectory
    lines: list[str] = field(default_factory=list)
    data: dict = field(default_factory=dict)


class Session:
    """What a workflow prepares for a pipeline (:func:`run_pipeline` drives it). A kind's session sets
    ``controllers`` and implements :meth:`run`; the other steps do nothing unless it overrides them."""

    #: the controllers to run, in order
    controllers: Sequence[str] = ()

    def head(self, out: Path) -> tuple[list[str], dict]:
        """Report lines and data before the runs (skipped controllers, analysis, design figures)."""
        return [], {}

    def run(self, name: str) -> Step:
        """One controller's run (raises :class:`~invctl.errors.RunInterrupted` with the prefix on Ctrl-C)."""
        raise NotImplementedError

    def meta(self, name: str) -> dict:
        """What a saved run records about where it came from (scene, parameters, controller)."""
        return {}

    def figure(self, name: str, step: Step, out: Path) -> None:
        """The run's own figure in ``out`` (or nothing)."""

    def animation(self, name: str) -> dict:
        """Options of the run's animation (``fps``, ``title``)."""
        return {}

    def finish(self, runs: dict[str, Trajectory], out: Path) -> tuple[list[str], dict]:
        """The comparison of the runs: report lines, data, figures in ``out``."""
        return [], {}

    def interrupted(self, runs: dict[str, Trajectory], out: Path, note: str) -> list[str]:
        """After a Ctrl-C: write what makes the complete ``runs`` loadable as a whole; returns the files written."""
        return []


def run_pipeline(bound: BoundScene, session: Session, *, out_dir, animate: bool = False) -> CommandResult:
    """Run every controller of ``session`` and compare them, writing runs, figures and, with ``animate``, animations
    (of ``bound.model``) to ``out_dir``. Returns the report, its data and the runs by controller (each a :class:`~invctl.results.Trajectory`)."""
    t0, started = time.perf_counter(), time.time()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    lines, data = session.head(out)
    data.setdefault("runs", {})
    runs: dict[str, Any] = {}
    for name in session.controllers:
        try:
            check_interrupt()
            step = session.run(name)
        except KeyboardInterrupt as exc:  # the runs before are on disk; the prefix of this one is exc.partial
            ri = exc if isinstance(exc, RunInterrupted) else RunInterrupted("interrupted")
            ri.args = (f"{ri} (controller {name}); complete runs: {', '.join(runs) or 'none'}",)
            ri.diagnostics.update(run_file=f"run_{name}.npz", complete=[str(out / f"run_{k}.npz") for k in runs])
            if runs:
                ri.diagnostics["complete"] += session.interrupted(runs, out, str(ri)) or []
            raise ri from None
        step.trajectory.to_npz(out / f"run_{name}.npz", meta=session.meta(name))
        session.figure(name, step, out)
        if animate and bound.drawing is not None:
            from ..plot.animate import animate as draw, frames

            draw(bound.model, bound.drawing, *frames(step.trajectory, bound.model), out / f"anim_{name}.gif",
                 **{"title": f"{bound.scene.name} ({name})", **session.animation(name)})
        runs[name] = step.trajectory
        lines += step.lines
        data["runs"][name] = step.data
    more, summary = session.finish(runs, out)
    data.update(summary)
    # what this run wrote (an earlier run's files in the same folder, e.g. its animations, are not listed)
    files = sorted(p.name for p in out.iterdir() if p.is_file() and p.stat().st_mtime >= started - 1.0)
    wall = time.perf_counter() - t0
    text = "\n".join(lines + more + [f"figures and data in {out}/ ({', '.join(files)}); total {wall:.1f} s"])
    return CommandResult(text, {**data, "out_dir": str(out), "files": files, "total_wall_s": wall}, runs)
