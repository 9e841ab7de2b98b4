"""Parameter and robustness sweeps on any ``concurrent.futures.Executor``.

A sweep evaluates a picklable function at many points.  It runs on a local
process pool by default, on any ``concurrent.futures.Executor`` a user passes,
and on a ``dask.distributed.Client`` unchanged (its ``get_executor()`` is used).
Every point ends in the result: values for those that worked, the exception
type and message for those that failed -- failed points are reported, never
dropped.
"""
from __future__ import annotations

import itertools
import os
import sys
import time
from concurrent.futures import Executor, ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from ..errors import INTERRUPT_LIKE, ParameterError, RunInterrupted, check_interrupt, is_interrupt, watch_sigint
from ..io import write_rows


def grid(**axes: Sequence[float]) -> tuple[list[dict[str, float]], tuple[int, ...]]:
    """All combinations of the given axes (first axis slowest) and the grid shape."""
    names = list(axes)
    values = [list(np.atleast_1d(axes[k])) for k in names]
    points = [dict(zip(names, combo)) for combo in itertools.product(*values)]
    return points, tuple(len(v) for v in values)


@dataclass
class SweepResult:
    """Outcome of a sweep.

    Attributes
    ----------
    points : list of dict
        The parameter points, in the order given.
    values : list of dict or None
        The function's result per point (``None`` where it failed).
    errors : list of str or None
        ``"ExceptionType: message"`` per failed point, ``None`` where it worked.
    shape : tuple
        Grid shape when the sweep came from ``grid`` (else ``(len(points),)``).
    wall_s : float
        Wall time of the whole sweep.
    """

    points: list[dict[str, Any]]
    values: list[dict[str, Any] | None]
    errors: list[str | None]
    shape: tuple[int, ...]
    wall_s: float = 0.0
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def failed(self) -> list[tuple[dict[str, Any], str]]:
        """The failed points with their error."""
        return [(p, e) for p, e in zip(self.points, self.errors) if e is not None]

    @property
    def n_failed(self) -> int:
        return sum(e is not None for e in self.errors)

    def array(self, key: str) -> np.ndarray:
        """One output as an array of the sweep's shape (NaN where the point failed)."""
        out = np.array([np.nan if v is None else float(v.get(key, np.nan)) for v in self.values])
        return out.reshape(self.shape)

    def rows(self) -> list[dict[str, Any]]:
        """One flat dict per point: parameters, outputs, and ``error``."""
        rows = []
        for p, v, e in zip(self.points, self.values, self.errors):
            row = dict(p)
            if v is not None:
                row.update({k: val for k, val in v.items() if np.isscalar(val)})
            row["error"] = e or ""
            rows.append(row)
        return rows

    def to_csv(self, path: str | os.PathLike) -> None:
        write_rows(path, self.rows())

    @property
    def failed_mask(self) -> np.ndarray:
        """True where the point raised (shape of the sweep)."""
        return np.array([e is not None for e in self.errors]).reshape(self.shape)

    def plot(self, key: str, ax=None, *, log: bool = False, contour: float | None = None, **kwargs):
        """A line (1-D sweep) or a heat map (2-D grid) of one output.

        Failed points are marked with a red x (their error is in ``failed``); NaN
        outputs of points that worked stay blank.  ``log`` colours by log10;
        ``contour`` draws the level line of that value (e.g. Lambda = 1).
        """
        import matplotlib.pyplot as plt

        if ax is None:
            _, ax = plt.subplots(figsize=(6, 4.5))
        names = list(self.points[0]) if self.points else []
        data = self.array(key)
        fail = self.failed_mask
        label = key
        if log:
            with np.errstate(divide="ignore", invalid="ignore"):
                data = np.where(data > 0, np.log10(np.where(data > 0, data, 1.0)), np.nan)
            label = f"log10 {key}"
        if len(self.shape) == 2 and len(names) == 2:
            xs = sorted({p[names[1]] for p in self.points}, key=self._order(names[1]))
            ys = sorted({p[names[0]] for p in self.points}, key=self._order(names[0]))
            mesh = ax.pcolormesh(np.arange(len(xs) + 1), np.arange(len(ys) + 1), np.ma.masked_invalid(data),
                                 shading="flat", **kwargs)
            ax.set_xticks(np.arange(len(xs)) + 0.5, [f"{x:.3g}" for x in xs], rotation=45)
            ax.set_yticks(np.arange(len(ys)) + 0.5, [f"{y:.3g}" for y in ys])
            ax.set_xlabel(self._label(names[1]))
            ax.set_ylabel(self._label(names[0]))
            ax.figure.colorbar(mesh, ax=ax, label=label)
            if contour is not None and np.isfinite(data).sum() >= 4:
                level = np.log10(contour) if log else contour
                finite = np.isfinite(data)
                if data[finite].min() < level < data[finite].max():
                    cx, cy = np.meshgrid(np.arange(len(xs)) + 0.5, np.arange(len(ys)) + 0.5)
                    ax.contour(cx, cy, np.ma.masked_invalid(data), levels=[level], colors="k", linewidths=1.5)
            bad = np.argwhere(fail)
            if bad.size:
                ax.plot(bad[:, 1] + 0.5, bad[:, 0] + 0.5, "rx", ms=10, mew=2, label="failed")
                ax.legend(loc="best", fontsize=8)
        else:
            x = np.array([list(p.values())[0] for p in self.points], float)
            ax.plot(x, data.ravel(), "o-", **kwargs)
            f = fail.ravel()
            if f.any():
                ax.plot(x[f], np.zeros(f.sum()), "rx", label="failed")
                ax.legend(loc="best")
            if contour is not None:
                ax.axhline(np.log10(contour) if log else contour, color="k", lw=1)
            ax.set_xlabel(self._label(names[0]) if names else "point")
            ax.set_ylabel(label)
        ax.set_title(f"{label} ({self.n_failed} failed of {len(self.points)})")
        return ax

    def _label(self, name: str) -> str:
        """Axis label of a sweep parameter (``meta["labels"]`` may give units or meaning)."""
        return self.meta.get("labels", {}).get(name, name)

    def _order(self, name):
        order = {}
        for p in self.points:
            order.setdefault(p[name], len(order))
        return lambda v: order[v]


