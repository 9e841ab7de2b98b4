"""Animations of saved runs: ``invctl animate RUN.npz``.

The run file records the scene (name or path) and its parameters; the scene's ``drawing(model)``
says which points and links to draw (:class:`invctl.plot.animate.Drawing`).
"""
from __future__ import annotations

from pathlib import Path

from ..errors import ResultFileError, SceneError
from ..io import check_output_path, read_meta
from ..scenes import CommandResult, load_scene

__all__ = ["animate_run"]


def _load(path):
    meta = read_meta(path)
    kind = meta["kind"]
    if kind == "ClosedLoopResult":
        from ..simulate.closed_loop import ClosedLoopResult

        return ClosedLoopResult.load(path), meta
    if kind == "Inverse":
        from ..inversion.result import Inverse

        return Inverse.load(path), meta
    if kind == "ContactTrajectory":
        from ..simulate.timestepping import ContactTrajectory

        return ContactTrajectory.load(path), meta
    raise ResultFileError(f"{path}: a {kind} has no mechanism to draw (animate closed-loop, contact or inverse runs)")


def animate_run(run_path, *, out=None, fps=25, speed=1.0, force=False) -> CommandResult:
    """``invctl animate RUN.npz [--out FILE.gif]``."""
    try:
        fps, speed = float(fps), float(speed)
    except ValueError:
        raise SceneError(f"--fps {fps!r} and --speed {speed!r} must be numbers") from None
    if not (fps > 0 and speed > 0):
        raise SceneError(f"--fps and --speed must be positive, got {fps}, {speed}")
    result, meta = _load(run_path)
    info = meta.get("info", {})
    name = info.get("scene")
    if not name:
        raise ResultFileError(f"{run_path}: the run does not record its scene; rerun it with this invctl")
    scene = load_scene(name)
    out = Path(out) if out else Path(run_path).with_suffix(".gif")
    out = check_output_path(out, force=force)
    if out.suffix.lower() not in (".gif", ".mp4"):
        raise SceneError(f"--out {out}: use .gif or .mp4")
    from ..plot.animate import animate_result

    written = animate_result(result, out, scene=scene, params=info.get("params", {}), fps=fps, speed=speed)
    return CommandResult(f"animation written to {written}", {"out": str(written), "scene": scene.name})
