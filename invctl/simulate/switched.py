"""Exact simulation of the switched position/force loop against a stiff wall (002 Sect. 4, 5.4).

The closed loop (:class:`invctl.control.switched.ClosedLoop`) is linear in every
mode, and its inputs (the user's profiles) are piecewise polynomials carried
as Taylor states, so between events the solution is ``S(t) = expm(A (t - t_k)) S_k``
exactly.  The propagation

* samples each window with one matrix exponential and ``log2 K`` matrix
  products (:func:`invctl.reference.gluing.powers_apply`) -- no Python loop over
  steps; the step resolves the fastest oscillation of the plant block
  (``samples_per_period`` per period), so stiff walls (``ke`` up to 1e9 and more)
  cost samples, never stability;
* locates every switch (``x = 0``, ``x_t = 0``) as a root of the exact solution
  (Brent's method on ``c . expm(A tau) S_k``), including grazing double
  crossings between samples (checked via sign changes of the velocity);
* resolves a touch with zero velocity by the Filippov rule: if the free-motion
  vector field pushes into the wall and the contact field pushes out, the state
  slides on ``x = 0`` (held) until one of them turns.

Time events (knots of the profiles, start and end of the reference contact
phases, App. A) are known in advance and handled exactly as well.
"""
from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import expm
from scipy.optimize import brentq, minimize_scalar

from ..control.switched import ClosedLoop
from ..errors import INTERRUPT_LIKE, ParameterError, RunInterrupted, SimulationFailed, is_interrupt, watch_sigint
from ..results import Status, Trajectory, plot_target
from ..reference.gluing import powers_apply

EV_ENTER, EV_LEAVE, EV_SLIDE, EV_UNSLIDE = 1, -1, 2, -2


