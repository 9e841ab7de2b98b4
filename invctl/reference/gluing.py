"""Gluing a user's motion and force profiles into one continuous reference (002 App. A).

The user gives a motion profile ``x~_d(t)`` for free motion, a force profile
``F~_d(t)`` for contact, and the intended contact intervals ``[t_c,i, t_b,i]``.
The reference generator is a linear system with state
``r = (x_d, x_d', y_1, y_1')`` switched at the (known) intended times:

* free motion, filter (A): ``x_d'' = -2 g2 x_d' - g2^2 (x_d - x~_d)``;
* contact, filters (31a), (31b): ``y_1'' = -2 g1 y_1' - g1^2 (y_1 - F~_d)``,
  ``x_d'' = -(ke^/be^) x_d' + y_1'/be^`` with ``F_d = y_1``;
* at ``t_c,i`` the force filter starts on the force-to-motion map (4):
  ``y_1 = ke^ x_d + be^ x_d'``, ``y_1' = ke^ x_d' + be^ x_d''``.

Then ``x_d, x_d'`` are continuous, ``x_d''`` is piecewise continuous
(Assumption 1), ``F_d`` and ``F_d'`` are continuous at ``t_c,i``, and (4)
``ke^ x_d + be^ x_d' = F_d`` holds throughout every contact interval.  Outside
contact, the controller's ``F_d`` is the virtual force of (4) applied to
``x_d``; the *desired* contact force shown to users is zero there.

Profiles are piecewise polynomials (:class:`scipy.interpolate.PPoly`, degree
<= 5); the generator is propagated exactly by matrix exponentials of the
system augmented with the Taylor coefficients of the inputs, so no integration
error enters the reference.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import CubicHermiteSpline, PPoly
from scipy.linalg import expm

from ..errors import ParameterError, ReferenceSignalError

#: maximal polynomial degree of a profile piece (Taylor state length DEG + 1 per input)
DEG = 5
T_FAR = 1.0e6


# ---------------------------------------------------------------------------
# profiles
# ---------------------------------------------------------------------------
def piecewise_polynomial(breaks, polys) -> PPoly:
    """A profile from breakpoints and per-piece polynomial coefficients in the local time.

    ``polys[i]`` lists coefficients of ``1, s, s^2, ...`` with ``s = t - breaks[i]``;
    the last piece extends to ``t = 1e6``.
    """
    breaks = [float(b) for b in breaks]
    if len(polys) != len(breaks):
        raise ReferenceSignalError("piecewise_polynomial: one coefficient list per breakpoint is needed "
                                   f"(got {len(breaks)} breakpoints, {len(polys)} pieces)")
    if any(b1 <= b0 for b0, b1 in zip(breaks, breaks[1:])):
        raise ReferenceSignalError(f"breakpoints must increase strictly, got {breaks}")
    k = max(len(p) for p in polys)
    if k - 1 > DEG:
        raise ReferenceSignalError(f"profile pieces of degree <= {DEG} are supported, got degree {k - 1}")
    c = np.zeros((k, len(polys)))
    for i, p in enumerate(polys):
        for j, a in enumerate(p):
            c[k - 1 - j, i] = float(a)
    return PPoly(c, np.array(breaks + [max(T_FAR, breaks[-1] + 1.0)]))


def approach_retract(t_c: float, t_b: float, v_app: float, x_ret: float, t0: float = 0.0,
                     overshoot_time: float = 0.02) -> PPoly:
    """Continuous motion profile for one contact: approach the wall ``x = 0`` at speed ``v_app``
    (crossing it at ``t_c``), keep going for ``overshoot_time`` (so that the *filtered* ``x_d``
    reaches the wall too), come back linearly to 0 at ``t_b`` (this part is not used in contact),
    then retract at ``v_app`` to ``x_ret < 0`` and stay."""
    d = min(overshoot_time, 0.5 * (t_b - t_c))
    if not (v_app > 0 and x_ret < 0 and t_b > t_c > t0 and d > 0):
        raise ReferenceSignalError(f"approach_retract needs v_app > 0, x_ret < 0, t0 < t_c < t_b, "
                                   f"overshoot_time > 0; got v_app={v_app}, x_ret={x_ret}, t0={t0}, "
                                   f"t_c={t_c}, t_b={t_b}, overshoot_time={overshoot_time}")
    t_r = t_b - x_ret / v_app
    peak = v_app * d
    return piecewise_polynomial([t0, t_c + d, t_b, t_r],
                                [[v_app * (t0 - t_c), v_app], [peak, -peak / (t_b - t_c - d)],
                                 [0.0, -v_app], [x_ret]])


def force_bump(t_c: float, t_b: float, F_max: float, t0: float = 0.0) -> PPoly:
    """Force profile ``F_max 16 s^2 (1 - s)^2`` on ``[t_c, t_b]`` (``s`` normalised time), zero elsewhere."""
    if not t_b > t_c > t0:
        raise ReferenceSignalError(f"force_bump needs t0 < t_c < t_b, got {t0}, {t_c}, {t_b}")
    T = t_b - t_c
    a = 16.0 * F_max
    # 16 F s^2 (1 - s)^2 = a (s^2 - 2 s^3 + s^4), s = tau / T
    return piecewise_polynomial([t0, t_c, t_b], [[0.0], [0, 0, a / T**2, -2 * a / T**3, a / T**4], [0.0]])


def from_callable(f, t0: float, t1: float, n: int = 200) -> PPoly:
    """A C^1 piecewise-cubic profile interpolating ``f`` and its (central-difference) slope on ``n`` intervals,
    constant after ``t1``."""
    t = np.linspace(t0, t1, n + 1)
    y = np.array([float(f(ti)) for ti in t])
    if not np.all(np.isfinite(y)):
        raise ReferenceSignalError("profile callable returned non-finite values")
    dy = np.gradient(y, t, edge_order=2)
    sp = CubicHermiteSpline(t, y, dy)
    c = np.hstack([sp.c, np.array([[0.0], [0.0], [0.0], [y[-1]]])])
    return PPoly(c, np.append(t, T_FAR))


def taylor(pp: PPoly, t: float) -> np.ndarray:
    """Taylor vector ``(u, u', ..., u^(DEG))`` of the piece of ``pp`` starting at or containing ``t``."""
    x = pp.x
    i = int(np.searchsorted(x, t, side="right") - 1)
    i = min(max(i, 0), pp.c.shape[1] - 1)
    k = pp.c.shape[0]
    s = t - x[i]
    out = np.zeros(DEG + 1)
    # derivatives of the local polynomial sum_m c[m] s^(k-1-m) at s
    coeffs = pp.c[:, i][::-1]  # ascending powers
    for j in range(min(k, DEG + 1)):
        val = 0.0
        for p in range(j, k):
            val += coeffs[p] * math.perm(p, j) * s ** (p - j)
        out[j] = val
    return out


# ---------------------------------------------------------------------------
# exact propagation helpers (shared with invctl.simulate.switched)
# ---------------------------------------------------------------------------
def nilpotent_block(n_inputs: int) -> np.ndarray:
    """Dynamics of the stacked Taylor states: ``d/dt u^(j) = u^(j+1)``, ``u^(DEG)`` constant."""
    m = DEG + 1
    N = np.zeros((n_inputs * m, n_inputs * m))
    for c in range(n_inputs):
        for j in range(m - 1):
            N[c * m + j, c * m + j + 1] = 1.0
    return N


def input_selector(n_inputs: int) -> np.ndarray:
    """Rows picking ``u`` (the 0th Taylor coefficient) of each input from the stacked Taylor states."""
    m = DEG + 1
    E = np.zeros((n_inputs, n_inputs * m))
    for c in range(n_inputs):
        E[c, c * m] = 1.0
    return E


def powers_apply(E: np.ndarray, S0: np.ndarray, K: int) -> np.ndarray:
    """``[S0, E S0, ..., E^K S0]`` (rows) by repeated doubling: ``log2 K`` matrix products, no loop over steps."""
    X = S0[None, :]
    P = E
    while X.shape[0] < K + 1:
        # einsum, not BLAS: these products are small, and threaded BLAS on a busy machine costs 10-40x
        X = np.vstack([X, np.einsum("kj,ij->ki", X, P)])
        P = np.einsum("ij,jk->ik", P, P)
    return X[: K + 1]


# ---------------------------------------------------------------------------
# the glued reference
# ---------------------------------------------------------------------------
@dataclass(frozen=True)
class ReferenceSamples:
    """Samples of the glued reference: ``x_d, x_d', x_d''``, controller ``F_d``, desired force, phase."""

    t: np.ndarray
    xd: np.ndarray
    xd_dot: np.ndarray
    xd_ddot: np.ndarray
    Fd: np.ndarray
    Fd_desired: np.ndarray
    contact: np.ndarray


@dataclass(frozen=True)
class GluedReference:
    """The reference generator of 002 App. A (see the module docstring).

    Parameters
    ----------
    x_profile, F_profile : PPoly
        The user's motion profile ``x~_d`` and force profile ``F~_d``.
    intervals : sequence of (t_c, t_b)
        Intended contact intervals, increasing and disjoint, after ``t0``.
    gamma1, gamma2 : float
        Filter constants of (31a) and (A) (rad/s).
    ke_hat, be_hat : float
        Estimates used in the force-to-motion map (4); ``be_hat > 0``.
    t0 : float
        Start time; the reference starts in free motion on the motion profile.
    """

    x_profile: PPoly
    F_profile: PPoly
    intervals: tuple
    gamma1: float
    gamma2: float
    ke_hat: float
    be_hat: float
    t0: float = 0.0
    contact_start: str = "crossing"
    n: int = field(default=4, init=False)
    n_inputs: int = field(default=2, init=False)
    contact_intervals: tuple = field(default=(), init=False)

    def __post_init__(self) -> None:
        for name in ("gamma1", "gamma2", "ke_hat", "be_hat"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ParameterError(f"{name} must be positive and finite, got {v}"
                                     + (" (the map (4) divides by be_hat; use a small positive value)"
                                        if name == "be_hat" else ""))
        if self.contact_start not in ("crossing", "time"):
            raise ParameterError(f"contact_start must be 'crossing' or 'time', got {self.contact_start!r}")
        iv = tuple((float(a), float(b)) for a, b in self.intervals)
        prev = self.t0
        for a, b in iv:
            if not (a > prev and b > a):
                raise ReferenceSignalError(
                    f"contact intervals must be increasing, disjoint and after t0 = {self.t0}: got {iv}")
            prev = b
        object.__setattr__(self, "intervals", iv)
        object.__setattr__(self, "contact_intervals", self._locate_contacts())

    # -- where contact starts ----------------------------------------------------------
    def _locate_contacts(self) -> tuple:
        """Actual contact intervals of the generator.

        ``contact_start='time'``: the user's ``t_c,i``.  ``'crossing'`` (default): the
        instant the *filtered* ``x_d`` reaches the wall ``x_d = 0`` upwards, searched in
        ``[t_b,i-1, t_b,i)``; the filter (A) lags a ramp by ``2 v / gamma2``, so
        switching at ``t_c,i`` would start the force filter from ``ke^ x_d(t_c) << 0``.
        """
        if self.contact_start == "time":
            return self.intervals
        out = []
        t, r = self.t0, self._initial_r()
        for a, b in self.intervals:
            hit = self._first_crossing(t, r, b)
            if hit is None:
                raise ReferenceSignalError(
                    f"the filtered motion reference never reaches the wall x_d = 0 before t_b = {b:.6g} "
                    f"(intended contact [{a:.6g}, {b:.6g}]); let the motion profile cross 0 earlier, raise "
                    "gamma2, or use contact_start='time'")
            tc, rc = hit
            rc = self.contact_reset() @ np.concatenate([rc, self.taylor_inputs(tc)[[0, DEG + 1]]])
            r = self._advance(tc, rc, b, True)
            t = b
            out.append((tc, b))
        return tuple(out)

    def _aug(self, contact: bool) -> np.ndarray:
        m = self.n_inputs * (DEG + 1)
        A, B = self.matrices(contact)
        Aa = np.zeros((4 + m, 4 + m))
        Aa[:4, :4] = A
        Aa[:4, 4:] = B @ input_selector(self.n_inputs)
        Aa[4:, 4:] = nilpotent_block(self.n_inputs)
        return Aa

    def _advance(self, t: float, r: np.ndarray, t_to: float, contact: bool) -> np.ndarray:
        Aa = self._aug(contact)
        for te in self.input_breaks(t, t_to) + [t_to]:
            r = (expm(Aa * (te - t)) @ np.concatenate([r, self.taylor_inputs(t)]))[:4]
            t = te
        return r

    def _first_crossing(self, t: float, r: np.ndarray, t_to: float):
        from scipy.optimize import brentq

        Aa = self._aug(False)
        h_max = min(1e-4, 0.05 / self.gamma2)
        for te in self.input_breaks(t, t_to) + [t_to]:
            S0 = np.concatenate([r, self.taylor_inputs(t)])
            if S0[0] >= 0:
                return t, r
            K = max(1, int(math.ceil((te - t) / h_max)))
            h = (te - t) / K
            S = powers_apply(expm(Aa * h), S0, K)
            k = np.flatnonzero(S[:, 0] >= 0)
            if k.size:
                k0 = int(k[0])
                tau = brentq(lambda s: (expm(Aa * s) @ S0)[0], h * (k0 - 1), h * k0, xtol=1e-15, rtol=1e-15)
                return t + tau, (expm(Aa * tau) @ S0)[:4]
            r = S[-1, :4]
            t = te
        return None

    def _initial_r(self) -> np.ndarray:
        u = taylor(self.x_profile, self.t0)
        return np.array([u[0], u[1], 0.0, 0.0])

    # -- phases and matrices ---------------------------------------------------------
    def phase(self, t) -> np.ndarray:
        """True where contact is intended (``t_c,i <= t < t_b,i``)."""
        t = np.asarray(t, float)
        out = np.zeros(t.shape, bool)
        for a, b in self.contact_intervals:
            out |= (t >= a) & (t < b)
        return out

    def switch_times(self) -> list[float]:
        return [x for ab in self.contact_intervals for x in ab]

    def input_breaks(self, t0: float, t1: float) -> list[float]:
        xs = np.concatenate([self.x_profile.x, self.F_profile.x])
        return sorted({float(x) for x in xs if t0 < x < t1})

    def taylor_inputs(self, t: float) -> np.ndarray:
        return np.concatenate([taylor(self.x_profile, t), taylor(self.F_profile, t)])

    def matrices(self, contact: bool) -> tuple[np.ndarray, np.ndarray]:
        """``(A_r, B_r)``: ``r' = A_r r + B_r (x~_d, F~_d)``."""
        A = np.zeros((4, 4))
        B = np.zeros((4, 2))
        A[0, 1] = 1.0
        if contact:
            g, k, be = self.gamma1, self.ke_hat, self.be_hat
            A[1, 1] = -k / be
            A[1, 3] = 1.0 / be
            A[2, 3] = 1.0
            A[3, 2] = -g * g
            A[3, 3] = -2 * g
            B[3, 1] = g * g
        else:
            g = self.gamma2
            A[1, 0] = -g * g
            A[1, 1] = -2 * g
            B[1, 0] = g * g
        return A, B

    def contact_reset(self) -> np.ndarray:
        """Linear reset at ``t_c,i`` on ``(r, u)``: ``y1 = ke^ x_d + be^ x_d'``, ``y1' = ke^ x_d' + be^ x_d''(t_c-)``."""
        A, B = self.matrices(False)
        R = np.zeros((4, 6))
        R[:2, :2] = np.eye(2)
        R[2, 0], R[2, 1] = self.ke_hat, self.be_hat
        acc = np.concatenate([A[1], B[1]])  # x_d'' before the switch
        R[3, 1] = self.ke_hat
        R[3] += self.be_hat * acc
        return R

    def output_rows(self, contact: bool) -> dict[str, np.ndarray]:
        """Rows on ``(r, u)`` giving ``xd, xd_dot, xd_ddot, Fd`` (controller) and ``Fd_desired``."""
        A, B = self.matrices(contact)
        rows = {
            "xd": np.eye(6)[0], "xd_dot": np.eye(6)[1],
            "xd_ddot": np.concatenate([A[1], B[1]]),
        }
        if contact:
            rows["Fd"] = np.eye(6)[2]
            rows["Fd_desired"] = np.eye(6)[2]
        else:
            rows["Fd"] = self.ke_hat * np.eye(6)[0] + self.be_hat * np.eye(6)[1]
            rows["Fd_desired"] = np.zeros(6)
        return rows

    def initial_state(self) -> np.ndarray:
        """``r(t0) = (x~_d(t0), x~_d'(t0), 0, 0)``: the motion filter starts at rest on the profile."""
        return self._initial_r()

    # -- exact sampling ------------------------------------------------------------------
    def sample(self, t_end: float, dt: float = 1e-4) -> ReferenceSamples:
        """Exact samples on the uniform grid ``t0, t0 + dt, ...`` up to ``t_end`` (plus event times)."""
        if not (t_end > self.t0 and dt > 0):
            raise ParameterError(f"sample needs t_end > t0 and dt > 0, got t_end={t_end}, dt={dt}")
        m = self.n_inputs * (DEG + 1)
        Nb = nilpotent_block(self.n_inputs)
        Sel = input_selector(self.n_inputs)
        events = sorted(set(self.switch_times()) | set(self.input_breaks(self.t0, t_end)))
        events = [e for e in events if self.t0 < e < t_end] + [t_end]
        t = self.t0
        r = self.initial_state()
        ts, rows = [], []
        for te in events:
            contact = bool(self.phase([t])[0])
            if any(t == a for a, _ in self.contact_intervals):
                r = self.contact_reset() @ np.concatenate([r, self.taylor_inputs(t)[[0, DEG + 1]]])
            q = self.taylor_inputs(t)
            A, B = self.matrices(contact)
            Aa = np.zeros((4 + m, 4 + m))
            Aa[:4, :4] = A
            Aa[:4, 4:] = B @ Sel
            Aa[4:, 4:] = Nb
            K = max(1, int(math.ceil((te - t) / dt - 1e-9)))
            h = (te - t) / K
            S = powers_apply(expm(Aa * h), np.concatenate([r, q]), K)
            out = self.output_rows(contact)
            S = S[:K]
            ru = np.hstack([S[:, :4], S[:, 4:] @ Sel.T])
            ts.append(t + h * np.arange(K))
            rows.append(np.column_stack([ru @ out[k] for k in ("xd", "xd_dot", "xd_ddot", "Fd", "Fd_desired")]
                                        + [np.full(K, contact)]))
            r = (expm(Aa * h) @ S[-1])[:4]
            t = te
        contact = bool(self.phase([t])[0])
        out = self.output_rows(contact)
        ru = np.concatenate([r, self.taylor_inputs(t)[[0, DEG + 1]]])
        ts.append(np.array([t]))
        rows.append(np.array([[ru @ out[k] for k in ("xd", "xd_dot", "xd_ddot", "Fd", "Fd_desired")] + [contact]]))
        T = np.concatenate(ts)
        Y = np.vstack(rows)
        return ReferenceSamples(T, Y[:, 0], Y[:, 1], Y[:, 2], Y[:, 3], Y[:, 4], Y[:, 5].astype(bool))
