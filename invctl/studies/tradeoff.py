"""Speed-versus-accuracy studies: sweep an accuracy knob, measure time and error.

A scene offers its trade-off with ``tradeoff_spec(params, smoke=False)``
returning a :class:`TradeoffSpec`: the knob (mesh size and scheme for
inversion, tolerances for closed-loop simulation, time step for
time-stepping), the values to try, a function that runs one setting and
returns its error against a finely resolved reference and its time, and a
sentence saying how that reference was obtained.
"""
from __future__ import annotations

import json
import math
import os
import sys
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from ..errors import INTERRUPT_LIKE, ResultFileError, RunInterrupted, is_interrupt, watch_sigint
from ..io import write_rows


@dataclass
class TradeoffSpec:
    """What to sweep and how to measure one setting.

    Parameters
    ----------
    knob : str
        Name of the accuracy knob (e.g. ``"N"``, ``"h"``, ``"rtol"``).
    values : sequence
        Settings to try; a setting may be a number, a string or a dict of
        several knobs (e.g. ``{"scheme": "radau3", "N": 40}``).
    run : callable
        ``run(value) -> {"error": float, "time_s": float, ...}``; the time
        covers the work a user would pay for that setting, not the reference.
    reference : str
        How the reference the errors are measured against was obtained.
    error_name : str
        What ``error`` measures (shown on plots).
    repeat : bool
        Whether a fast setting may be re-run for a steadier time; ``False`` when a
        second run would be cheaper than the first for reasons a user does not
        get for free (e.g. a cached NLP build): then the first, cold run counts.
    """

    knob: str
    values: Sequence[Any]
    run: Callable[[Any], Mapping[str, Any]]
    reference: str
    error_name: str = "error"
    scene: str = ""
    repeat: bool = True


@dataclass
class TradeoffResult:
    """Rows of (knob, value, error, time_s, ...) with the reference description."""

    knob: str
    rows: list[dict[str, Any]]
    reference: str
    error_name: str = "error"
    scene: str = ""
    failures: list[dict[str, Any]] = field(default_factory=list)
    partial: str = ""  #: why the rows stop short (an interrupted study), empty when complete

    @property
    def errors(self) -> np.ndarray:
        return np.array([r["error"] for r in self.rows], float)

    @property
    def times(self) -> np.ndarray:
        return np.array([r["time_s"] for r in self.rows], float)

    def pareto(self) -> np.ndarray:
        """Boolean mask of rows no other row beats in both time and error."""
        e, t = self.errors, self.times
        mask = np.ones(len(e), bool)
        for i in range(len(e)):
            dominated = (e <= e[i]) & (t <= t[i]) & ((e < e[i]) | (t < t[i]))
            mask[i] = not dominated.any()
        return mask

    def recommend(self, max_error: float) -> dict[str, Any] | None:
        """The fastest row whose error is at most ``max_error`` (None if none is)."""
        ok = [r for r in self.rows if r["error"] <= max_error]
        return min(ok, key=lambda r: r["time_s"]) if ok else None

    def table(self) -> str:
        """A fixed-width text table, Pareto-optimal rows starred."""
        mask = self.pareto()
        lines = [f"{self.knob:>24}  {self.error_name:>12}  {'time_s':>10}  pareto"]
        for row, p in zip(self.rows, mask):
            lines.append(f"{_fmt(row['value']):>24}  {row['error']:12.3e}  {row['time_s']:10.4f}  {'*' if p else ''}")
        for f in self.failures:
            lines.append(f"{_fmt(f['value']):>24}  failed: {f['message']}")
        lines.append(f"reference: {self.reference}")
        if self.partial:
            lines.append(f"PARTIAL: {self.partial}")
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        return {
            "scene": self.scene, "knob": self.knob, "error_name": self.error_name,
            "rows": [{"knob": self.knob, **r, "value": _jsonable_value(r["value"])} for r in self.rows],
            "failures": [{**f, "value": _jsonable_value(f["value"])} for f in self.failures],
            "reference": self.reference,
            "pareto": self.pareto().tolist(),
            **({"partial": self.partial} if self.partial else {}),
        }

    def to_csv(self, path: str | os.PathLike) -> None:
        write_rows(path, [{"knob": self.knob, **r, "value": _fmt(r["value"])} for r in self.rows], ("knob",))

    def to_json(self, path: str | os.PathLike) -> None:
        with open(path, "w") as fh:
            json.dump(self.to_dict(), fh, indent=1)

    @classmethod
    def from_json(cls, path: str | os.PathLike) -> "TradeoffResult":
        """Read what :meth:`to_json` wrote.

        Raises
        ------
        ResultFileError
            Missing, unreadable or truncated file, not a trade-off table, rows without a finite
            ``error``/``time_s``.
        """
        try:
            with open(path) as fh:
                d = json.load(fh)
        except FileNotFoundError:
            raise ResultFileError(f"{path}: no such file") from None
        except (OSError, UnicodeDecodeError, ValueError) as exc:
            raise ResultFileError(f"{path}: not a readable JSON file ({type(exc).__name__}: {exc}); the file is "
                                  "truncated or not written by invctl study tradeoff") from None
        if not (isinstance(d, dict) and isinstance(d.get("knob"), str) and isinstance(d.get("rows"), list)
                and isinstance(d.get("reference"), str)):
            raise ResultFileError(f"{path}: not a trade-off table (needs 'knob', 'rows', 'reference'; written by "
                                  "invctl study tradeoff)")
        rows = []
        for i, r in enumerate(d["rows"]):
            if not isinstance(r, dict) or "value" not in r:
                raise ResultFileError(f"{path}: row {i} is not a trade-off row")
            for key in ("error", "time_s"):
                v = r.get(key)
                if isinstance(v, bool) or not isinstance(v, (int, float)) or (key == "time_s" and not math.isfinite(v)):
                    raise ResultFileError(f"{path}: row {i}: {key!r} = {v!r} is not a number")
            rows.append({k: v for k, v in r.items() if k != "knob"})
        failures = d.get("failures", [])
        if not isinstance(failures, list):
            raise ResultFileError(f"{path}: 'failures' must be a list")
        return cls(d["knob"], rows, d["reference"], str(d.get("error_name", "error")), str(d.get("scene", "")),
                   failures, str(d.get("partial", "")))

    def plot(self, ax=None):
        """Error against time on log axes, each point labelled, the Pareto front drawn."""
        import matplotlib.pyplot as plt

        if ax is None:
            _, ax = plt.subplots(figsize=(6.5, 4.5))
        e, t, mask = self.errors, self.times, self.pareto()
        groups: dict[str, list[int]] = {}
        for i, r in enumerate(self.rows):
            groups.setdefault(str(r.get("group", "")), []).append(i)
        for name, idx in groups.items():
            ax.loglog(t[idx], e[idx], "o", label=name or None)
        for i, r in enumerate(self.rows):
            v = r["value"]
            if isinstance(v, dict) and "group" in r:
                v = {k: x for k, x in v.items() if str(x) != str(r["group"])}
            ax.annotate(_fmt(v), (t[i], e[i]), textcoords="offset points", xytext=(4, 4), fontsize=7)
        order = np.argsort(t[mask])
        ax.loglog(t[mask][order], e[mask][order], "k--", lw=1, label="Pareto front")
        ax.set_xlabel("time [s]")
        ax.set_ylabel(self.error_name)
        ax.set_title(f"{self.scene}: speed vs accuracy ({self.knob})")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
        return ax


