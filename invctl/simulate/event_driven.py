"""Event-driven reference simulator for Lagrangian complementarity systems.

An independent code path used to validate the time-stepping: smooth phases
are integrated with a tight-tolerance Runge-Kutta method (scipy DOP853),
with the active contacts enforced as equalities (index-1: accelerations and
multipliers from the contact LCP (7) restricted to the active set); events
are located to machine precision by the integrator's root finder:

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

import numpy as np
from scipy.integrate import solve_ivp

from ..contact.mechanics import ContactSystem
from ..contact.lcp import solve_lcp
from ..control.pdplus import FeedbackLaw, zero_input
from ..errors import INTERRUPT_LIKE, RunInterrupted, SimulationFailed, is_interrupt, watch_sigint
from .timestepping import ContactTrajectory

__all__ = ["simulate_event_driven"]


def simulate_event_driven(model, q0, v0, t_end: float, *, law: FeedbackLaw | None = None, t0: float = 0.0,
                          gains=None, params=None, rtol: float = 1e-12, atol: float = 1e-12,
                          v_rest: float = 1e-7, max_events: int = 10000, dt_out: float | None = None,
                          potential=None, max_impacts: int | None = None) -> ContactTrajectory:
    """Simulate exactly (up to integrator tolerance) from ``(q0, v0)`` to ``t_end``.

    Returns a :class:`ContactTrajectory` (time along the last axis) with ``stats["events"]`` (list of
    ``(t, kind, contact, U_minus, U_plus)``), ``stats["impact_t"]``,
    ``stats["impact_contact"]``, ``stats["impact_pre"]``,
    ``stats["impact_post"]``, ``stats["impact_v_plus"]``. With ``max_impacts`` the run ends at that
    impact (a reference for the first impacts that does not have to get through later Zeno phases).
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
    ts, qs, vs = [t], [q.copy()], [v.copy()]
    events = []
    imp = {"t": [], "i": [], "pre": [], "post": [], "vplus": []}

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

                evs = []
                for i in range(mu):
                    if act[i]:
                        def ev(tt, x, i=i, act=act):
                            return accel(tt, x[:n], x[n:], act)[1][i]
                    else:
                        def ev(tt, x, i=i):
                            return float(cs.gaps(x[:n], th)[i])
                    ev.terminal = True
                    ev.direction = -1
                    evs.append(ev)
                t_eval = None
                if dt_out:
                    t_eval = np.arange(t, t_end, dt_out)[1:]
                sol = solve_ivp(rhs, (t, t_end), np.r_[q, v], method="DOP853", rtol=rtol, atol=atol, events=evs,
                                t_eval=t_eval, dense_output=False)
                if sol.status == -1:
                    raise SimulationFailed(f"event-driven: integrator failed at t = {sol.t[-1]:.6g}: {sol.message}")
                if sol.t.size:
                    ts.extend(sol.t.tolist())
                    qs.extend(sol.y[:n].T)
                    vs.extend(sol.y[n:].T)
                if sol.status == 0:
                    t = t_end
                    break
                hit = [i for i in range(mu) if sol.t_events[i].size and
                       (sol.t_events[i][0] > t or len(sol.t_events[i]) > 1 or not np.isclose(sol.t_events[i][0], t))]
                if not hit:
                    raise SimulationFailed(f"event-driven: terminated at t = {sol.t[-1]:.6g} without an event")
                te = min(sol.t_events[i][-1] if sol.t_events[i][0] <= t else sol.t_events[i][0] for i in hit)
                i_ev = [i for i in hit if np.isclose(min(sol.t_events[i][sol.t_events[i] > t]
                                                         if np.any(sol.t_events[i] > t) else sol.t_events[i]),
                                                     te, rtol=0, atol=1e-13)]
                ye = sol.y_events[i_ev[0]][-1] if sol.y_events[i_ev[0]].shape[0] else sol.y[:, -1]
                t, q, v = float(te), ye[:n].copy(), ye[n:].copy()
                if act[i_ev[0]]:
                    active[i_ev[0]] = False
                    events.append((t, "release", i_ev[0], 0.0, 0.0))
                    continue
                # impact(s)
                g = cs.gaps(q, th)
                W = cs.gradients(q, th)
                U = W.T @ v
                closed = g <= 1e-10 + 1e-9 * np.abs(U)
                inv = closed & (U <= 1e-14)
                ee = e.copy()
                slow = inv & (np.abs(U) < v_rest)
                ee[slow] = 0.0
                res = cs.impact(q, v, theta=th, e=ee, involved=inv)
                Up = W.T @ res.v_plus
                for i in np.flatnonzero(inv):
                    events.append((t, "impact", int(i), float(U[i]), float(Up[i])))
                    if res.p[i] > 0 and U[i] < -v_rest:
                        imp["t"].append(t)
                        imp["i"].append(int(i))
                        imp["pre"].append(float(U[i]))
                        imp["post"].append(float(Up[i]))
                        imp["vplus"].append(res.v_plus.copy())
                v = res.v_plus
                ts.append(t)
                qs.append(q.copy())
                vs.append(v.copy())
                Up = W.T @ v
                active = settle(t, q, v, closed & (np.abs(Up) <= max(1e-12, 1e-9 * np.abs(U).max(initial=0))))
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
            part.status, part.message = "interrupted", f"interrupted at t = {ts[k - 1]:.6g} of {t_end:g}"
            raise RunInterrupted(f"event-driven simulation interrupted at t = {ts[k - 1]:.6g} of {t_end:g}; the "
                                 "simulated prefix is in exc.partial", partial=part) from None
    return package(ts, qs, vs)