@dataclass
class SwitchedSimulation(Trajectory):
    """Result of :func:`simulate_switched`: dense exact samples plus events and scores.

    Arrays share the time axis ``t`` (event instants appear twice, before and after
    the switch).  ``wall`` marks samples in contact with the wall, ``ctrl`` those
    where the controller is in force mode (3b), ``intended`` the reference contact
    phases.  ``xt, vt`` are empty for the rigid plant.
    """

    t: np.ndarray
    x: np.ndarray
    v: np.ndarray
    xt: np.ndarray
    vt: np.ndarray
    xd: np.ndarray
    xd_dot: np.ndarray
    Fd: np.ndarray
    Fd_desired: np.ndarray
    Fe: np.ndarray
    Fc: np.ndarray
    wall: np.ndarray
    ctrl: np.ndarray
    intended: np.ndarray
    event_t: np.ndarray
    event_surface: np.ndarray
    event_kind: np.ndarray
    peak_force: float
    contact_phases: int
    bounces: int
    force_rms_error: float
    wall_time: float
    label: str = ""
    meta: dict = field(default_factory=dict)
    status: str = "ok"
    message: str = ""
    stats: dict = field(default_factory=dict)

    _KIND = "SwitchedSimulation"
    _ARRAYS = ("t", "x", "v", "xt", "vt", "xd", "xd_dot", "Fd", "Fd_desired", "Fe", "Fc", "wall", "ctrl",
               "intended", "event_t", "event_surface", "event_kind", "peak_force", "contact_phases", "bounces",
               "force_rms_error", "wall_time")

    @property
    def n_events(self) -> int:
        return int(self.event_t.size)

    @property
    def q(self) -> np.ndarray:
        """The position ``x`` as ``(1, len(t))`` (``v`` is its velocity; the wrist's tip is ``xt, vt``)."""
        return np.atleast_2d(self.x)

    y = q  # the output is the position

    @property
    def u(self) -> np.ndarray:
        """The actuator force ``F_c``, ``(1, len(t))``."""
        return np.atleast_2d(self.Fc)

    @property
    def lam(self) -> np.ndarray:
        """The contact force ``F_e``, ``(1, len(t))``."""
        return np.atleast_2d(self.Fe)

    def sample(self, t) -> dict:
        """``x, Fe, Fd`` (and ``xt, vt``) at times ``t``, and the common fields ``q, v, u, y, lam`` as ``(rows,
        len(t))``: linear interpolation between the exact samples (which include both sides of every event)."""
        t = np.atleast_1d(np.asarray(t, float))
        keys = ["x", "Fe", "Fd"] + (["xt", "vt"] if self.xt.size else [])
        own = {k: np.interp(t, self.t, getattr(self, k)) for k in keys}
        return {**Trajectory.sample(self, t), **own}

    def contact_intervals(self) -> list[tuple[float, float]]:
        """Intervals of wall contact ``[(t_on, t_off), ...]``."""
        return _intervals(self.t, self.wall)

    def summary(self) -> str:
        return (f"{self.label or 'switched simulation'}: t in [{self.t[0]:.4g}, {self.t[-1]:.4g}] s, "
                f"{self.t.size} samples, {self.n_events} events\n"
                f"  peak contact force {self.peak_force:.6g} N, contact phases {self.contact_phases}, "
                f"bounces {self.bounces}, force RMS error in intended contact {self.force_rms_error:.6g} N\n"
                f"  wall time {self.wall_time:.3g} s")

    def to_dict(self) -> dict:
        return {"status": self.status, "success": self.success, "message": self.message,
                "peak_force": self.peak_force, "bounces": self.bounces, "contact_phases": self.contact_phases,
                "force_rms_error": self.force_rms_error, "n_events": self.n_events,
                "contact_intervals": self.contact_intervals(), "wall_time": self.wall_time,
                "t_end": float(self.t[-1]), "label": self.label}

    def to_csv(self, path) -> None:
        """Sampled signals as CSV (one row per sample; events and scores are in :meth:`to_npz`)."""
        cols = ["t", "x", "v"] + (["xt", "vt"] if self.xt.size else []) + \
            ["xd", "xd_dot", "Fd", "Fd_desired", "Fe", "Fc", "wall", "ctrl", "intended"]
        data = np.column_stack([np.asarray(getattr(self, c), float) for c in cols])
        np.savetxt(path, data, delimiter=",", header=",".join(cols), comments="", fmt="%.17g")

    def plot(self, ax=None, *, path=None, title: str | None = None, **options):
        """Position and force against desired force, contact phases shaded (``ax``: two axes to draw in;
        ``path``: save the figure there too). Returns the figure."""
        from ..plot import save
        from ..plot.switched import plot_simulation

        ax, path = plot_target(ax, path)
        fig = plot_simulation(self, axes=ax, title=title)[0].figure
        save(fig, path)
        return fig


def _intervals(t, mask) -> list[tuple[float, float]]:
    mask = np.asarray(mask, bool)
    if mask.size == 0:
        return []
    d = np.diff(mask.astype(int))
    on = [int(i) for i in np.flatnonzero(d == 1) + 1]
    off = [int(i) for i in np.flatnonzero(d == -1) + 1]
    if mask[0]:
        on = [0] + on
    if mask[-1]:
        off = off + [mask.size - 1]
    return [(float(t[a]), float(t[b])) for a, b in zip(on, off)]


