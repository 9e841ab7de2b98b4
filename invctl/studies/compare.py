"""What the feedforward buys: the measures of every tracking run and the one-line comparison of C1 with C2.

:func:`compare_runs` takes the simulated runs (:class:`~invctl.simulate.closed_loop.ClosedLoopResult`) and
returns a :class:`Comparison`: per controller the cumulative and final output error, peak and RMS input,
the largest gain the funnel controller used (``kappa_bar / (1 - phi^2 ||e_bar||^2)``, the gain on ``e_bar``
in (48)), the time spent above 90 % of any funnel, whether the run stayed in its region and funnels, and
the steady offsets left after the move.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: a funnel ratio above this counts as "near the boundary"
NEAR_BOUNDARY = 0.9
#: the law's clip of 1 - phi^2 e^2 (invctl.control.funnel_nmp)
_CLIP = 1e-6


def steady_offsets(run, move_end: float, y_names=None, *, rel=0.01, settle=0.1) -> list:
    """Output errors that remain after the move: ``[(name, offset), ...]`` for every output whose mean error
    over the last quarter of ``[move_end, t_end]`` exceeds ``rel`` times its reference excursion and varies
    there by less than ``settle`` times its size (a steady offset, not a decaying transient)."""
    t = run.t
    if run.departure is not None or t.size < 8 or not move_end < t[-1]:
        return []
    tail = t >= t[-1] - 0.25 * (t[-1] - move_end)
    if tail.sum() < 4:
        return []
    names = list(y_names or run.y_names or [f"y{i + 1}" for i in range(run.y.shape[0])])
    out = []
    for i in range(run.y.shape[0]):
        e = run.y[i, tail] - run.y_ref[i, tail]
        excursion = float(np.ptp(run.y_ref[i])) or float(np.max(np.abs(run.y_ref[i]))) or 1.0
        mean = float(np.mean(e))
        if abs(mean) > rel * excursion and float(np.ptp(e)) < settle * abs(mean):
            out.append((names[i], mean))
    return out


def run_measures(run, kappa_bar=None, move_end=None) -> dict:
    """The measures of one run (see the module docstring); ``kappa_bar`` of its funnel controller (None:
    no feedback), ``move_end`` the end of the reference's transition (for the steady offsets)."""
    t = run.t
    u = np.atleast_2d(run.u)
    unorm = np.linalg.norm(u, axis=0)
    span = float(t[-1] - t[0]) if t.size > 1 else 0.0
    rms = (np.sqrt(np.trapezoid(unorm ** 2, t) / span) if span > 0 else float(unorm[0]) if unorm.size else 0.0)
    out = {"cumulative_output_error": float(run.cumulative_errors["output"]),
           "cumulative_errors": {k: float(v) for k, v in run.cumulative_errors.items()},
           "final_output_error": float(run.output_error[-1]) if t.size else float("nan"),
           "peak_input": float(np.max(unorm)) if unorm.size else 0.0,
           "rms_input": float(rms),
           "input_peaks": [float(np.max(np.abs(ui))) for ui in u],
           "max_gain": None, "max_funnel_ratio": None, "time_near_boundary": None,
           "inside": run.departure is None and run.status in ("ok",),
           "status": run.status,
           "departure": None if run.departure is None else {"t": run.departure[0], "what": run.departure[1]},
           "steady_offsets": [] if move_end is None else steady_offsets(run, move_end)}
    if run.ratios.size:
        ratios = np.asarray(run.ratios, float)
        worst = np.max(ratios, axis=0)
        near = (worst > NEAR_BOUNDARY).astype(float)
        dt = np.diff(t)
        out["max_funnel_ratio"] = float(np.max(ratios))
        out["time_near_boundary"] = float(np.sum(dt * 0.5 * (near[1:] + near[:-1]))) if t.size > 1 else 0.0
        if kappa_bar is not None:
            out["max_gain"] = float(np.max(kappa_bar / np.maximum(1.0 - ratios[-1] ** 2, _CLIP)))
    return out