def _fmt(v: Any) -> str:
    if isinstance(v, dict):
        return ",".join(f"{k}={_fmt(x)}" for k, x in v.items())
    if isinstance(v, float):
        return f"{v:.3g}"
    return str(v)


def _jsonable_value(v: Any) -> Any:
    if isinstance(v, dict):
        return {k: _jsonable_value(x) for k, x in v.items()}
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    return v


def run_tradeoff(spec: TradeoffSpec, *, progress: bool = True, min_time_s: float = 0.5,
                 max_repeats: int = 5) -> TradeoffResult:
    """Run every setting of ``spec`` in this process, one after another.

    Settings run serially on purpose: timings measured under contention for
    cores would not be comparable.  A fast setting is repeated (up to
    ``max_repeats`` times, until ``min_time_s`` is spent) and its best time
    kept, so one scheduling hiccup does not decide the trade; ``repeats`` says
    how many runs there were.  A setting that raises is reported in
    ``failures`` with its message, not dropped.

    Raises
    ------
    RunInterrupted
        On Ctrl-C (SIGINT): ``partial`` is the result with the rows complete so far.
    """
    rows: list = []
    failures: list = []
    k, value = 0, None
    try:
        for k, value in enumerate(spec.values, 1):
            with watch_sigint() as sigint:
                _one_setting(spec, value, rows, failures, min_time_s, max_repeats)
            if sigint.seen:  # a compiled solver turned Ctrl-C into a failure of this setting: not a result
                if failures and failures[-1]["value"] is value:
                    failures.pop()
                raise KeyboardInterrupt
            if progress:
                last = rows[-1] if rows and rows[-1]["value"] is value else None
                msg = "failed" if last is None else f"error {last['error']:.3e} in {last['time_s']:.3f} s"
                print(f"tradeoff {spec.scene} {spec.knob}={_fmt(value)}: {msg} ({k}/{len(spec.values)})",
                      file=sys.stderr)
    except INTERRUPT_LIKE as _exc:
        if not is_interrupt(_exc):
            raise
        note = (f"interrupted at {spec.knob}={_fmt(value)} ({k}/{len(spec.values)}); {len(rows)} of "
                f"{len(spec.values)} settings complete")
        raise RunInterrupted(note, partial=TradeoffResult(spec.knob, rows, spec.reference, spec.error_name,
                                                          spec.scene, failures, note)) from None
    return TradeoffResult(spec.knob, rows, spec.reference, spec.error_name, spec.scene, failures)


def _one_setting(spec: TradeoffSpec, value, rows: list, failures: list, min_time_s: float, max_repeats: int) -> None:
    """Run one setting (repeated while fast), appending to ``rows`` or ``failures``."""
    try:
        out = dict(spec.run(value))
        for key in ("error", "time_s"):
            if key not in out:
                raise KeyError(f"trade-off run for {spec.knob}={value!r} returned no {key!r}")
        spent, times = float(out["time_s"]), [float(out["time_s"])]
        while spec.repeat and spent < min_time_s and len(times) < max_repeats:
            t = float(spec.run(value)["time_s"])
            times.append(t)
            spent += t
        out["time_s"], out["repeats"] = min(times), len(times)
    except KeyError:
        raise
    except Exception as exc:  # noqa: BLE001 - the boundary to the caller's job (a scene's study, a TradeoffSpec's run):
        # whatever one setting raises is that setting's result, reported in ``failures``
        failures.append({"value": value, "message": f"{type(exc).__name__}: {exc}"})
        return
    rows.append({"value": value, **out})