# ---------------------------------------------------------------------------
class _Engine:
    def __init__(self, loop: ClosedLoop, *, h_max, samples_per_period, max_events, slide_tol, progress,
                 state0=None, x_tol=1e-15):
        self.state0 = state0
        self.x_tol = x_tol
        self.loop = loop
        self.sigint = None  # watch_sigint() of simulate_switched
        self.h_max = h_max
        self.spp = samples_per_period
        self.max_events = max_events
        self.slide_tol = slide_tol
        self.progress = progress
        self._h: dict = {}
        self.modes: list[tuple] = []
        self._mode_id: dict = {}

    def mode_id(self, key) -> int:
        if key not in self._mode_id:
            self._mode_id[key] = len(self.modes)
            self.modes.append(key)
        return self._mode_id[key]

    def step(self, bits, phase, sliding) -> float:
        key = (bits, phase, sliding)
        if key not in self._h:
            A = self.loop.matrix(bits, phase, sliding)
            ev = np.linalg.eigvals(A[:self.loop.np, :self.loop.np])
            h = self.h_max
            w = np.max(np.abs(ev.imag)) if ev.size else 0.0
            if w > 0:
                h = min(h, 2 * math.pi / (self.spp * w))
            lam = np.max(np.abs(ev.real)) if ev.size else 0.0
            if lam > 0:
                h = min(h, 8.0 / lam)
            self._h[key] = h
        return self._h[key]

    # -- constraints of the current mode: (row c, surface j, kind, offset) with c.S + offset > 0 required
    def constraints(self, bits, phase, sliding):
        out = []
        for j, (_, ip, iv, _, _) in enumerate(self.loop.surfaces):
            if j == sliding:
                b0 = tuple(False if i == j else b for i, b in enumerate(bits))
                b1 = tuple(True if i == j else b for i, b in enumerate(bits))
                a0 = self.loop.matrix(b0, phase)[iv]
                a1 = self.loop.matrix(b1, phase)[iv]
                out.append((a0, j, "slide0", 0.0))     # leave to the free side when a0 <= 0
                out.append((-a1, j, "slide1", 0.0))    # leave to the contact side when a1 >= 0
                continue
            c = np.zeros(self.loop.n)
            c[ip] = 1.0 if bits[j] else -1.0
            out.append((c, j, "pos", 0.5 * self.x_tol))
        return out

    def decide(self, S, bits, phase, j, h):
        """New bit (or sliding) of surface ``j`` at a state on it: direction, then Filippov rule."""
        _, ip, iv, _, _ = self.loop.surfaces[j]
        b0 = tuple(False if i == j else b for i, b in enumerate(bits))
        b1 = tuple(True if i == j else b for i, b in enumerate(bits))
        a0 = float(self.loop.matrix(b0, phase)[iv] @ S)
        a1 = float(self.loop.matrix(b1, phase)[iv] @ S)
        v = float(S[iv])
        v_tol = self.slide_tol * max(abs(a0), abs(a1)) * h
        if v > v_tol:
            return b1, -1
        if v < -v_tol:
            return b0, -1
        if a0 <= 0:
            return b0, -1
        if a1 > 0:
            return b1, -1
        return b0, j

    # -- first root of c . S(tau) on (lo, hi] from S at lo (c . S > 0 required, violated at hi)
    @staticmethod
    def root(A, S0, c, lo, hi, offset=0.0):
        f = lambda s: float(c @ (expm(A * s) @ S0)) + offset  # noqa: E731
        flo, fhi = f(lo), f(hi)
        if fhi > 0:
            return None
        if flo <= 0:
            # starting on the surface: move past the initial excursion (g ~ g1 s + g2 s^2 / 2)
            g1 = float(c @ (A @ S0))
            g2 = float(c @ (A @ (A @ S0)))
            if g1 <= 0:
                return lo
            guesses = ([lo + g1 / -g2] if g2 < 0 else []) + list(np.linspace(lo, hi, 34)[1:-1])
            for s in sorted(x for x in guesses if lo < x < hi):
                if f(s) > 0:
                    lo = s
                    break
            else:
                return lo
        return brentq(f, lo, hi, xtol=1e-16 + 1e-13 * (hi - lo), rtol=1e-15)

    def graze(self, A, X, h, cons, k_limit):
        """First grazing double crossing between samples (position on its side at both samples).

        Every interval where the guarded ``g = sgn*x`` has a local minimum (``sgn*v``: - to +) is
        screened with the cubic Hermite interpolant of ``(x, v)`` (error ~ (h w)^4/384 of the
        amplitude for ``h = T/samples_per_period``); intervals whose estimated minimum comes within
        1e-3 of the local amplitude (plus ``x_tol``) of the surface are refined exactly.
        """
        best = None
        s_grid = np.linspace(0.0, 1.0, 17)
        h00 = 2 * s_grid**3 - 3 * s_grid**2 + 1
        h10 = s_grid**3 - 2 * s_grid**2 + s_grid
        h01 = -2 * s_grid**3 + 3 * s_grid**2
        h11 = s_grid**3 - s_grid**2
        for c, j, kind, off in cons:
            if kind != "pos":
                continue
            _, ip, iv, _, _ = self.loop.surfaces[j]
            sgn = c[ip]
            g = sgn * X[:k_limit + 1, ip]
            dg = sgn * X[:k_limit + 1, iv]
            cand = np.flatnonzero((dg[:-1] < 0) & (dg[1:] > 0))
            if not cand.size:
                continue
            g0, g1, d0, d1 = g[cand], g[cand + 1], dg[cand], dg[cand + 1]
            est = (np.outer(g0, h00) + np.outer(h * d0, h10) + np.outer(g1, h01) + np.outer(h * d1, h11)).min(axis=1)
            scale = np.abs(g0) + np.abs(g1) + h * (np.abs(d0) + np.abs(d1))
            flagged = cand[est <= 1e-3 * scale + self.x_tol]
            cv = np.zeros(self.loop.n)
            cv[iv] = sgn
            for k in flagged:
                if best is not None and k * h >= best[0]:
                    break
                tm = self.root(A, X[k], -cv, 0.0, h)  # sgn*v from <0 to >0: root of -sgn*v
                if tm is None:
                    continue
                Sm = expm(A * tm) @ X[k]
                if c @ Sm + off <= 0:
                    tau = self.root(A, X[k], c, 0.0, tm, off)
                    if tau is not None and (best is None or k * h + tau < best[0]):
                        best = (k * h + tau, k, tau, c, j, kind)
                    break
        return best

    def run(self, t0, t_end):
        loop = self.loop
        ref = loop.reference
        t = t0
        S = loop.initial_state(t0)
        if self.state0 is not None:
            S[:loop.np] = self.state0
        phase = bool(ref.phase([t])[0])
        bits = tuple(False for _ in loop.surfaces)
        sliding = -1
        for j, (_, ip, _, _, _) in enumerate(loop.surfaces):
            if S[ip] > 0:
                bits = tuple(True if i == j else b for i, b in enumerate(bits))
        for j, (_, ip, _, _, _) in enumerate(loop.surfaces):
            if S[ip] == 0:
                bits, sl = self.decide(S, bits, phase, j, self.step(bits, phase, -1))
                sliding = sl if sl >= 0 else sliding
        t_events = sorted({x for x in ref.switch_times() + ref.input_breaks(t0, t_end) if t0 < x < t_end})
        t_events.append(t_end)
        T, X_all, M = self.T, self.X, self.M = [], [], []  # kept on the engine: an interruption keeps the prefix
        self.start = (t, S.copy(), self.mode_id((bits, phase, sliding)))
        events = self.events = []
        contact_starts = {a for a, _ in ref.contact_intervals}
        last_report = time.perf_counter()
        stalled = 0
        for te in t_events:
            while t < te:
                if getattr(self.sigint, "seen", False):  # a Ctrl-C swallowed by a compiled callee
                    raise KeyboardInterrupt
                A = loop.matrix(bits, phase, sliding)
                h = self.step(bits, phase, sliding)
                K = int(min(4096, max(1, math.ceil((te - t) / h - 1e-9))))
                tw = min(te, t + K * h)
                h = (tw - t) / K
                E = expm(A * h)
                X = powers_apply(E, S, K)
                if not np.all(np.isfinite(X)):
                    raise SimulationFailed(f"non-finite state at t = {t:.9g} s (mode {bits}, phase {phase})",
                                           partial=self._partial(T, X_all, M))
                mid = self.mode_id((bits, phase, sliding))
                cons = self.constraints(bits, phase, sliding)
                G = np.column_stack([X[1:] @ c + off for c, _, _, off in cons])
                bad = np.flatnonzero(np.any(G <= 0, axis=1))
                k_first = int(bad[0]) + 1 if bad.size else K
                hit = None
                if bad.size:
                    k = k_first
                    for ci, (c, j, kind, off) in enumerate(cons):
                        if G[k - 1, ci] <= 0:
                            tau = self.root(A, X[k - 1], c, 0.0, h, off)
                            tau = 0.0 if tau is None else tau
                            cand = ((k - 1) * h + tau, k - 1, tau, c, j, kind)
                            if hit is None or cand[0] < hit[0]:
                                hit = cand
                g = self.graze(A, X, h, cons, k_first if hit is None else hit[1] + 1)
                if g is not None and (hit is None or g[0] < hit[0]):
                    hit = g
                if hit is None:
                    T.append(t + h * np.arange(K))
                    X_all.append(X[:K])
                    M.append(np.full(K, mid))
                    S = X[K]
                    t = tw
                else:
                    _, k, tau, c, j, kind = hit
                    T.append(t + h * np.arange(k + 1))
                    X_all.append(X[:k + 1])
                    M.append(np.full(k + 1, mid))
                    S = expm(A * tau) @ X[k]
                    t = t + k * h + tau
                    _, ip, iv, _, _ = loop.surfaces[j]
                    T.append(np.array([t]))
                    X_all.append(S[None, :].copy())
                    M.append(np.array([mid]))
                    stalled = stalled + 1 if (k == 0 and tau == 0.0) else 0
                    if kind == "pos":
                        S[ip] = 0.0
                        if stalled >= 2:  # no progress: the excursion is below resolution -> tangential touch
                            S[iv] = 0.0
                        new_bits, sl = self.decide(S, bits, phase, j, h)
                    else:
                        new_bits = tuple((kind == "slide1") if i == j else b for i, b in enumerate(bits))
                        sl = -1
                    if sl >= 0:
                        S[ip] = 0.0
                        S[iv] = 0.0
                        kind_code = EV_SLIDE
                    elif sliding >= 0:
                        kind_code = EV_UNSLIDE
                    else:
                        kind_code = EV_ENTER if new_bits[j] and not bits[j] else EV_LEAVE
                    if new_bits == bits and sl == sliding:
                        # a touch without change of side: step on to avoid re-detecting the same root
                        S[ip] = 0.0
                    bits, sliding = new_bits, sl
                    events.append((t, j, kind_code))
                    if len(events) > self.max_events:
                        raise SimulationFailed(
                            f"more than {self.max_events} switching events by t = {t:.9g} s "
                            "(chattering or Zeno behaviour); raise max_events or check the gains",
                            partial=self._partial(T, X_all, M), diagnostics={"events": len(events)})
                if self.progress and time.perf_counter() - last_report > 2.0:
                    print(f"  switched simulation: t = {t:.5g} / {t_end:.5g} s, {len(events)} events",
                          file=sys.stderr)
                    last_report = time.perf_counter()
            # time event: new input piece, reference phase switch
            S = S.copy()
            S[loop.np + loop.nr:] = ref.taylor_inputs(te)
            if te in contact_starts:
                S = loop.contact_reset(S)
            phase = bool(ref.phase([te])[0])
        T.append(np.array([t]))
        X_all.append(S[None, :])
        M.append(np.array([self.mode_id((bits, phase, sliding))]))
        return np.concatenate(T), np.vstack(X_all), np.concatenate(M), events

    def _partial(self, T, X_all, M):
        if getattr(self, "start", None) is None:
            return None
        k = min(len(T), len(X_all), len(M))  # an interruption may land between the appends of one window
        if k == 0:  # interrupted in the first window: the initial state
            t, S, m = self.start
            return {"t": np.array([t]), "S": S[None, :], "mode": np.array([m])}
        return {"t": np.concatenate(T[:k]), "S": np.vstack(X_all[:k]), "mode": np.concatenate(M[:k])}