@dataclass
class Comparison:
    """Measures per controller (``measures[name]``: :func:`run_measures`) and the headline of ``a`` vs ``b``."""

    measures: dict
    a: str = "C1"
    b: str = "C2"
    u_unit: str = ""
    y_units: dict = field(default_factory=dict)

    def headline(self) -> str:
        """One line: what ``a`` gains over ``b`` on every measure, and the steady offsets that remain."""
        M, a, b = self.measures, self.a, self.b
        if not {a, b} <= set(M):
            return ""
        A, B = M[a], M[b]

        def rel(key, what):
            x, y = A[key], B[key]
            if x is None or y is None or not y > 0:
                return None
            return f"{what} {100 * (1 - x / y):+.0f} %"

        parts = [p for p in (rel("cumulative_output_error", "cumulative error"),
                             rel("final_output_error", "final error"), rel("peak_input", "peak input"),
                             rel("rms_input", "RMS input"), rel("max_gain", "largest gain")) if p]
        near = (A["time_near_boundary"], B["time_near_boundary"])
        if None not in near:
            parts.append(f"time above {NEAR_BOUNDARY:.0%} of a funnel {near[0]:.3g} s vs {near[1]:.3g} s")
        line = f"{a} vs {b} (reduction, + = {a} better): " + ", ".join(parts)
        out = [n for n in (a, b) if not M[n]["inside"]]
        if out:
            line += "; NOT comparable: " + ", ".join(
                f"{n} {M[n]['departure']['what']} at t = {M[n]['departure']['t']:.3g} s" if M[n]["departure"]
                else f"{n} {M[n]['status']}" for n in out)
        offsets = {n: M[n]["steady_offsets"] for n in M if M[n]["steady_offsets"]}
        if offsets:
            line += "; steady offset after the move: " + "; ".join(
                f"{n}: " + ", ".join(f"{nm} {v:+.3g}{(' ' + self.y_units[nm]) if self.y_units.get(nm) else ''}"
                                     for nm, v in offs) for n, offs in offsets.items())
        return line

    def table(self) -> str:
        u = f" [{self.u_unit}]" if self.u_unit else ""
        head = (f"{'':7s}{'cum. |e_y|':>11s} {'final |e_y|':>12s} {'peak |u|' + u:>13s} {'RMS |u|' + u:>13s} "
                f"{'max gain':>10s} {'t > 90%':>8s} {'max phi|e|':>11s}  stayed inside")
        lines = [head]
        for n, M in self.measures.items():
            f = lambda x, w, p: f"{'-':>{w}s}" if x is None else f"{x:{w}.{p}g}"  # noqa: E731
            lines.append(f"{n:7s}{M['cumulative_output_error']:11.4g} {M['final_output_error']:12.4g} "
                         f"{M['peak_input']:13.4g} {M['rms_input']:13.4g} {f(M['max_gain'], 10, 4)} "
                         f"{f(M['time_near_boundary'], 8, 3)} {f(M['max_funnel_ratio'], 11, 4)}  "
                         + ("yes" if M["inside"] else f"NO ({M['status']})"))
        h = self.headline()
        return "\n".join(lines + ([h] if h else []))

    def to_dict(self) -> dict:
        return {"measures": self.measures, "headline": self.headline(), "a": self.a, "b": self.b}


def compare_runs(runs: dict, *, kappa_bar: dict | None = None, move_end: float | None = None, a="C1", b="C2",
                 units: dict | None = None) -> Comparison:
    """The measures of every run and the comparison of ``a`` with ``b``; ``kappa_bar[name]`` is the gain of
    the run's funnel controller (absent: no feedback), ``units`` maps output/input names to units."""
    kappa_bar, units = dict(kappa_bar or {}), dict(units or {})
    measures = {name: run_measures(r, kappa_bar.get(name), move_end) for name, r in runs.items()}
    first = next(iter(runs.values()), None)
    u_units = {units.get(n, "") for n in (first.u_names if first is not None else [])}
    return Comparison(measures, a, b, u_units.pop() if len(u_units) == 1 else "",
                      {n: units[n] for n in (first.y_names if first is not None else []) if n in units})
