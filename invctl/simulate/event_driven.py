"""Event-driven reference simulator for Lagrangian complementarity systems.

An independent code path used to validate the time-stepping: smooth phases
are integrated with a tight-tolerance Runge-Kutta method (scipy DOP853),
with the active contacts enforced as equalities (index-1: accelerations and
multipliers from the contact LCP (7) restricted to the active set); events
are located to machine precision by the integrator's root finder (which sees
a sign change of an event function only between the ends of a step, so a
gap that starts a segment at zero is first watched for opening, see
``gap_tol``):

* an open gap closes (``f_i = 0`` from above): Moreau's impact law (4)/(5)
  is applied with the exact LCP solver, then the contacts that stay closed
  with zero normal velocity are sorted by the contact LCP (7) into active
  (``lam_i > 0``) and releasing ones;
* an active multiplier reaches zero: the contact is released.

Accumulations of impacts (Zeno) are cut when the approach velocity falls
below ``v_rest``: the contact is then made persistent (the remaining
velocity is removed plastically); for the bouncing ball this adds an error
of order ``v_rest^2 / g`` to the rest time.  Laws with discontinuities in
the state (if_else switching) are not handled (their switches are not
located): use smooth laws.
"""
from __future__ import annotations

from typing import Any

import numpy as np
from scipy.integrate import solve_ivp
from scipy.optimize import brentq

from ..contact.mechanics import ContactSystem
from ..contact.lcp import solve_lcp
from ..control.pdplus import FeedbackLaw, zero_input
from ..errors import INTERRUPT_LIKE, RunInterrupted, SimulationFailed, is_interrupt, watch_sigint
from ..results import Status
from .timestepping import ContactTrajectory