def simulate_switched(loop: ClosedLoop, t_end: float, *, t0: float = 0.0, h_max: float = 2e-4,
                      samples_per_period: int = 32, max_events: int = 20000, slide_tol: float = 1e-6,
                      progress: bool = False, label: str = "", meta: dict | None = None,
                      state0=None, x_tol: float = 1e-15) -> SwitchedSimulation:
    """Simulate the switched loop exactly from ``t0`` to ``t_end``.

    Parameters
    ----------
    loop : ClosedLoop
        Plant, controller (3) and glued reference.
    h_max : float
        Largest sampling step (s) of the output and of the switch search.
    samples_per_period : int
        Samples per period of the fastest plant oscillation of the active mode.
    max_events : int
        Abort with :class:`SimulationFailed` (carrying the partial trajectory) after this many switches.
    slide_tol : float
        A touch whose velocity is below ``slide_tol * |a| * h`` is treated as tangential (Filippov rule).
    x_tol : float
        Penetration (m) below which a surface counts as not crossed: positions that only
        reach the wall within round-off (a reference converging onto it) cause no switch.
        Crossings are located at the level ``x_tol/2`` and then projected onto the surface.
    state0 : array, optional
        Initial plant state (default: at rest relative to the reference, ``x = x_d(t0)``, ``x' = x_d'(t0)``).
    """
    if not (t_end > t0):
        raise ParameterError(f"t_end must exceed t0, got t0 = {t0}, t_end = {t_end}")
    if not (h_max > 0 and samples_per_period >= 4):
        raise ParameterError(f"need h_max > 0 and samples_per_period >= 4, got {h_max}, {samples_per_period}")
    w0 = time.perf_counter()
    if state0 is not None:
        state0 = np.asarray(state0, float)
        if state0.shape != (loop.np,) or not np.all(np.isfinite(state0)):
            raise ParameterError(f"state0 must be {loop.np} finite numbers {loop.plant.names}, got {state0}")
    eng = _Engine(loop, h_max=h_max, samples_per_period=samples_per_period, max_events=max_events,
                  slide_tol=slide_tol, progress=progress, state0=state0, x_tol=x_tol)
    try:
        with watch_sigint() as eng.sigint:
            T, S, Mi, events = eng.run(t0, t_end)
            return _result(loop, eng, T, S, Mi, events, t_end, w0, label, meta)
    except INTERRUPT_LIKE as exc:
        if not (is_interrupt(exc) or getattr(eng.sigint, "seen", False)):
            raise
        part = eng._partial(getattr(eng, "T", []), getattr(eng, "X", []), getattr(eng, "M", []))
        sim, t_now = None, t0
        if part is not None:
            t_now = float(part["t"][-1])
            kept = [e for e in getattr(eng, "events", []) if e[0] <= t_now]
            sim = _result(loop, eng, part["t"], part["S"], part["mode"], kept, t_now, w0, label, meta)
            sim.status, sim.message = Status.INTERRUPTED, f"interrupted at t = {t_now:.6g} s of {t_end:g} s"
        raise RunInterrupted(f"switched simulation{' ' + label if label else ''} interrupted at t = {t_now:.6g} s "
                             f"of {t_end:g} s; the simulated prefix is in exc.partial", partial=sim) from None


