"""Handlers of ``invctl simulate <scene>`` and ``invctl pipeline <scene>`` for tracking scenes (003 Sect. 6).

``simulate``: one closed-loop run (C1 feedforward + funnel, C2 funnel only, C3 feedforward only) of the
mismatched plant; ``pipeline``: invert, simulate C1/C2/C3, print the comparison, write the figures.
These are command glue on top of the study layer (imported lazily).
"""
from __future__ import annotations

import time
from pathlib import Path

from ..errors import SceneError
from ..model.params import parse_assignments
from ..scenes import CommandResult

__all__ = ["simulate_command", "pipeline_command"]

_SIM_OPTIONS = {"controller", "plant_set", "t_end", "out", "plot", "inverse", "quiet"}
_PIPE_OPTIONS = {"out_dir", "t_end", "quiet"}


def _check(options, allowed, command):
    unknown = sorted(k for k, v in options.items() if k not in allowed and v not in (None, False, [], ""))
    if unknown:
        raise SceneError(f"invctl {command} does not take option(s) {unknown} for this scene")


def _inverse_from(path):
    from ..inversion import Inverse

    p = Path(path)
    if not p.exists():
        raise SceneError(f"--inverse {path}: no such file (write one with `invctl invert <scene> --out FILE.npz`)")
    return Inverse.from_npz(p)


def simulate_command(scene_module, params: dict, controller=None, plant_set=None, t_end=None, out=None, plot=None,
                     inverse=None, quiet=False, **options) -> CommandResult:
    """Handler of ``invctl simulate <scene> --controller C1|C2|C3 [--plant-set name=value] ...``."""
    from .tracking import CONTROLLERS, run_controller, setup_tracking

    _check(options, _SIM_OPTIONS, "simulate")
    name = (controller or "C1").upper()
    if name not in CONTROLLERS:
        raise SceneError(f"--controller {controller!r}: choose one of {sorted(CONTROLLERS)} "
                         f"({', '.join(f'{k}: {v}' for k, v in CONTROLLERS.items())})")
    plant_params = parse_assignments(plant_set, option="--plant-set")
    t_end = 2.0 if t_end is None else float(t_end)
    if not t_end > 0:
        raise SceneError(f"--t-end must be positive, got {t_end}")
    t0 = time.perf_counter()
    inv = _inverse_from(inverse) if inverse else None
    setup = setup_tracking(scene_module, params, plant_params, inverse=inv, invert=name in ("C1", "C3", "C1-42"),
                           t_end=t_end, progress=not quiet)
    res = run_controller(setup, name)
    wall_total = time.perf_counter() - t0
    if out:
        res.to_csv(out) if str(out).lower().endswith(".csv") else res.save(out)
    if plot:
        from ..plot import close

        close(res.plot(plot))
    s = res.summary()
    lines = [f"invctl simulate {setup.model.name} --controller {name} ({CONTROLLERS[name]}), "
             f"plant: " + (", ".join(f"{k}={v:.6g}" for k, v in setup.plant.values.items()
                                    if v != setup.model.values[k]) or "= reference model"),
             f"  cumulative output error       int ||y - y_ref|| dt   = {s['cumulative_output_error']:.6g}",
             f"  cumulative end-effector error int ||r - r_ref|| dt   = {s['cumulative_endeffector_error']:.6g}",
             f"  final output error                                    = {s['final_output_error']:.4g}"]
    if s["max_funnel_ratio"] is not None:
        lines.append(f"  max funnel ratio phi|e| = {s['max_funnel_ratio']:.4f} (margin {s['funnel_margin']:.4f})")
    lines += [f"  input peaks |u| = {[round(x, 4) for x in s['input_peaks']]}",
              f"  max constraint drift = {s['max_constraint_drift']:.3g}",
              f"  closed loop {s['wall_s']:.3f} s wall (setup {wall_total - s['wall_s']:.2f} s)"]
    data = {**s, "setup_timings": setup.timings, "total_wall_s": wall_total,
            "plant": {k: v for k, v in setup.plant.values.items() if v != setup.model.values[k]}}
    return CommandResult("\n".join(lines), data)


def pipeline_command(scene_module, params: dict, out_dir="invctl-out", t_end=None, quiet=False,
                     **options) -> CommandResult:
    """Handler of ``invctl pipeline <scene>``: invert, simulate C1/C2/C3, compare, plot."""
    from .tracking import run_tracking_study

    _check(options, _PIPE_OPTIONS, "pipeline")
    t0 = time.perf_counter()
    study = run_tracking_study(scene_module, params, t_end=2.0 if t_end is None else float(t_end),
                               controllers=("C1", "C2", "C3", "C1-42"), progress=not quiet)
    out = Path(out_dir or "invctl-out")
    study.save(out)
    from ..plot import close

    close(study.plot(out))
    wall = time.perf_counter() - t0
    text = "\n".join([study.table(), f"figures and data in {out}/ (fig5..fig9, run_C*.npz, study.json); "
                                     f"total {wall:.1f} s"])
    return CommandResult(text, {**study.to_dict(), "out_dir": str(out), "total_wall_s": wall})