def simulate_event_driven(model, q0, v0, t_end: float, *, law: FeedbackLaw | None = None, t0: float = 0.0,
                          gains=None, params=None, rtol: float = 1e-12, atol: float = 1e-12,
                          v_rest: float = 1e-7, max_events: int = 10000, dt_out: float | None = None,
                          potential=None, max_impacts: int | None = None, gap_tol: float = 1e-10) -> ContactTrajectory:
    """Simulate exactly (up to integrator tolerance) from ``(q0, v0)`` to ``t_end``.

    Returns a :class:`ContactTrajectory` (time along the last axis) with ``stats["events"]`` (list of
    ``(t, kind, contact, U_minus, U_plus)``), ``stats["impact_t"]``,
    ``stats["impact_contact"]``, ``stats["impact_pre"]``,
    ``stats["impact_post"]``, ``stats["impact_v_plus"]``. With ``max_impacts`` the run ends at that
    impact (a reference for the first impacts that does not have to get through later Zeno phases).
    ``gap_tol``: a gap that left zero (after an impact or a release) is watched for closing again once it
    has opened by ``gap_tol``; if it falls by ``gap_tol`` first, that is an impact (located ``gap_tol``
    late, i.e. ``gap_tol / |U|`` in time).
    """
    cs = ContactSystem(model)
    law = law or zero_input(potential)
    th = model.theta_values if params is None else np.asarray(params, float)
    kap = np.asarray(law.kappa_values if gains is None else gains, float)
    n, mu = model.n, cs.m_u
    fM, ff, fB = model.function("M"), model.function("f"), model.function("B")
    fuV = law.function(model)
    e = cs.restitution(th)

    def forces(t, q, v):
        u, V = fuV(q, v, t, th, kap)
        F = np.array(ff(q, v, th)).ravel() + np.array(fB(q, th)).reshape(n, model.m) @ np.array(u).ravel()
        return np.array(fM(q, th)), F, float(V)

    def accel(t, q, v, active):
        M, F, _ = forces(t, q, v)
        a0 = np.linalg.solve(M, F)
        lam = np.zeros(mu)
        if active.any():
            W = cs.gradients(q, th)[:, active]
            MiW = np.linalg.solve(M, W)
            D = W.T @ MiW
            w = np.array(cs.f_Wdot_v(q, v, th)).ravel()[active] + W.T @ a0
            la = np.linalg.solve(D, -w)
            lam[active] = la
            a0 = a0 + MiW @ la
        return a0, lam

    def settle(t, q, v, closed):
        """Active set among closed contacts with zero normal velocity: contact LCP (7)."""
        if not closed.any():
            return closed
        M, F, _ = forces(t, q, v)
        a0 = np.linalg.solve(M, F)
        W = cs.gradients(q, th)[:, closed]
        D = W.T @ np.linalg.solve(M, W)
        w = np.array(cs.f_Wdot_v(q, v, th)).ravel()[closed] + W.T @ a0
        sol = solve_lcp(D, w)
        act = np.zeros(mu, bool)
        act[np.flatnonzero(closed)[sol.z > 0]] = True
        return act

    q, v, t = np.asarray(q0, float).copy(), np.asarray(v0, float).copy(), float(t0)
    g0 = cs.gaps(q, th)
    if np.any(g0 < -1e-12):
        raise SimulationFailed(f"event-driven: initial gaps {g0.tolist()} violate f >= 0")
    U0 = cs.gradients(q, th).T @ v
    active = settle(t, q, v, (g0 <= 1e-12) & (np.abs(U0) <= 1e-12))
    # A gap is watched for closing (f_i = 0 from above) only once it is "armed", i.e. clearly open.
    # Right after an impact or a release the gap is zero up to round-off, and its sign at the start of
    # the next segment is noise: if the whole flight to the next impact fits in one integrator step,
    # a start at -1e-18 shows no sign change over that step and the impact is stepped over (which
    # machine's round-off decides). Such a leaving gap is watched instead for rising by gap_tol
    # (then armed) or for falling by gap_tol (a closing without a flight, handled as an impact),
    # both thresholds clearly away from its value at the segment's start.
    armed = (g0 > gap_tol) & ~active
    ts, qs, vs = [t], [q.copy()], [v.copy()]
    events: list = []
    imp: dict[str, list] = {"t": [], "i": [], "pre": [], "post": [], "vplus": []}

    def package(ts, qs, vs):
        """The trajectory of the samples so far (impacts and events up to the last sample)."""
        T, Q, Vv = np.array(ts), np.array(qs), np.array(vs)
        Pz = np.zeros((mu, T.size - 1))
        gaps = np.array([cs.gaps(qq, th) for qq in Q]).reshape(T.size, mu).T
        Un = np.array([cs.gradients(qq, th).T @ vv for qq, vv in zip(Q, Vv)]).reshape(T.size, mu).T
        En, Vl = [], []
        for tt, qq, vv in zip(T, Q, Vv):
            M, _, Vk = forces(tt, qq, vv)
            En.append(0.5 * vv @ M @ vv)
            Vl.append(Vk)
        k = int(np.searchsorted(imp["t"], T[-1], side="right"))
        stats = {"events": [e for e in events if e[0] <= T[-1]], "impact_t": np.array(imp["t"][:k]),
                 "impact_contact": np.array(imp["i"][:k], int), "impact_pre": np.array(imp["pre"][:k]),
                 "impact_post": np.array(imp["post"][:k]), "impact_v_plus": np.array(imp["vplus"][:k]).reshape(-1, n),
                 "Un": Un, "backend": "event-driven"}
        # time along the last axis, as every result type
        return ContactTrajectory(T, Q.T, Vv.T, Pz, np.zeros((mu, T.size - 1), bool), gaps, np.array(En),
                                 np.array(Vl), float("nan"), {"q": list(model.q_names), "gaps": list(cs.names)}, stats)

    with watch_sigint() as sigint:  # notes a Ctrl-C that a compiled callee swallows
        try:
            for _ in range(max_events):
                if sigint.seen:  # a Ctrl-C that CasADi's argument conversion swallowed
                    raise KeyboardInterrupt
                if t >= t_end:
                    break
                act = active.copy()

                def rhs(tt, x, act=act):
                    a, _ = accel(tt, x[:n], x[n:], act)
                    return np.r_[x[n:], a]

                g_start = cs.gaps(q, th)
                evs: list = []
                kinds: list = []
                watch: list[tuple[Any, int, str]]
                for i in range(mu):
                    if act[i]:
                        def ev(tt, x, i=i, act=act):
                            return accel(tt, x[:n], x[n:], act)[1][i]
                        watch = [(ev, -1, "release")]
                    elif armed[i]:
                        def ev_gap(tt, x, i=i):
                            return float(cs.gaps(x[:n], th)[i])
                        watch = [(ev_gap, -1, "close")]
                    else:
                        up, down = max(g_start[i], 0.0) + gap_tol, min(g_start[i], 0.0) - gap_tol

                        def ev_up(tt, x, i=i, c=up):
                            return float(cs.gaps(x[:n], th)[i]) - c

                        def ev_down(tt, x, i=i, c=down):
                            return float(cs.gaps(x[:n], th)[i]) - c
                        watch = [(ev_up, 1, "arm"), (ev_down, -1, "close")]
                    for fn, direction, kind in watch:
                        fn.terminal, fn.direction = True, direction
                        evs.append(fn)
                        kinds.append((kind, i))
                t_eval = None
                if dt_out:
                    t_eval = np.arange(t, t_end, dt_out)[1:]
                leaving = ~act & ~armed
                sol = solve_ivp(rhs, (t, t_end), np.r_[q, v], method="DOP853", rtol=rtol, atol=atol, events=evs,
                                t_eval=t_eval, dense_output=bool(leaving.any()))
                if sol.status == -1:
                    raise SimulationFailed(f"event-driven: integrator failed at t = {sol.t[-1]:.6g}: {sol.message}")
                t_seg = np.asarray(sol.t, float).ravel()
                if t_seg.size:  # (scipy returns lists when t_eval has no point in a short segment)
                    y_seg = np.asarray(sol.y, float).reshape(2 * n, t_seg.size)
                    ts.extend(t_seg.tolist())
                    qs.extend(y_seg[:n].T)
                    vs.extend(y_seg[n:].T)
                if sol.status == 0:
                    t = t_end
                    break
                fired = [k for k in range(len(evs)) if sol.t_events[k].size]
                if not fired:
                    raise SimulationFailed(f"event-driven: terminated at t = {sol.t[-1]:.6g} without an event")
                k_ev = min(fired, key=lambda k: sol.t_events[k][0])
                kind, i_ev = kinds[k_ev]
                t, ye = float(sol.t_events[k_ev][0]), sol.y_events[k_ev][0]
                if kind == "close" and leaving[i_ev]:
                    t, ye = _first_closing(sol, i_ev, t, lambda x, i=i_ev: float(cs.gaps(x[:n], th)[i]))
                q, v = ye[:n].copy(), ye[n:].copy()
                if kind == "arm":
                    armed[i_ev] = True
                    continue
                if kind == "release":
                    active[i_ev] = False
                    events.append((t, "release", i_ev, 0.0, 0.0))
                    continue
                # impact(s)
                g = cs.gaps(q, th)
                W = cs.gradients(q, th)
                U = W.T @ v
                closed = g <= gap_tol + 1e-9 * np.abs(U)
                closed[i_ev] = True
                inv = closed & (U <= 1e-14)
                ee = e.copy()
                slow = inv & (np.abs(U) < v_rest)
                ee[slow] = 0.0
                res = cs.impact(q, v, theta=th, e=ee, involved=inv)
                Up = W.T @ res.v_plus
                for j in np.flatnonzero(inv):
                    events.append((t, "impact", int(j), float(U[j]), float(Up[j])))
                    if res.p[j] > 0 and U[j] < -v_rest:
                        imp["t"].append(t)
                        imp["i"].append(int(j))
                        imp["pre"].append(float(U[j]))
                        imp["post"].append(float(Up[j]))
                        imp["vplus"].append(res.v_plus.copy())
                v = res.v_plus
                ts.append(t)
                qs.append(q.copy())
                vs.append(v.copy())
                Up = W.T @ v
                active = settle(t, q, v, closed & (np.abs(Up) <= max(1e-12, 1e-9 * np.abs(U).max(initial=0))))
                armed[closed | active] = False
                if max_impacts is not None and len(imp["t"]) >= max_impacts:
                    break
            else:
                raise SimulationFailed(f"event-driven: more than {max_events} events before t_end = {t_end}",
                                       partial=(np.array(ts), np.array(qs).T, np.array(vs).T))
        except INTERRUPT_LIKE as exc:
            if not (is_interrupt(exc) or sigint.seen):
                raise
            k = min(len(ts), len(qs), len(vs))  # up to the last event or smooth phase completed
            part = package(ts[:k], qs[:k], vs[:k])
            part.status, part.message = Status.INTERRUPTED, f"interrupted at t = {ts[k - 1]:.6g} of {t_end:g}"
            raise RunInterrupted(f"event-driven simulation interrupted at t = {ts[k - 1]:.6g} of {t_end:g}; the "
                                 "simulated prefix is in exc.partial", partial=part) from None
    return package(ts, qs, vs)


def _first_closing(sol, i, te, gap, samples: int = 64):
    """Where a leaving gap that was caught only at ``-gap_tol`` really closed: the last sign change from
    positive to non-positive of ``gap`` on the step that ends at ``te`` (dense output, located to round-off).
    A flight that never rose above zero (a closing without a flight) keeps ``te``."""
    ts = sol.sol.ts
    ta = float(ts[ts < te].max(initial=ts[0]))
    grid = np.linspace(ta, te, samples + 1)
    g = np.array([gap(sol.sol(tt)) for tt in grid])
    pos = np.flatnonzero(g > 0)
    if not pos.size:
        return te, sol.sol(te)
    j = pos[-1]
    tr = brentq(lambda tt: gap(sol.sol(tt)), grid[j], grid[j + 1], xtol=1e-16, rtol=4 * np.finfo(float).eps)
    return float(tr), sol.sol(tr)