def _result(loop, eng, T, S, Mi, events, t_end, w0, label, meta) -> SwitchedSimulation:
    """The outputs and scores of the samples ``T, S, Mi`` up to ``t_end``."""
    out = _outputs(loop, eng, T, S, Mi)
    wall, intended = out["wall"], out["intended"]
    peak = _peak_force(loop, eng, T, S, Mi, out["Fe"])
    n_phases = len(_intervals(T, wall))
    n_intended = sum(1 for a, _ in loop.reference.contact_intervals if a < t_end)
    err = out["Fe"] - out["Fd_desired"]
    if np.any(intended):
        dt = np.diff(T)
        seg = intended[:-1] & intended[1:]
        dur = float(np.sum(dt[seg]))
        sq = 0.5 * (err[:-1] ** 2 + err[1:] ** 2)
        rms = math.sqrt(float(np.sum((sq * dt)[seg])) / dur) if dur > 0 else 0.0
    else:
        rms = 0.0
    ev = np.array(events, float).reshape(-1, 3)
    for name, arr in out.items():
        if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
            raise SimulationFailed(f"output {name} has non-finite values", partial=out)
    return SwitchedSimulation(
        t=T, x=out["x"], v=out["v"], xt=out["xt"], vt=out["vt"], xd=out["xd"], xd_dot=out["xd_dot"],
        Fd=out["Fd"], Fd_desired=out["Fd_desired"], Fe=out["Fe"], Fc=out["Fc"], wall=wall, ctrl=out["ctrl"],
        intended=intended, event_t=ev[:, 0], event_surface=ev[:, 1].astype(int), event_kind=ev[:, 2].astype(int),
        peak_force=peak, contact_phases=n_phases, bounces=max(0, n_phases - n_intended), force_rms_error=rms,
        wall_time=time.perf_counter() - w0, label=label, meta=dict(meta or {}),
    )


