"""Records of contact simulations: the result type, its exact run statistics,
the chunk recorder of the compiled Moreau-Jean loop and its memory budget.

A run streams its steps chunk by chunk out of the compiled loop; the
:class:`ChunkRecorder` keeps every ``record_every``-th step and/or the event
steps (impacts and changes of the active or loaded set), never all steps.
Statistics that need every step (smallest gap, largest increase of the
energy and of ``V``, impacts, rest time) are accumulated inside the compiled
loop and are exact whatever is recorded (see ``ContactTrajectory.stats``; those the
run monitors, ``stats["monitor"]``).
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from ..errors import ParameterError, RecordingError, ResourceLimitError, ResultFileError, SimulationFailed
from ..results import Animated, plot_target

#: format version of the ContactTrajectory files written now (3: time along the last axis); files
#: of version 2 (time along the first axis) are read and transposed
CONTACT_FORMAT_VERSION = 3
_TIME_FIRST_VERSIONS = (2,)
#: the stats entries with time along one axis (transposed with the arrays)
_TIMED_STATS = ("Un", "u")

#: default memory budget of a run: this fraction of the memory available when it starts
DEFAULT_MEMORY_FRACTION = 0.5


def available_memory() -> int:
    """Bytes of memory available to new allocations (``MemAvailable`` on Linux)."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return 4 << 30


def resolve_memory_budget(budget=None) -> tuple[int, str]:
    """``(bytes, description)`` of a memory budget: a number of bytes, or None
    for :data:`DEFAULT_MEMORY_FRACTION` of :func:`available_memory`."""
    if budget is None:
        cap = os.environ.get("INVCTL_MAX_MEMORY")
        if cap:
            try:
                return int(float(cap)), f"INVCTL_MAX_MEMORY = {cap}"
            except ValueError:
                raise ParameterError(f"INVCTL_MAX_MEMORY must be a number of bytes, got {cap!r}") from None
        avail = available_memory()
        return int(DEFAULT_MEMORY_FRACTION * avail), (f"{DEFAULT_MEMORY_FRACTION:.0%} of the "
                                                      f"{_fmt_bytes(avail)} available")
    try:
        b = float(budget)
    except (TypeError, ValueError):
        raise ParameterError(f"memory_budget must be a number of bytes, got {budget!r}") from None
    if not (b > 0 and math.isfinite(b)):
        raise ParameterError(f"memory_budget must be a positive number of bytes, got {budget!r}")
    return int(b), "memory_budget"