def _call(fn: Callable[..., Mapping[str, Any]], point: Mapping[str, Any]):
    try:
        out = fn(**point)
        return dict(out), None
    except Exception as exc:  # a failed point is data, not a crash of the sweep
        return None, f"{type(exc).__name__}: {exc}"


def executor_slots(executor, max_workers) -> int:
    """How many points run at once on ``executor`` (as :func:`open_executor` decides), without starting workers."""
    if executor == "serial":
        return 1
    if executor is None:
        return max(1, max_workers or os.cpu_count() or 1)
    if hasattr(executor, "get_executor") and not isinstance(executor, Executor):  # dask.distributed.Client
        try:
            return max(1, sum(executor.nthreads().values()))
        except Exception:
            return os.cpu_count() or 1
    return max(1, getattr(executor, "_max_workers", None) or os.cpu_count() or 1)


def open_executor(executor, max_workers):
    """``(executor, owned, slots)``: a process pool by default (``max_workers`` processes, default the CPU count),
    a Dask client's executor, the given executor, or ``None`` (serial: ``"serial"`` or one process)."""
    slots = executor_slots(executor, max_workers)
    if executor == "serial" or (executor is None and slots <= 1):
        return None, False, 1
    if executor is None:
        return ProcessPoolExecutor(max_workers=slots), True, slots
    if hasattr(executor, "get_executor") and not isinstance(executor, Executor):  # dask.distributed.Client
        return executor.get_executor(), False, slots
    if not isinstance(executor, Executor):
        raise ParameterError(f"executor must be a concurrent.futures.Executor, a dask.distributed.Client or "
                             f"'serial', got {type(executor).__name__}")
    return executor, False, slots


def sweep(
    fn: Callable[..., Mapping[str, Any]],
    points: Sequence[Mapping[str, Any]] | tuple[list, tuple],
    *,
    executor: Executor | Any | None = None,
    max_workers: int | None = None,
    progress: bool = True,
    label: str = "sweep",
) -> SweepResult:
    """Evaluate ``fn(**point)`` at every point, in parallel.

    Parameters
    ----------
    fn : callable
        Picklable (module-level) function returning a dict of scalar outputs.
    points : list of dict, or the ``(points, shape)`` pair from :func:`grid`
    executor : concurrent.futures.Executor or dask.distributed.Client, optional
        Where to run.  Default: a local process pool (``max_workers``
        processes, default the CPU count; one runs in this process); ``"serial"`` runs in this process.
    progress : bool
        Print ``label: done/total`` lines to stderr.

    Raises
    ------
    RunInterrupted
        On Ctrl-C (SIGINT): pending points are cancelled and ``partial`` is the result with the
        points complete so far (the others carry the error ``"not run: interrupted"``;
        ``meta["partial"]`` says so).
    """
    if isinstance(points, tuple) and len(points) == 2 and isinstance(points[1], tuple):
        pts, shape = points
    else:
        pts = list(points)
        shape = (len(pts),)
    pts = [dict(p) for p in pts]
    values: list[dict | None] = [None] * len(pts)
    errors: list[str | None] = [None] * len(pts)
    t0 = time.perf_counter()
    step = max(1, len(pts) // 10)

    def report(done: int) -> None:
        if progress and (done % step == 0 or done == len(pts)):
            print(f"{label}: {done}/{len(pts)} points ({time.perf_counter() - t0:.1f} s)", file=sys.stderr)

    finished = [False] * len(pts)
    ex, owned, _ = open_executor(executor, max_workers)
    try:
        if ex is None:
            for i, p in enumerate(pts):
                check_interrupt()
                with watch_sigint() as sigint:
                    values[i], errors[i] = _call(fn, p)
                if sigint.seen:  # Ctrl-C, possibly turned into a failure of this point by a compiled solver
                    raise KeyboardInterrupt
                finished[i] = True
                report(i + 1)
        else:
            futures = {}
            try:
                futures = {ex.submit(_call, fn, p): i for i, p in enumerate(pts)}
                for done, fut in enumerate(as_completed(futures), 1):
                    i = futures[fut]
                    try:
                        values[i], errors[i] = fut.result()
                    except Exception as exc:  # worker died, pickling failed, ...
                        values[i], errors[i] = None, f"{type(exc).__name__}: {exc}"
                    finished[i] = True
                    report(done)
            except INTERRUPT_LIKE as _exc:
                if not is_interrupt(_exc):
                    raise
                for fut in futures:
                    fut.cancel()
                if owned:
                    ex.shutdown(wait=False, cancel_futures=True)
                    owned = False
                raise
            finally:
                if owned:
                    ex.shutdown()
    except INTERRUPT_LIKE as _exc:
        if not is_interrupt(_exc):
            raise
        k = sum(finished)
        note = f"{label} interrupted: {k} of {len(pts)} points complete"
        errors = [e if f else "not run: interrupted" for e, f in zip(errors, finished)]
        values = [v if f else None for v, f in zip(values, finished)]
        partial = SweepResult(pts, values, errors, shape, time.perf_counter() - t0, {"partial": note})
        raise RunInterrupted(note, partial=partial) from None
    return SweepResult(pts, values, errors, shape, time.perf_counter() - t0)