def _outputs(loop: ClosedLoop, eng: _Engine, T, S, Mi) -> dict:
    n = T.size
    out = {k: np.zeros(n) for k in ("xd", "xd_dot", "Fd", "Fd_desired", "Fe", "Fc")}
    out["wall"] = np.zeros(n, bool)
    out["ctrl"] = np.zeros(n, bool)
    out["intended"] = np.zeros(n, bool)
    for mid, (bits, phase, _sliding) in enumerate(eng.modes):
        sel = Mi == mid
        if not np.any(sel):
            continue
        Ss = S[sel]
        rr = loop.ref_rows(phase)
        for k in ("xd", "xd_dot", "Fd", "Fd_desired"):
            out[k][sel] = Ss @ rr[k]
        out["Fe"][sel] = Ss @ loop.fe_row(bits)
        out["Fc"][sel] = Ss @ loop.fc_row(bits, phase)
        out["wall"][sel] = loop.wall_on(bits)
        out["ctrl"][sel] = loop.ctrl_on(bits)
        out["intended"][sel] = phase
    out["x"] = S[:, 0]
    out["v"] = S[:, 1]
    if loop.np == 4:
        out["xt"], out["vt"] = S[:, 2], S[:, 3]
    else:
        out["xt"], out["vt"] = np.zeros(0), np.zeros(0)
    return out


def _peak_force(loop, eng, T, S, Mi, Fe) -> float:
    """Largest contact force, refined between samples by bounded maximisation of the exact solution."""
    if Fe.size == 0 or not np.any(Fe > 0):
        return float(max(Fe.max(initial=0.0), 0.0))
    k = int(np.argmax(Fe))
    peak = float(Fe[k])
    if 0 < k < T.size - 1 and Mi[k - 1] == Mi[k] == Mi[k + 1]:
        bits, phase, sliding = eng.modes[Mi[k]]
        A = loop.matrix(bits, phase, sliding)
        c = loop.fe_row(bits)
        t_lo, t_hi = T[k - 1], T[k + 1]
        S0 = S[k - 1]
        res = minimize_scalar(lambda s: -float(c @ (expm(A * s) @ S0)), bounds=(0.0, t_hi - t_lo),
                              method="bounded", options={"xatol": 1e-12 * max(1.0, t_hi - t_lo)})
        peak = max(peak, -float(res.fun))
    return peak