def _fmt_bytes(b: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(b) < 1024 or unit == "TiB":
            return f"{b:.3g} {unit}"
        b /= 1024.0
    return f"{b:.3g} TiB"


@dataclass
class ContactTrajectory(Animated):
    """Result of a time-stepping (or event-driven) contact simulation, time along the last axis: ``q``, ``v``
    ``(n, len(t))`` from ``t[0]`` on; ``gaps`` ``(m_u, len(t))``; ``P`` (the impulses of each step, ``P/h``
    estimates the contact force) and ``active`` (the active-set flags) ``(m_u, len(t) - 1)`` for a finished run
    (one column per step); ``energy`` (mechanical) and ``V`` (the law's Lyapunov function) ``(len(t),)``;
    ``stats["Un"]`` (normal velocities) ``(m_u, len(t))``, ``stats["u"]`` (inputs) ``(m, len(t))``; the impact
    table ``stats["impact_v_plus"]`` is ``(n_impacts, n)``, one row per impact.

    A decimated or event record (``run(..., record_every=k)`` or ``record="events"``) holds the recorded steps
    only: column ``j`` is the state at step ``stats["step_index"][j]`` and ``P[:, j]``, ``active[:, j]`` the
    impulse and active set of that step; the last column is the final state.  Its statistics
    (:attr:`max_gap_violation`, :attr:`max_V_increase`, :attr:`max_energy_increase`, :meth:`impacts`,
    :meth:`rest_time`) come from the exact accumulators of the run, which see every step; :meth:`impact_mask`
    needs every step and raises :class:`~invctl.errors.RecordingError`.
    """

    t: np.ndarray
    q: np.ndarray
    v: np.ndarray
    P: np.ndarray
    active: np.ndarray
    gaps: np.ndarray
    energy: np.ndarray
    V: np.ndarray
    h: float
    names: dict = field(default_factory=dict)
    stats: dict = field(default_factory=dict)
    impact_vel_tol: float = 1e-8
    meta: dict = field(default_factory=dict)
    status: str = "ok"
    message: str = ""

    _KIND, _VERSION, _OLDER = "ContactTrajectory", CONTACT_FORMAT_VERSION, _TIME_FIRST_VERSIONS
    _ARRAYS = ("t", "q", "v", "P", "active", "gaps", "energy", "V")
    _PREFIXED = {"stats": "stats:"}
    _REQUIRED = ("stats",)

    # ---------------------------------------------------------- derived data
    @property
    def u(self) -> np.ndarray:
        """The inputs ``(m, len(t))`` (``stats["u"]``; no rows for an uncontrolled run)."""
        u = self.stats.get("u")
        u = None if u is None else np.atleast_2d(np.asarray(u, float))
        return u if u is not None and u.shape[-1] == np.size(self.t) else np.zeros((0, np.size(self.t)))

    @property
    def lam(self) -> np.ndarray:
        """Contact force estimates ``P / h`` of the step starting at each sample, ``(m_u, len(t))`` (the last
        sample, which starts no step, is zero)."""
        P = np.atleast_2d(np.asarray(self.P, float)) / self.h
        pad = np.size(self.t) - P.shape[-1]
        return np.hstack([P, np.zeros((P.shape[0], pad))]) if pad > 0 else P[:, :np.size(self.t)]

    @property
    def complete(self) -> bool:
        """True when every step is recorded."""
        return self.stats.get("record", "steps") == "steps" and int(self.stats.get("record_every", 1)) == 1

    def _need_complete(self, what: str):
        if not self.complete:
            raise RecordingError(
                f"{what} needs every step, but this trajectory recorded "
                f"{self.stats.get('record')!r} with record_every={self.stats.get('record_every')}; use the exact "
                "run statistics (impacts(), max_gap_violation, max_V_increase, stats['dV_max_impact'], ...) "
                "or re-run with record_every=1")

    def _monitored(self, key: str, name: str, what: str) -> bool:
        """Whether ``stats[key]`` holds the run's accumulator; False when every step is recorded (the
        records give it); raises :class:`RecordingError` for a reduced record of a run that did not
        monitor ``name``."""
        if key in self.stats:
            return True
        mon = self.stats.get("monitor")
        if mon is None or name in list(mon) or self.complete:
            return False
        raise RecordingError(
            f"{what} needs the running statistic {name!r}, which this run did not monitor (monitor="
            f"{tuple(str(k) for k in mon)}) and its reduced record cannot give; re-run with "
            f"MoreauJean(..., monitor=(..., {name!r})) (or monitor='all') or record_every=1")

    def impacts(self, contact: int | None = None):
        """Impact steps (see :meth:`impact_mask`); returns arrays
        ``(times, contact index, pre-impact normal velocity, post-impact
        normal velocity, post-impact v)``, one entry per impact (the
        post-impact velocities are ``(n_impacts, n)``, one row per impact,
        like ``stats["impact_v_plus"]``).  The impact time is reported as
        the mid-point of the step (first-order accurate).  Exact for
        decimated and event records too (accumulated during the run)."""
        if not self.complete:
            s = self.stats
            sel = slice(None) if contact is None else (np.asarray(s["impact_contact"]) == contact)
            return (np.asarray(s["impact_t"])[sel], np.asarray(s["impact_contact"])[sel],
                    np.asarray(s["impact_pre"])[sel], np.asarray(s["impact_post"])[sel],
                    np.asarray(s["impact_v_plus"]).reshape(-1, self.q.shape[0])[sel])
        Un = self.stats["Un"]
        pre, post = Un[:, :-1], Un[:, 1:]
        hit = self.impact_mask()
        if contact is not None:
            hit[[i for i in range(hit.shape[0]) if i != contact], :] = False
        k, i = np.nonzero(hit.T)  # ordered by step, then contact
        return self.t[k] + 0.5 * self.h, i, pre[i, k], post[i, k], self.v[:, k + 1].T

    def impact_mask(self) -> np.ndarray:
        """``(m_u, steps)`` flags of impacts (time last, like ``P``): the contact carries an impulse, was
        approaching (``W_i^T v_k < -impact_vel_tol``) and carried none in the
        previous step (so persistent contact along a curved boundary, whose
        normal velocity is O(h) each step, is not counted as impacts)."""
        self._need_complete("impact_mask()")
        Un = self.stats.get("Un")
        if Un is None:
            raise SimulationFailed("trajectory has no normal velocities (stats['Un'])")
        loaded = self.P > 0
        prev = np.hstack([np.zeros((loaded.shape[0], 1), bool), loaded[:, :-1]])
        return loaded & ~prev & (Un[:, :-1] < -self.impact_vel_tol)

    @property
    def impact_times(self) -> np.ndarray:
        """Sorted distinct impact times (event-driven results: the located times)."""
        if "impact_t" in self.stats:
            return np.unique(np.asarray(self.stats["impact_t"], float))
        return np.unique(self.impacts()[0])

    @property
    def max_gap_violation(self) -> float:
        """``max(0, -min gap)`` over every step of the run."""
        if self._monitored("gap_min", "gaps", "max_gap_violation"):
            g = np.asarray(self.stats["gap_min"], float)
            return float(max(0.0, -g.min())) if g.size else 0.0
        return float(max(0.0, -self.gaps.min())) if self.gaps.size else 0.0

    @property
    def max_V_increase(self) -> float:
        """Largest one-step increase of ``V`` over every step (should be <=
        round-off for dissipative laws, 000 (39)/(55))."""
        if self._monitored("dV_max", "lyapunov", "max_V_increase"):
            return float(self.stats["dV_max"])
        return float(np.max(np.diff(self.V), initial=0.0))

    @property
    def max_energy_increase(self) -> float:
        """Largest one-step increase of the mechanical energy over every step."""
        if self._monitored("dE_max", "energy", "max_energy_increase"):
            return float(self.stats["dE_max"])
        return float(np.max(np.diff(self.energy), initial=0.0))

    def rest_time(self, contact: int = 0, vel_tol: float | None = None) -> float:
        """First time after which contact ``contact`` stays closed with zero
        normal velocity (nan if it never settles).

        ``vel_tol`` defaults to ``10 impact_vel_tol``; a decimated record only
        knows the value its run accumulated with (``rest_vel_tol`` of ``run``).
        """
        if not self.complete:
            self._monitored("rest_last_bad", "rest", "rest_time()")
            rtol = float(self.stats["rest_vel_tol"])
            if vel_tol is not None and float(vel_tol) != rtol:
                raise RecordingError(f"rest_time(vel_tol={vel_tol}): this record accumulated the rest time with "
                                     f"vel_tol = {rtol}; re-run with rest_vel_tol={vel_tol} or record_every=1")
            last = int(np.asarray(self.stats["rest_last_bad"])[contact])
            steps = int(self.stats["steps"])
            t0 = float(self.t[0])
            if last < 0:
                return t0
            return float("nan") if last >= steps else t0 + (last + 1) * self.h
        Un = self.stats["Un"][contact]
        tol = vel_tol if vel_tol is not None else 10 * self.impact_vel_tol
        still = (np.abs(Un) <= tol) & (self.gaps[contact] <= max(1e-9, 10 * self.h * tol))
        bad = np.flatnonzero(~still)
        if bad.size == 0:
            return float(self.t[0])
        if bad[-1] == still.size - 1:
            return float("nan")
        return float(self.t[bad[-1] + 1])

    # ------------------------------------------------------------ save / plot
    @classmethod
    def _read(cls, path, kw: dict, version: int) -> dict:
        """Files of format version 2 (time along the first axis) transposed to the time-last layout; shapes checked."""
        if version in _TIME_FIRST_VERSIONS:
            for d, keys in ((kw, ("q", "v", "P", "active", "gaps")), (kw["stats"], _TIMED_STATS)):
                for k in keys:
                    if k in d and np.ndim(d[k]) == 2:
                        d[k] = np.ascontiguousarray(d[k].T)
        if isinstance(kw["stats"].get("monitor"), list):  # a tuple written as a JSON list
            kw["stats"]["monitor"] = tuple(kw["stats"]["monitor"])
        cls._check_shapes(path, kw)
        return kw

    @staticmethod
    def _check_shapes(path, d: dict) -> None:
        """Raise :class:`ResultFileError` unless the arrays have the time-last shapes."""
        q, gaps, P, N = d["q"], d["gaps"], d["P"], d["t"].size
        rows = lambda a: a.shape[0] if a.ndim == 2 else -1  # noqa: E731
        steps = P.shape[1] if P.ndim == 2 and P.shape[1] in (N - 1, N) else -1  # one column per step (or sample)
        want = {"t": (N,), "q": (rows(q), N), "v": q.shape, "gaps": (rows(gaps), N), "P": (rows(gaps), steps),
                "active": (rows(gaps), steps), "energy": (N,), "V": (N,)}
        for k, shape in want.items():
            if d[k].shape != shape:
                raise ResultFileError(f"{path}: malformed ContactTrajectory file ({k} has shape {d[k].shape} for "
                                      f"{N} times, expected {shape}: time along the last axis)")

    def plot(self, ax=None, *, path=None, **options):
        """Phase portrait, gaps, impulses, energy and V (see :mod:`invctl.plot.contact`; with ``ax``, the
        generic panels of :class:`~invctl.results.Trajectory` in those axes). Returns the figure."""
        ax, path = plot_target(ax, path)
        if ax is not None:
            return self._generic_plot(ax, path=path, fields=options.pop("fields", ("q", "lam")))
        from ..plot.contact import plot_contact_trajectory

        return plot_contact_trajectory(self, path=path, **options)


# ------------------------------------------------------------------ recorder
@dataclass(frozen=True)
class RowLayout:
    """Rows of the per-step output ``y`` of the compiled step.

    ``y = (q, v, t, gap, U, E, V, u, P, active | U_next, impact, event, ok)``;
    the part before ``|`` (``ncols`` rows) is what a record keeps.
    """

    n: int
    mu: int
    m: int

    @property
    def ncols(self) -> int:
        return 2 * self.n + 3 + 4 * self.mu + self.m

    def sl(self, name: str) -> slice:
        return self._slices[name]

    @cached_property
    def _slices(self) -> dict:
        n, mu, m = self.n, self.mu, self.m
        sizes = [("q", n), ("v", n), ("t", 1), ("gap", mu), ("U", mu), ("E", 1), ("V", 1), ("u", m), ("P", mu),
                 ("act", mu), ("U_next", mu), ("impact", mu), ("event", 1), ("ok", 1)]
        out, o = {}, 0
        for key, size in sizes:
            out[key] = slice(o, o + size)
            o += size
        return out

    @property
    def ny(self) -> int:
        return self.ncols + 2 * self.mu + 2


class ChunkRecorder:
    """Keeps the recorded rows of a run that streams out of the compiled loop.

    Internally one row per recorded step; the :class:`ContactTrajectory` built from them
    (``MoreauJean._package``) holds their transposes, time along the last axis.

    Parameters
    ----------
    layout : RowLayout
    N : int
        Number of steps of the run.
    every : int
        Record every ``every``-th step (step 0 included).
    events : bool
        Record the event steps (impacts, changes of the active or loaded set)
        instead of (``every == 1``) or in addition to the decimated steps.
    t0, h : float
        Start time and step (impact times are step mid-points).
    """

    def __init__(self, layout: RowLayout, N: int, every: int, events: bool, t0: float, h: float):
        self.L = layout
        self.N, self.every, self.events = int(N), int(every), bool(events)
        self.t0, self.h = float(t0), float(h)
        self.complete = self.every == 1 and not self.events
        self.impacts = self.every > 1 or self.events
        self.regular = self.every > 1 or not self.events
        self.blocks: list = []
        self.steps: list = []
        if not self.events:
            self.R = np.empty((self.rows_needed(N, every, events), layout.ncols))
            self.S = np.empty(self.R.shape[0], np.int64)
            self.A = np.empty((self.R.shape[0], layout.mu), bool)  # active flags, taken while a chunk is in cache
        self.pos = 0
        self.n_event_rows = 0
        self.imp: dict[str, list] = {k: [] for k in ("step", "contact", "pre", "post", "v_plus", "dV", "dE")}
        self.n_imp_rows = 0

    @staticmethod
    def rows_needed(N: int, every: int, events: bool) -> int:
        """Recorded rows known before the run (events not counted) plus the final state."""
        if events and every == 1:
            return 2
        return -(-int(N) // int(every)) + 1

    @staticmethod
    def row_bytes_of(layout: RowLayout) -> int:
        """Bytes of one recorded row (values, step index, active flags)."""
        return 8 * layout.ncols + 8 + layout.mu

    def row_bytes(self) -> int:
        return self.row_bytes_of(self.L)

    def impact_bytes(self) -> int:
        return 8 * (6 + self.L.n)

    def nbytes(self) -> int:
        """Bytes held now (records and impact table)."""
        rows = self.pos if not self.events else self.n_event_rows
        return rows * self.row_bytes() + self.n_imp_rows * self.impact_bytes()

    def consume(self, Y: np.ndarray, use: int, base: int, x_after: dict, cols: np.ndarray | None = None):
        """Record the rows of steps ``0..use-1`` of a chunk whose first step is
        ``base``: ``Y[:, :use]`` (``ny x >= use``), or, with ``cols``, the
        sorted steps ``cols`` whose rows are ``Y[:, :len(cols)]`` (the compiled
        driver keeps only the rows this recorder may need: every ``every``-th
        step and, with an impact table, the event steps and the steps after
        them).  ``x_after`` holds ``v``, ``E``, ``V`` of the state after step
        ``use - 1`` (post-impact values)."""
        L = self.L
        if use <= 0:
            return
        if cols is None:
            cols = np.arange(use)
        m = cols.size
        if self.complete:
            assert m == use, "a complete record needs every step of the chunk"
            self.R[self.pos:self.pos + use] = Y[:L.ncols, :use].T
            self.S[self.pos:self.pos + use] = base + cols
            self.A[self.pos:self.pos + use] = Y[L.sl("act"), :use].T > 0.5
            self.pos += use
        else:
            parts = []
            if self.regular:
                parts.append(np.flatnonzero((base + cols) % self.every == 0))
            ev = np.flatnonzero(Y[L.sl("event").start, :m] > 0.5) if self.events or self.impacts else None
            if ev is not None and self.events:
                parts.append(ev)
                if base == 0 and m and cols[0] == 0:
                    parts.append(np.zeros(1, np.intp))
            sel = parts[0] if len(parts) == 1 else np.unique(np.concatenate(parts))
            if sel.size:
                rows = Y[:L.ncols, sel].T
                if self.events:
                    self.blocks.append(rows)
                    self.steps.append(base + cols[sel])
                    self.n_event_rows += sel.size
                else:
                    self.R[self.pos:self.pos + sel.size] = rows
                    self.S[self.pos:self.pos + sel.size] = base + cols[sel]
                    self.A[self.pos:self.pos + sel.size] = rows[:, L.sl("act")] > 0.5
                    self.pos += sel.size
            if ev is not None and ev.size:
                self._impacts(Y, cols, use, base, ev, x_after)

    def _impacts(self, Y, cols, use, base, ev, x_after):
        L = self.L
        sub = Y[L.sl("impact"), :][:, ev] > 0.5
        ci, cj = np.nonzero(sub)
        if ci.size == 0:
            return
        col = ev[cj]
        nxt = col + 1
        m = cols.size
        inside = nxt < m
        inside[inside] = cols[nxt[inside]] == cols[col[inside]] + 1
        assert np.all(inside | (cols[col] + 1 == use)), "the row after an impact step is missing"
        vq = L.sl("v")
        vplus = np.empty((col.size, L.n))
        Vn = np.empty(col.size)
        En = np.empty(col.size)
        vplus[inside] = Y[vq, nxt[inside]].T
        Vn[inside] = Y[L.sl("V").start, nxt[inside]]
        En[inside] = Y[L.sl("E").start, nxt[inside]]
        if not inside.all():
            vplus[~inside] = x_after["v"]
            Vn[~inside] = x_after["V"]
            En[~inside] = x_after["E"]
        self.imp["step"].append(base + cols[col])
        self.imp["contact"].append(ci)
        self.imp["pre"].append(Y[L.sl("U").start + ci, col])
        self.imp["post"].append(Y[L.sl("U_next").start + ci, col])
        self.imp["v_plus"].append(vplus)
        self.imp["dV"].append(Vn - Y[L.sl("V").start, col])
        self.imp["dE"].append(En - Y[L.sl("E").start, col])
        self.n_imp_rows += ci.size

    def finish(self, final_row: np.ndarray, N: int):
        """Append the final state (its ``P``, ``active`` entries are unused)."""
        if self.events:
            self.blocks.append(final_row.reshape(1, -1))
            self.steps.append(np.array([N]))
            self.R = np.concatenate(self.blocks, axis=0)
            self.S = np.concatenate(self.steps).astype(np.int64)
            self.blocks, self.steps = [], []
            self.pos = self.R.shape[0]
        else:
            self.R[self.pos] = final_row
            self.S[self.pos] = N
            self.A[self.pos] = False
            self.pos += 1

    def impact_table(self) -> dict:
        """Exact impact table of the run (every step seen)."""
        cat = {k: (np.concatenate(v) if v else np.zeros((0, self.L.n) if k == "v_plus" else 0))
               for k, v in self.imp.items()}
        order = np.lexsort((cat["contact"], cat["step"])) if cat["step"].size else np.zeros(0, int)
        out = {f"impact_{k}": np.asarray(v)[order] for k, v in cat.items()}
        out["impact_step"] = out["impact_step"].astype(np.int64)
        out["impact_contact"] = out["impact_contact"].astype(np.int64)
        out["impact_t"] = (self.t0 + out["impact_step"] * self.h) + 0.5 * self.h  # as t[k] + h/2 of a full record
        return out

    def settle(self) -> None:
        """Drop what an interruption left half recorded (the lists of one chunk appended in turn)."""
        k = min(len(self.blocks), len(self.steps))
        del self.blocks[k:], self.steps[k:]
        self.n_event_rows = sum(b.shape[0] for b in self.blocks)
        k = min(len(v) for v in self.imp.values())
        for v in self.imp.values():
            del v[k:]
        self.n_imp_rows = sum(a.size for a in self.imp["contact"])

    def active(self) -> np.ndarray:
        """Active flags of the recorded rows (one row per recorded step)."""
        if self.events:
            return self.rows()[0][:, self.L.sl("act")] > 0.5
        return self.A[:self.pos]

    def rows(self):
        """``(R, S)``: recorded rows so far and their step indices (views)."""
        if self.events and self.blocks:
            return np.concatenate(self.blocks, axis=0), np.concatenate(self.steps).astype(np.int64)
        return self.R[:self.pos], self.S[:self.pos]


def check_budget(*, N: int, h: float, t0: float, every: int, events: bool, row_bytes: int, buffer_bytes: int,
                 budget, what: str = "Moreau-Jean run") -> dict:
    """Estimate the memory of a run before it starts; raise
    :class:`ResourceLimitError` naming the settings that fit when it exceeds
    the budget.  Returns the estimate (bytes) and the budget."""
    limit, desc = resolve_memory_budget(budget)
    rows = ChunkRecorder.rows_needed(N, every, events)
    need = rows * row_bytes + buffer_bytes
    est = {"estimate_bytes": int(need), "budget_bytes": int(limit), "record_rows": int(rows),
           "row_bytes": int(row_bytes), "buffer_bytes": int(buffer_bytes)}
    if need <= limit:
        return est
    room = (limit - buffer_bytes) // row_bytes - 1
    fits: dict[str, float] = {}
    if room >= 1:
        fits["record_every"] = int(-(-N // room))
        fits["t_end"] = t0 + room * every * h
    rec = ("every step" if every == 1 else f"every {every}-th step") if not events else "events"
    alt = []
    if "record_every" in fits:
        k = int(fits["record_every"])
        need_k = ChunkRecorder.rows_needed(N, k, False) * row_bytes + buffer_bytes
        alt.append(f"record_every={k} (--record-every {k}; {_fmt_bytes(need_k)})")
    if not events:
        alt.append('record="events" (--record events: impacts and contact changes only, plus first and last step)')
    if "t_end" in fits:
        alt.append(f"t_end <= {fits['t_end']:.6g} (--t-end)")
    alt.append("a larger memory_budget")
    raise ResourceLimitError(
        f"{what} of {N} steps recording {rec} needs about {_fmt_bytes(need)} ({row_bytes} bytes per recorded "
        f"step, {_fmt_bytes(buffer_bytes)} of chunk buffers) but the memory budget is {_fmt_bytes(limit)} "
        f"({desc}); options that fit: " + "; ".join(alt) + ". Statistics (max gap violation, energy/V increase, "
        "impacts, rest time) stay exact under decimation.",
        diagnostics={**est, "fits": fits})
