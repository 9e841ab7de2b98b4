"""Animations of saved runs: ``invctl animate RUN.npz``.

The run file records the scene (name or path) and its parameters; the scene's ``drawing(model)``
says which points and links to draw (:class:`invctl.plot.animate.Drawing`).  Loading a scene file
runs its code, so a scene file named only inside a run file is never loaded: the user names it
(``--scene PATH``); a shipped scene recorded by its name is loaded as usual.
"""
from __future__ import annotations

import math
from pathlib import Path

from ..errors import AnimationError, OptionError, ResultFileError, SceneError
from ..io import check_output_path, read_meta
from ..results import load
from ..scenes import CommandResult, _is_path, load_scene


def _load(path):
    meta = read_meta(path)
    if meta["kind"] not in ("ClosedLoopResult", "Inverse", "ContactTrajectory"):
        raise ResultFileError(f"{path}: a {meta['kind']} has no mechanism to draw (animate closed-loop, contact or "
                              "inverse runs)")
    return load(path), meta


def _positive(name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise OptionError(f"--{name} {value!r}: expected a number") from None
    if not (math.isfinite(v) and v > 0):
        raise OptionError(f"--{name} {value!r}: must be a positive finite number (default: fps 25, speed 1)")
    return v


def _scene_of_run(run_path, recorded, scene):
    """The scene to draw with: ``scene`` (named by the user), else the recorded shipped scene name."""
    if scene is not None:
        return load_scene(scene)
    if not recorded:
        raise ResultFileError(f"{run_path}: the run does not record its scene; pass --scene NAME_OR_PATH "
                              "(or rerun it with this invctl)")
    if not isinstance(recorded, str):
        raise ResultFileError(f"{run_path}: the recorded scene {recorded!r} is not a name or path")
    if _is_path(recorded):
        raise SceneError(f"{run_path}: the run was computed with the scene file {recorded!r}; a scene file is code, "
                         "and invctl does not run one named only inside a result file: if you trust that file, "
                         f"pass --scene {recorded}")
    return load_scene(recorded)


def animate_run(run_path, *, out=None, fps=25, speed=1.0, force=False, scene=None) -> CommandResult:
    """``invctl animate RUN.npz [--out FILE.gif] [--scene NAME_OR_PATH]``."""
    fps, speed = _positive("fps", fps), _positive("speed", speed)
    out = Path(out) if out else Path(run_path).with_suffix(".gif")
    if out.suffix.lower() not in (".gif", ".mp4"):
        raise AnimationError(f"--out {out}: cannot write a {out.suffix or 'suffix-less'} animation; use a .gif "
                             "(works everywhere) or .mp4 (needs ffmpeg) file name")
    result, meta = _load(run_path)
    info = meta.get("info", {})
    scene = _scene_of_run(run_path, info.get("scene"), scene)
    out = check_output_path(out, force=force)
    from ..plot.animate import animate_result

    written = animate_result(result, out, scene=scene, params=info.get("params", {}), fps=fps, speed=speed)
    return CommandResult(f"animation written to {written}", {"out": str(written), "scene": scene.name})
