"""The numbers a scene declares it wants to see (:class:`invctl.scenes.Report`), computed and formatted.

A report's ``compute(ctx)`` returns ``{name: value}``; values are numbers, arrays or short texts.
Where the scene gives the paper's printed value for a name, the report shows both and the
largest absolute difference.
"""
from __future__ import annotations

import numpy as np

from ..errors import InvctlError, SceneError
from ..scenes import ReportContext


def format_value(v) -> str:
    if isinstance(v, (bool, np.bool_)):
        return str(bool(v))
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return f"{float(v):.6g}"
    if isinstance(v, str):
        return v
    a = np.asarray(v)
    if a.dtype.kind in "fiu" and a.size <= 24:
        text = np.array2string(a.astype(float), precision=6, suppress_small=True, separator=", ",
                               max_line_width=10**6)
        return " ".join(text.split())
    if a.dtype.kind in "fiu":
        return f"array{a.shape} in [{a.min():.4g}, {a.max():.4g}]"
    return str(v)


def _difference(value, printed):
    try:
        a, b = np.asarray(value, float), np.asarray(printed, float)
        if a.shape != b.shape:
            return None
        return float(np.max(np.abs(a - b))) if a.size else 0.0
    except (TypeError, ValueError):
        return None


def run_reports(scene, model, params, settings, command: str, *, result=None, controller=None):
    """Text and data of every report of ``scene`` that applies to ``command`` (and ``controller``)."""
    ctx = ReportContext(scene, model, dict(params or {}), dict(settings or {}), result, controller)
    lines, data = [], {}
    for rep in scene.reports:
        if not rep.applies(command, controller):
            continue
        try:
            values = rep.compute(ctx)
        except InvctlError:
            raise
        except Exception as exc:  # noqa: BLE001 - the boundary to the scene's code: anything a report raises
            raise SceneError(f"scene {scene.name!r}: report {rep.title!r} failed: {type(exc).__name__}: {exc}") from exc
        if not isinstance(values, dict):
            raise SceneError(f"scene {scene.name!r}: report {rep.title!r} must return a dict name -> value, "
                             f"got {type(values).__name__}")
        entry = {"values": values}
        lines.append(f"{rep.title}:")
        width = max((len(k) for k in values), default=0)
        for k, v in values.items():
            line = f"  {k:<{width}s}  {format_value(v)}"
            if k in rep.printed:
                diff = _difference(v, rep.printed[k])
                line += f"   (paper: {format_value(rep.printed[k])}" + (
                    f"; max difference {diff:.3g})" if diff is not None else ")")
                entry.setdefault("differences", {})[k] = diff
            lines.append(line)
        if rep.printed:
            entry["printed"] = dict(rep.printed)
        data[rep.title] = entry
    return "\n".join(lines), data


def add_reports(lines: list, scene, model, params, settings, command: str, **run) -> dict:
    """:func:`run_reports`, its text appended to ``lines``; returns its data (empty: no report applies)."""
    text, data = run_reports(scene, model, params, settings, command, **run)
    if text:
        lines.append(text)
    return data


def write_run(lines: list, data: dict, run, *, out=None, meta=None, plot=None, draw=None, what: str = "run",
              indent: str = "  ") -> None:
    """Write ``run`` to ``out`` (CSV when the name ends in ``.csv`` and the run has ``to_csv``, else ``.npz`` with
    ``meta``) and the figure to ``plot`` (``draw(plot)``, default ``run.plot(plot)``) when asked, noting both in
    ``lines`` and ``data`` (``run`` may be None when only a figure is drawn)."""
    if out:
        if str(out).lower().endswith(".csv") and hasattr(run, "to_csv"):
            run.to_csv(out)
        else:
            out = run.to_npz(out, meta=meta)
        data["out"] = str(out)
        lines.append(f"{indent}{what} written to {out}")
    if plot:
        from ..plot import close

        close(draw(plot) if draw else run.plot(plot))
        data["plot"] = str(plot)
        lines.append(f"{indent}figure written to {plot}")
