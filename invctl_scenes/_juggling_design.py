"""The recursive impact design of 000 Sect. 4, (29)-(33), for the one-DoF prismatic joint with
clearance (000 Fig. 2(b)) seen as a juggler.

Body 1 (mass ``m1``, position ``q1``, actuated) carries a slot; body 2 (``m2``, ``q2``, the
uncontrolled object) moves in it; gaps ``y1 = f1 = q2 - q1 - l`` and ``y2 = f2 = q1 - q2 + L - l``
(000 Example 3), restitution ``e``; in flight body 2 has a constant acceleration ``a2`` (0 on a
horizontal guide).  One cycle is the impact sequence ``Sigma_1 -> Sigma_2 -> Sigma_1`` of Sect. 4:
right after an impact on ``y1 = 0`` at ``t0`` (state ``q2(t0)``, ``q2'(t0+)``), body 2 flies for
``D0``, is hit by the other wall (``y2 = 0``) with approach speed ``A = y2'(t1-) < 0``, flies for
``D1`` and is hit again by the first wall with ``B = y1'(t2-) < 0``.  The maps (28)-(32) are closed
forms here: in flight ``q2(t0 + s) = q2 + q2' s + a2 s^2 / 2``; an impact on ``y_i = 0`` with approach
speed ``U < 0`` changes body 2's velocity by ``-/+ (1 + e) U m1 / (m1 + m2)`` (Newton's law (4) with
the Delassus number ``1/m1 + 1/m2``) and body 1's by ``+/- (1 + e) U m2 / (m1 + m2)``.

* **Step 2** ((33)): for a desired post-impact state ``(q2d, v2d)`` at ``t2`` and flight times
  ``(D0, D1)``, the position equation gives body 2's velocity between the impacts, then ``A`` and
  ``B`` follow linearly.  They must be negative (a wall can only push body 2 away from itself): step 2
  *fails* when no ``(D0, D1)`` in the search window gives ``A < 0`` and ``B < 0`` -- for instance a
  body 2 moving left (``q2'(t0+) <= 0``) cannot be brought to the right of its start within one
  cycle ("more intermediate collisions may be needed", 000 after (33)).
* **Step 3**: body 1's trajectory on each flight, as the gap it keeps: on ``[t0, t1]`` ``y2`` goes
  from ``L - 2l`` (slope ``y2'(t0+)``) to the middle of the slot at rest relative to body 2, stays
  there, and closes to ``0`` with slope ``A`` at ``t1``; the same for ``y1`` on ``[t1, t2]`` (from
  ``y1'(t1+) = e A`` to ``B``).  The two transitions are Hermite cubics short enough to be monotone
  (Fritsch-Carlson: a slope at most three times the secant), ``tau = m1 q1''`` plus feedback.
* **Step 4**: viability, ``0 < y1, y2`` strictly between the planned impacts, checked on the pieces.

Among the flight times that pass steps 2 and 4, :func:`design_cycle` takes the pair with the smallest
peak relative acceleration of body 1 (a smooth plan); :func:`design`
a sequence of cycles towards a final target, :func:`juggling_plan_law` turns a plan into a compiled
:class:`~invctl.control.pdplus.FeedbackLaw` (body 1 makes the gap follow the plan), :func:`plan_vs_run`
compares a simulation with the plan.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import casadi as ca
import numpy as np

from invctl.control.pdplus import FeedbackLaw
from invctl.errors import JugglingInfeasible, ParameterError

__all__ = ["Juggler", "JugglerState", "Flight", "Cycle", "JugglingPlan", "design_cycle", "design",
           "juggling_plan_law", "plan_vs_run"]


@dataclass(frozen=True)
class Juggler:
    """Data of the one-DoF juggler (module docstring)."""

    m1: float
    m2: float
    l: float
    L: float
    e: float
    a2: float = 0.0

    def __post_init__(self):
        bad = [k for k in ("m1", "m2") if not getattr(self, k) > 0]
        if bad or not self.L > 2 * self.l or not 0 <= self.e <= 1:
            raise ParameterError(f"Juggler: need m1, m2 > 0, L > 2 l and e in [0, 1], got {self}")

    @property
    def clearance(self) -> float:
        return self.L - 2 * self.l

    def kick(self, U: float) -> tuple[float, float]:
        """Velocity changes ``(dv1, dv2)`` of an impact on ``y1 = 0`` with approach speed ``U < 0``
        (Newton's law (4); for ``y2 = 0`` both change sign)."""
        M = self.m1 + self.m2
        return (1 + self.e) * U * self.m2 / M, -(1 + self.e) * U * self.m1 / M


@dataclass(frozen=True)
class JugglerState:
    """State right after an impact on ``y1 = 0`` (``y1'(t0+) = v2 - v1 >= 0``)."""

    t: float
    q1: float
    v1: float
    q2: float
    v2: float


def _hermite(y0, dy0, y1, dy1, T):
    """Ascending coefficients of the cubic on ``[0, T]`` with the given end values and slopes."""
    c2 = (3 * (y1 - y0) - (2 * dy0 + dy1) * T) / T**2
    c3 = (2 * (y0 - y1) + (dy0 + dy1) * T) / T**3
    return np.array([y0, dy0, c2, c3])


@dataclass(frozen=True)
class Flight:
    """A flight of body 2 between two impacts and the gap body 1 keeps meanwhile.

    ``wall`` is the gap closed at its end (2: ``y = y2 = q1 - q2 + L - l``, 1: ``y = y1 = q2 - q1 - l``);
    ``pieces`` are ``(s0, cubic coefficients in s - s0)`` over ``s = t - t0`` in ``[0, D]``.
    """

    t0: float
    q2: float
    v2: float
    D: float
    wall: int
    pieces: tuple

    def gap(self, s):
        """``(y, y', y'')`` at ``s`` (numpy)."""
        s = np.asarray(s, float)
        out = [np.zeros_like(s) for _ in range(3)]
        for k, (s0, c) in enumerate(self.pieces):
            end = self.pieces[k + 1][0] if k + 1 < len(self.pieces) else np.inf
            m = (s >= s0) & (s < end)
            x = s[m] - s0
            out[0][m] = c[0] + c[1] * x + c[2] * x**2 + c[3] * x**3
            out[1][m] = c[1] + 2 * c[2] * x + 3 * c[3] * x**2
            out[2][m] = 2 * c[2] + 6 * c[3] * x
        return out


def _profile(y0, dy0, y_end, dy_end, D, mid):
    """Pieces: monotone cubic from ``(y0, dy0)`` to ``(mid, 0)``, rest at ``mid``, monotone cubic to
    ``(y_end, dy_end)`` at ``D``."""
    Ta = D / 3 if dy0 == 0 else min(D / 3, 3 * abs(mid - y0) / abs(dy0))
    Tb = D / 3 if dy_end == 0 else min(D / 3, 3 * abs(mid - y_end) / abs(dy_end))
    return ((0.0, _hermite(y0, dy0, mid, 0.0, Ta)), (Ta, np.array([mid, 0.0, 0.0, 0.0])),
            (D - Tb, _hermite(mid, 0.0, y_end, dy_end, Tb)))


@dataclass(frozen=True)
class Cycle:
    """One designed cycle ``Sigma_1 -> Sigma_2 -> Sigma_1``.

    Attributes
    ----------
    start, end : JugglerState
        Post-impact states at ``t0`` and ``t2`` (``end`` is the designed one).
    D0, D1, A, B : float
        The fictitious inputs of step 2: flight times and approach speeds ``y2'(t1-)``, ``y1'(t2-)``.
    flights : (Flight, Flight)
        Step 3 on ``[t0, t1]`` and ``[t1, t2]``.
    impact1 : tuple
        ``(t1, q2(t1), v2(t1+), q1(t1), v1(t1+))``.
    peak_acceleration : float
        Largest ``|y''|`` of the plan (the selection criterion).
    """

    start: JugglerState
    end: JugglerState
    D0: float
    D1: float
    A: float
    B: float
    flights: tuple
    impact1: tuple
    peak_acceleration: float


@dataclass
class JugglingPlan:
    """Cycles in sequence and a final flight (``hold``) bringing body 2 to the middle of the slot at
    rest relative to body 1."""

    juggler: Juggler
    cycles: list = field(default_factory=list)
    hold: Flight | None = None

    @property
    def t_end(self) -> float:
        return self.cycles[-1].end.t if self.cycles else 0.0

    def impact_table(self) -> list:
        """Planned impacts: ``(t, wall, q2, v2 after)``."""
        rows = []
        for c in self.cycles:
            rows.append((c.impact1[0], 2, c.impact1[1], c.impact1[2]))
            rows.append((c.end.t, 1, c.end.q2, c.end.v2))
        return rows


def _flight(j: Juggler, q, v, s):
    return q + v * s + 0.5 * j.a2 * s**2, v + j.a2 * s


def _viable(j: Juggler, f: Flight, samples: int = 400) -> bool:
    y = f.gap(np.linspace(0.0, f.D, samples + 2)[1:-1])[0]
    return bool(np.all(y > 0) and np.all(y < j.clearance))


def _peak(pieces, D) -> float:
    """Largest ``|y''|`` of piecewise cubics (linear ``y''`` per piece: its ends)."""
    out = 0.0
    for k, (s0, c) in enumerate(pieces):
        T = (pieces[k + 1][0] if k + 1 < len(pieces) else D) - s0
        out = max(out, abs(2 * c[2]), abs(2 * c[2] + 6 * c[3] * T))
    return out


def _cycle(j: Juggler, st: JugglerState, q2d: float, v2d: float, D0: float, D1: float, *, check: bool = True):
    """Steps 2-4 for fixed flight times: ``(Cycle, None)``, or ``(None, "step2" | "step4")``."""
    M = j.m1 + j.m2
    k = (1 + j.e) * j.m1 / M
    q2_t1, v2_t1m = _flight(j, st.q2, st.v2, D0)
    w = (q2d - q2_t1 - 0.5 * j.a2 * D1**2) / D1             # body 2 between the impacts (position equation)
    A = (w - v2_t1m) / k                                     # Sigma_2: v2+ = v2- + (1 + e) A m1 / M
    B = (w + j.a2 * D1 - v2d) / k                            # Sigma_1: v2+ = v2- - (1 + e) B m1 / M
    if not (A < 0 and B < 0):
        return None, "step2"
    mid = 0.5 * j.clearance
    f0 = Flight(st.t, st.q2, st.v2, D0, 2, _profile(j.clearance, st.v1 - st.v2, 0.0, A, D0, mid))
    f1 = Flight(st.t + D0, q2_t1, w, D1, 1, _profile(j.clearance, j.e * A, 0.0, B, D1, mid))
    if check and not (_viable(j, f0) and _viable(j, f1)):
        return None, "step4"
    v1_t1p = (v2_t1m + A) - (1 + j.e) * A * j.m2 / M         # y2' = v1 - v2, then the kick of Sigma_2
    q2_t2, v2_t2m = _flight(j, q2_t1, w, D1)
    dv1, dv2 = j.kick(B)
    end = JugglerState(st.t + D0 + D1, q2_t2 - j.l, v2_t2m - B + dv1, q2_t2, v2_t2m + dv2)
    peak = max(_peak(f0.pieces, D0), _peak(f1.pieces, D1))
    return Cycle(st, end, D0, D1, A, B, (f0, f1), (st.t + D0, q2_t1, w, q2_t1 - (j.L - j.l), v1_t1p), peak), None


def design_cycle(j: Juggler, st: JugglerState, q2d: float, v2d: float, *, durations=None, window=(1e-3, 2.0),
                 grid: int = 60) -> Cycle:
    """One cycle from ``st`` to the post-impact state ``(q2d, v2d)`` (module docstring).

    Parameters
    ----------
    durations : (D0, D1), optional
        Fixed flight times; by default the pairs of a ``grid`` x ``grid`` log-spaced search over
        ``window`` x ``window`` (seconds) are tried and the smoothest viable one is kept.

    Raises
    ------
    JugglingInfeasible
        Step 2 fails (no flight times give both approach speeds negative) or step 4 fails (every
        solution of step 2 leaves the slot between the impacts); ``diagnostics`` says which.
    """
    if not (st.v2 - st.v1 >= -1e-12):
        raise ParameterError(f"design_cycle: the start must follow an impact on y1 = 0 (y1' = v2 - v1 >= 0), "
                             f"got v1 = {st.v1}, v2 = {st.v2}")
    pairs = [tuple(durations)] if durations is not None else [
        (a, b) for a in np.geomspace(window[0], window[1], grid) for b in np.geomspace(window[0], window[1], grid)]
    cands = [c for c in (_cycle(j, st, q2d, v2d, D0, D1, check=False)[0] for D0, D1 in pairs) if c is not None]
    n_step2 = len(pairs) - len(cands)
    for c in sorted(cands, key=lambda c: c.peak_acceleration):      # step 4 on the smoothest first
        if _viable(j, c.flights[0]) and _viable(j, c.flights[1]):
            return c
    diag = {"start": st, "target": (q2d, v2d), "window": window, "pairs": len(pairs), "step2": n_step2,
            "step4": len(cands)}
    if not cands:
        why = ("body 2 leaves the first wall moving towards it (q2'(t0+) <= 0) and the target lies ahead: the "
               "second wall can only push it back" if st.v2 <= 0 and q2d > st.q2 else
               "the velocity changes needed have the wrong sign for the walls that would produce them")
        raise JugglingInfeasible(
            f"000 (33), step 2 fails: no flight times in {window} s reach q2 = {q2d:.6g}, q2' = {v2d:.6g} after the "
            f"impacts Sigma_1 -> Sigma_2 -> Sigma_1 from q2 = {st.q2:.6g}, q2' = {st.v2:.6g} ({why}); more "
            "intermediate collisions are needed: add cycles, or change the target", diagnostics=diag)
    raise JugglingInfeasible(
        f"000 Sect. 4, step 4 fails: {len(cands)} flight-time pairs solve step 2 for q2 = {q2d:.6g}, "
        f"q2' = {v2d:.6g}, but on every one body 1 would leave the slot between the impacts; widen the window or "
        "add cycles", diagnostics=diag)


def design(j: Juggler, start: JugglerState, targets: Sequence[tuple], *, hold_time: float = 0.2,
           **kw) -> JugglingPlan:
    """Cycles through ``targets`` (``(q2d, v2d)`` post-impact states, one per cycle), each designed from
    the previous designed end (000's recursion), then a hold flight of ``hold_time``.

    Raises
    ------
    JugglingInfeasible
        A cycle fails (message as in :func:`design_cycle`, with its index); ``partial`` is the plan of the
        cycles before it.
    """
    plan = JugglingPlan(j)
    st = start
    for k, (q2d, v2d) in enumerate(targets):
        try:
            cyc = design_cycle(j, st, float(q2d), float(v2d), **kw)
        except JugglingInfeasible as exc:
            raise JugglingInfeasible(f"cycle {k + 1} of {len(targets)}: {exc}", partial=plan,
                                     diagnostics={**exc.diagnostics, "cycle": k + 1}) from exc
        plan.cycles.append(cyc)
        st = cyc.end
    if hold_time > 0:
        mid = 0.5 * j.clearance
        dy0 = st.v2 - st.v1
        Ta = hold_time if dy0 == 0 else min(hold_time, 3 * mid / abs(dy0))
        plan.hold = Flight(st.t, st.q2, st.v2, np.inf, 1, ((0.0, _hermite(0.0, dy0, mid, 0.0, Ta)),
                                                          (Ta, np.array([mid, 0.0, 0.0, 0.0]))))
    return plan


def _gap_sx(pieces, s):
    """``(y, y', y'')`` of piecewise cubics at the SX time ``s`` (straight-line ``if_else``)."""
    def cubic(c, x):
        return (c[0] + c[1] * x + c[2] * x**2 + c[3] * x**3, c[1] + 2 * c[2] * x + 3 * c[3] * x**2,
                2 * c[2] + 6 * c[3] * x)

    s0, c = pieces[-1]
    y = cubic(c, s - s0)
    for k in range(len(pieces) - 2, -1, -1):
        s0, c = pieces[k]
        inside = s < pieces[k + 1][0]
        y = tuple(ca.if_else(inside, a, b) for a, b in zip(cubic(c, s - s0), y))
    return y


def _reference(plan: JugglingPlan, t):
    """The planned gap at the SX time ``t``: ``(wall, y, y', y'')`` of the active flight (``wall`` 2:
    ``y = y2``, 1: ``y = y1``)."""
    flights = [f for c in plan.cycles for f in c.flights] + ([plan.hold] if plan.hold is not None else [])
    refs = [(f.t0, ca.SX(float(f.wall)), *_gap_sx(f.pieces, t - f.t0)) for f in flights]
    out = refs[-1][1:]
    for k in range(len(refs) - 2, -1, -1):
        inside = t < refs[k + 1][0]
        out = tuple(ca.if_else(inside, x, y) for x, y in zip(refs[k][1:], out))
    return out


def juggling_plan_law(model, plan: JugglingPlan, *, Kp: float, Kv: float, body1: int = 0,
                      body2: int = 1) -> FeedbackLaw:
    """The plan as a compiled law (step 3): body 1 makes the gap of the active flight follow its planned
    profile, ``y'' = y_ref'' + Kp (y_ref - y) + Kv (y_ref' - y')`` with the measured gap and body 2's
    free-flight acceleration ``f_2 / m_2``, i.e. ``tau = m1 q1''_des - f_1``.  The impacts then happen at
    the planned times with the planned approach speeds ``A``, ``B`` (the fictitious inputs of step 2)
    whatever small errors body 2 has accumulated; those are not corrected within the plan (000's
    recursion would re-plan from the measured post-impact state).  ``B`` must be ``e_body1``."""
    if not plan.cycles:
        raise ParameterError("juggling_plan_law: the plan has no cycles")
    j = plan.juggler

    def build(model, t, kappa):
        wall, yr, dyr, ddyr = _reference(plan, t)
        q1, q2, v1, v2 = model.q[body1], model.q[body2], model.v[body1], model.v[body2]
        a2 = model.f[body2] / model.M[body2, body2]
        is2 = wall > 1.5
        y = ca.if_else(is2, q1 - q2 + j.L - j.l, q2 - q1 - j.l)
        dy = ca.if_else(is2, v1 - v2, v2 - v1)
        ydd = ddyr + kappa[0] * (yr - y) + kappa[1] * (dyr - dy)
        a1 = ca.if_else(is2, a2 + ydd, a2 - ydd)
        return ca.vertcat(model.M[body1, body1] * a1 - model.f[body1]), None

    return FeedbackLaw("juggling_design", ("Kp", "Kv"), (float(Kp), float(Kv)), build,
                       {"lyapunov": False, "juggling_plan": plan})


def plan_vs_run(plan: JugglingPlan, tr, *, body2: int = 1, walls=(0, 1)) -> dict:
    """Planned impacts against those of a simulation ``tr`` (:class:`~invctl.simulate.timestepping.
    ContactTrajectory`): for each planned impact the realized impact on the same wall nearest in time;
    largest differences of the time, of body 2's position and of its post-impact velocity."""
    if "impact_t" in tr.stats:                 # located impacts (event-driven runs, reduced records)
        st = tr.stats
        times, contact = np.asarray(st["impact_t"], float), np.asarray(st["impact_contact"], int)
        v_plus = np.asarray(st["impact_v_plus"], float).reshape(times.size, -1)
    else:
        times, contact, _, _, v_plus = tr.impacts()
    dt, dq, dv = 0.0, 0.0, 0.0
    for t, wall, q2, v2 in plan.impact_table():
        sel = np.flatnonzero(contact == walls[wall - 1])
        if sel.size == 0:
            return {"planned impacts": len(plan.impact_table()), "missing impact on wall": wall, "at": t}
        k = sel[np.argmin(np.abs(times[sel] - t))]
        q2_run = float(np.interp(times[k], tr.t, tr.q[body2]))  # q: (n, len(t))
        dt, dq = max(dt, abs(times[k] - t)), max(dq, abs(q2_run - q2))
        dv = max(dv, abs(v_plus[k, body2] - v2))
    return {"planned impacts": len(plan.impact_table()), "realized impacts": int(times.size),
            "max |t_run - t_plan|": dt, "max |q2_run - q2_plan| at the impacts": dq,
            "max |q2'_run - q2'_plan| after the impacts": dv}
