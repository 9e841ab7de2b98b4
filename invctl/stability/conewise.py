"""Stability of the switched motion/force error system (002 Sect. 3, App. B).

The tracking error ``z = (x_d - x, x_d' - x')`` of the 1-DOF manipulator under
the switched controller 002 (3) obeys the switched system 002 (9)-(11)::

    z' = A_i z + N w_i(t),   A_i = [[0, 1], [-K_i, -B_i]],   N = (0, 1),

with ``i = 1`` in free motion and ``i = 2`` in contact.  Lemma 1 bounds every
switching sequence by the time-invariant worst-case conewise system ``Sigma^w``
(13) that picks ``argmax_i z^T A_i z``; Theorem 1 decides its GUAS either by a
visible eigenvector (Definition 2) or by the return-map factor
``Lambda = Lambda_1^2 Lambda_2^2 < 1`` of one rotation, (14)-(16).

Three independent ways to Lambda are provided:

* :func:`lambda_closed_form` -- the printed formulas (14), (15), (16);
* :func:`lambda_appendix_b` -- the general cone-to-cone factors (33)-(35) in
  real-Jordan coordinates with the boundary rays (22);
* :func:`lambda_numerical` -- integration of ``Sigma^w`` with the *Lemma 1*
  switching rule (``argmax z^T A_i z``) by an explicit Runge-Kutta method with
  event location through one full rotation (no use of the cone geometry).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.integrate import solve_ivp

from ..errors import ParameterError, StabilityError

#: relative band on B^2 - 4K inside which a subsystem is treated as critically damped (15)
CRITICAL_RTOL = 1e-12


# ---------------------------------------------------------------------------
# the switched error system (9)-(11)
# ---------------------------------------------------------------------------
@dataclass(frozen=True)
class SwitchedErrorSystem:
    """The unperturbed/perturbed error system 002 (9)-(10) by its four numbers.

    Parameters
    ----------
    K1, B1 : float
        Stiffness and damping of the free-motion subsystem (11a).
    K2, B2 : float
        Stiffness and damping of the contact subsystem (11b) or (30).

    Raises
    ------
    StabilityError
        If a subsystem is not Hurwitz (``K_i <= 0`` or ``B_i <= 0``).
    """

    K1: float
    B1: float
    K2: float
    B2: float

    def __post_init__(self) -> None:
        for name in ("K1", "B1", "K2", "B2"):
            v = getattr(self, name)
            if not math.isfinite(v):
                raise ParameterError(f"{name} = {v} is not finite")
        bad = [f"{n} = {getattr(self, n):.6g}" for n in ("K1", "B1", "K2", "B2") if getattr(self, n) <= 0]
        if bad:
            which = {"K1": "kp", "B1": "kd + b", "K2": "(1 + kf) ke", "B2": "(1 + kf) be + bf + b"}
            hints = ", ".join(f"{b.split(' ')[0]} ~ {which[b.split(' ')[0]]}" for b in bad)
            raise StabilityError(
                f"subsystem not Hurwitz: {', '.join(bad)} (need K_i > 0 and B_i > 0; {hints}). "
                "Choose positive gains kp, kd, kf > -1, bf so that every subsystem of 002 (10) is stable.",
                diagnostics={"K1": self.K1, "B1": self.B1, "K2": self.K2, "B2": self.B2},
            )

    # -- construction from physical parameters ------------------------------------------
    @classmethod
    def from_params(cls, *, M: float, b: float, kp: float, kd: float, ke: float, be: float,
                    kf: float, bf: float) -> "SwitchedErrorSystem":
        """002 (11a), (11b) from plant, environment and controller parameters."""
        if M <= 0:
            raise ParameterError(f"mass M must be positive, got M = {M}")
        return cls(K1=kp / M, B1=(kd + b) / M, K2=(1 + kf) * ke / M, B2=((1 + kf) * be + bf + b) / M)

    # -- matrices ------------------------------------------------------------------------
    @property
    def dK(self) -> float:
        return self.K1 - self.K2

    @property
    def dB(self) -> float:
        return self.B1 - self.B2

    def K(self, i: int) -> float:
        return (self.K1, self.K2)[i - 1]

    def B(self, i: int) -> float:
        return (self.B1, self.B2)[i - 1]

    def A(self, i: int) -> np.ndarray:
        """``A_i`` of (9)."""
        return np.array([[0.0, 1.0], [-self.K(i), -self.B(i)]])

    N = np.array([[0.0], [1.0]])

    def statespace(self, i: int):
        """Subsystem ``i`` as a python-control ``StateSpace`` (input w_i, output z)."""
        import control

        return control.ss(self.A(i), self.N, np.eye(2), np.zeros((2, 1)))

    def eigenvalues(self, i: int) -> np.ndarray:
        K, B = self.K(i), self.B(i)
        d = B * B - 4 * K
        if d >= 0:
            r = math.sqrt(d)
            return np.array([(-B + r) / 2, (-B - r) / 2])
        w = math.sqrt(-d) / 2
        return np.array([complex(-B / 2, w), complex(-B / 2, -w)])

    def damping_case(self, i: int) -> str:
        """``'complex'`` (14), ``'critical'`` (15) or ``'real'`` (16)."""
        K, B = self.K(i), self.B(i)
        d = B * B - 4 * K
        if abs(d) <= CRITICAL_RTOL * max(B * B, 4 * K):
            return "critical"
        return "real" if d > 0 else "complex"

    # -- Lemma 1 ---------------------------------------------------------------------------
    def worst_case_mode(self, z) -> int:
        """Subsystem chosen by Lemma 1: ``argmax_i z^T A_i z`` (ties -> 1, closure of S_1)."""
        z = np.asarray(z, float)
        return 1 if z @ self.A(1) @ z >= z @ self.A(2) @ z else 2

    def in_cone(self, i: int, z, *, closed: bool = True) -> bool:
        """Membership of ``z`` in the cone ``S_i`` of Lemma 1 (or its closure)."""
        z1, z2 = float(z[0]), float(z[1])
        s = z2 * (self.dK * z1 + self.dB * z2)
        scale = (abs(self.dK) * abs(z1) + abs(self.dB) * abs(z2)) * abs(z2) + 1e-300
        tol = 1e-12 * scale if closed else 0.0
        return s <= tol if i == 1 else s >= -tol if closed else s > 0


# ---------------------------------------------------------------------------
# Perturbations (11c), (11d)
# ---------------------------------------------------------------------------
def perturbations(xd, xd_dot, xd_ddot, *, M, b, Ma, bf, ke, be, ke_hat=None, be_hat=None):
    """``w_1(t)`` (11c) and ``w_2(t)`` (11d) from the glued reference.

    ``w_f = (ke_hat - ke) x_d + (be_hat - be) x_d'`` of (5) enters ``w_2``.
    """
    xd, xd_dot, xd_ddot = (np.asarray(a, float) for a in (xd, xd_dot, xd_ddot))
    ke_hat = ke if ke_hat is None else ke_hat
    be_hat = be if be_hat is None else be_hat
    wf = (ke_hat - ke) * xd + (be_hat - be) * xd_dot
    w1 = (M - Ma) / M * xd_ddot + b / M * xd_dot
    w2 = xd_ddot + (bf + b) / M * xd_dot - wf / M
    return w1, w2


# ---------------------------------------------------------------------------
# visible eigenvectors (Definition 2, Theorem 1 i)
# ---------------------------------------------------------------------------
@dataclass(frozen=True)
class VisibleEigenvector:
    cone: int
    eigenvalue: float
    vector: tuple[float, float]


def eigenvectors(sys: SwitchedErrorSystem, i: int) -> list[tuple[float, np.ndarray]]:
    """Real eigenpairs of ``A_i`` (17): ``v = ((-B +- sqrt(B^2-4K))/(2K), 1)``; empty if complex."""
    case = sys.damping_case(i)
    K, B = sys.K(i), sys.B(i)
    if case == "complex":
        return []
    if case == "critical":
        lam = float(-B / 2)
        return [(lam, np.array([lam / K, 1.0]))]
    r = math.sqrt(B * B - 4 * K)
    out = []
    for lam in ((-B + r) / 2, (-B - r) / 2):
        out.append((lam, np.array([lam / K, 1.0])))
    return out


def visible_eigenvectors(sys: SwitchedErrorSystem) -> list[VisibleEigenvector]:
    """Eigenvectors of ``A_i`` lying in the closure of the cone ``S_i`` (Definition 2), checked geometrically."""
    vis = []
    for i in (1, 2):
        for lam, v in eigenvectors(sys, i):
            if sys.in_cone(i, v, closed=True):
                vis.append(VisibleEigenvector(i, float(lam), (float(v[0]), float(v[1]))))
    return vis


def theorem1_conditions(sys: SwitchedErrorSystem) -> dict[str, bool]:
    """The inequalities of Theorem 1 i (a), (b)1), (b)2) as printed (independent of :func:`visible_eigenvectors`)."""
    K1, B1, K2, B2, dK, dB = sys.K1, sys.B1, sys.K2, sys.B2, sys.dK, sys.dB
    d1, d2 = B1 * B1 - 4 * K1, B2 * B2 - 4 * K2
    crit1 = sys.damping_case(1) == "critical"
    crit2 = sys.damping_case(2) == "critical"
    a = b1 = False
    if dB < 0 and (d1 >= 0 or crit1):
        # dK/dB < 2K1/(B1 - sqrt(d1)), multiplied through by dB < 0 (no division by zero)
        b1_eff = B1 - math.sqrt(max(d1, 0.0))
        a = dK * b1_eff >= 2 * K1 * dB  # closure: equality (eigenvector on the line) counts as visible
    if dB < 0 and (d2 >= 0 or crit2):
        b2_eff = B2 + math.sqrt(max(d2, 0.0))
        b1 = dK * b2_eff <= 2 * K2 * dB
    b2 = (d2 >= 0 or crit2) and dB >= 0
    return {"i_a": bool(a), "i_b1": bool(b1), "i_b2": bool(b2)}


# ---------------------------------------------------------------------------
# Lambda: closed form (14)-(16)
# ---------------------------------------------------------------------------
def _require_applicable(sys: SwitchedErrorSystem) -> None:
    if not sys.dK < 0:
        raise StabilityError(
            f"Theorem 1 needs K2 > K1 (Delta K < 0); got K1 = {sys.K1:.6g}, K2 = {sys.K2:.6g}. "
            "The worst-case system of Lemma 1 may then have sliding modes and Lambda is not defined.",
            diagnostics={"K1": sys.K1, "K2": sys.K2},
        )


def _require_rotation(sys: SwitchedErrorSystem) -> None:
    _require_applicable(sys)
    vis = visible_eigenvectors(sys)
    if vis:
        raise StabilityError(
            "Lambda is undefined: Sigma^w has a visible eigenvector "
            f"(cone {vis[0].cone}, eigenvalue {vis[0].eigenvalue:.6g}), so trajectories stop rotating; "
            "stability follows from Theorem 1 i instead.",
            diagnostics={"visible": [asdict_v(v) for v in vis]},
        )


def asdict_v(v: VisibleEigenvector) -> dict:
    return {"cone": v.cone, "eigenvalue": v.eigenvalue, "vector": list(v.vector)}


def lambda_i_closed_form(sys: SwitchedErrorSystem, i: int, *, printed_15: bool = False) -> float:
    """``Lambda_i`` by (14) (complex), (15) (critically damped) or (16) (real eigenvalues).

    Notes
    -----
    (15) as printed, ``|B_i L/(2 dK - B_i dB)| exp((-1)^i 2 dK/(2 dK - B_i dB))``, is wrong
    for ``i = 1``: evaluating (34) with the proof's ``P_i`` and rays (22) gives the
    prefactor raised to ``(-1)^i`` (as in (14)), i.e. ``|(2 dK - B_1 dB)/(B_1 L)|`` for
    ``i = 1``.  The corrected form is used; it agrees with (34), with the limits of
    (14) and (16) at ``B^2 -> 4K`` and with the integrated return map.  ``printed_15=True``
    evaluates the printed form (see docs/reproduction.md).
    """
    K, B, dK, dB = sys.K(i), sys.B(i), sys.dK, sys.dB
    L = math.hypot(dK, dB)
    sgn = (-1) ** i
    case = sys.damping_case(i)
    if case == "complex":
        w = 0.5 * math.sqrt(4 * K - B * B)
        Q = B * dK - 2 * K * dB
        # phi = mod(-arctan(s 2 w dK / Q), pi): arctan2 differs from arctan(y/Q) by a multiple of pi,
        # which the mod removes, and it is defined for Q = 0
        phi = math.fmod(-math.atan2(sgn * 2 * w * dK, Q), math.pi)
        if phi < 0:
            phi += math.pi
        base = (K / w) * (dK**2 / L**2 + Q**2 / (4 * w * w * L**2)) ** -0.5
        return base**sgn * math.exp(-B / (2 * w) * phi)
    if case == "critical":
        den = 2 * dK - B * dB
        if den == 0:
            raise StabilityError("critically damped subsystem with its eigenvector on the switching line "
                                 "(2 dK = B dB): the eigenvector is visible and Lambda is undefined")
        pre = abs(B * L / den)
        return (pre if printed_15 else pre**sgn) * math.exp(sgn * 2 * dK / den)
    r = math.sqrt(B * B - 4 * K)
    la, lb = (-B - r) / 2, (-B + r) / 2
    f_b = abs((dK * lb + K * dB) / (K * L))
    f_a = abs((dK * la + K * dB) / (K * L))
    if f_a == 0 or f_b == 0:
        raise StabilityError("an eigenvector of A_%d lies on the switching line: it is visible and "
                             "Lambda is undefined" % i)
    return f_b ** (sgn * la / (lb - la)) * f_a ** (sgn * lb / (la - lb))


def lambda_closed_form(sys: SwitchedErrorSystem, *, printed_15: bool = False) -> tuple[float, float, float]:
    """``(Lambda_1, Lambda_2, Lambda = Lambda_1^2 Lambda_2^2)`` by 002 (14)-(16) ((15) corrected, see
    :func:`lambda_i_closed_form`).

    Raises
    ------
    StabilityError
        If Theorem 1 does not apply (``K2 <= K1``) or a visible eigenvector exists.
    """
    _require_rotation(sys)
    l1 = lambda_i_closed_form(sys, 1, printed_15=printed_15)
    l2 = lambda_i_closed_form(sys, 2, printed_15=printed_15)
    return l1, l2, (l1 * l2) ** 2


# ---------------------------------------------------------------------------
# Lambda: App. B (33)-(35) in real-Jordan coordinates
# ---------------------------------------------------------------------------
def _jordan(sys: SwitchedErrorSystem, i: int):
    """Real Jordan decomposition ``A_i = P J P^-1`` computed from the eigen-decomposition."""
    A = sys.A(i)
    case = sys.damping_case(i)
    K, B = sys.K(i), sys.B(i)
    if case == "complex":
        eigs, V = np.linalg.eig(A)
        k = int(np.argmax(eigs.imag))
        a, w = eigs[k].real, eigs[k].imag
        v = V[:, k]
        # A (Re v) = a Re v - w Im v, A (Im v) = w Re v + a Im v  ->  P = [Re v, -Im v], J = [[a, -w], [w, a]]
        P = np.column_stack([v.real, -v.imag])
        return case, P, (a, w)
    if case == "critical":
        lam = -B / 2
        v1 = np.array([1.0, lam])
        # generalized eigenvector: (A - lam I) v2 = v1 solved in least squares (singular matrix)
        v2 = np.linalg.lstsq(A - lam * np.eye(2), v1, rcond=None)[0]
        return case, np.column_stack([v1, v2]), (lam,)
    r = math.sqrt(B * B - 4 * K)
    la, lb = (-B - r) / 2, (-B + r) / 2
    P = np.column_stack([[1.0, la], [1.0, lb]])
    return case, P, (la, lb)


def lambda_i_appendix_b(sys: SwitchedErrorSystem, i: int) -> float:
    """``Lambda_i`` from (33)-(35) with rays (22) and a numerically computed real Jordan form."""
    L = math.hypot(sys.dK, sys.dB)
    rho_line = np.array([sys.dB, -sys.dK]) / L
    e1 = np.array([1.0, 0.0])
    # cone 1: enters on rho_21, leaves on rho_12 = (1, 0); cone 2 (the symmetric copy): enters on
    # -(1, 0), leaves on rho_21 (22)
    r_in, r_out = (rho_line, e1) if i == 1 else (-e1, rho_line)
    case, P, ev = _jordan(sys, i)
    Pi = np.linalg.inv(P)
    ti, to = Pi @ r_in, Pi @ r_out
    if case == "complex":
        a, w = ev
        ang = math.atan2(ti[0] * to[1] - ti[1] * to[0], ti @ to)
        if ang < 0:
            ang += 2 * math.pi
        # J rotates counter-clockwise in the Jordan coordinates with the P above
        return float(np.linalg.norm(ti) / np.linalg.norm(to) * math.exp(a / w * ang))
    if case == "critical":
        (lam,) = ev
        return abs(ti[1] / to[1]) * math.exp(lam * (to[0] / to[1] - ti[0] / ti[1]))
    la, lb = ev
    return (abs(to[1] / ti[1]) ** (la / (lb - la))) * (abs(to[0] / ti[0]) ** (lb / (la - lb)))


def lambda_appendix_b(sys: SwitchedErrorSystem) -> tuple[float, float, float]:
    """``(Lambda_1, Lambda_2, Lambda)`` by the general formulas (33)-(35) of App. B."""
    _require_rotation(sys)
    l1, l2 = lambda_i_appendix_b(sys, 1), lambda_i_appendix_b(sys, 2)
    return l1, l2, (l1 * l2) ** 2


# ---------------------------------------------------------------------------
# Lambda: numerical integration of the worst-case system through one rotation
# ---------------------------------------------------------------------------
@dataclass(frozen=True)
class RotationResult:
    """One rotation of ``Sigma^w`` from the ray ``(1, 0)`` back to it."""

    Lambda: float
    sector_factors: tuple[float, ...]
    sector_modes: tuple[int, ...]
    sector_times: tuple[float, ...]
    period: float
    visible: bool
    nfev: int


def lambda_numerical(sys: SwitchedErrorSystem, *, rtol: float = 1e-12, method: str = "DOP853",
                     max_decay: float = 1e-14) -> RotationResult:
    """Integrate ``Sigma^w`` with the Lemma 1 rule ``argmax_i z^T A_i z`` through one rotation.

    Starting at ``z = (1, 0)``, the mode of each sector is chosen by comparing
    ``z^T A_1 z`` and ``z^T A_2 z`` just clockwise of the current point; the sector
    ends where ``z^T (A_1 - A_2) z = -z_2 (dK z_1 + dB z_2)`` changes sign, i.e. where
    one of its two linear factors does (two event functions, located by the
    integrator; the factor the sector starts on is only watched for a crossing
    back).  Nothing of the closed forms is used.  If a sector never ends before
    ``|z|`` has decayed by ``max_decay``, a visible eigenvector has captured the
    trajectory and ``visible`` is True.
    """
    _require_applicable(sys)
    A = {1: sys.A(1), 2: sys.A(2)}
    dK, dB = sys.dK, sys.dB
    lines = (np.array([0.0, 1.0]), np.array([dK, dB]) / math.hypot(dK, dB))

    slowest = min(-complex(ev).real for i in (1, 2) for ev in np.atleast_1d(sys.eigenvalues(i)))
    t_cap = -math.log(max_decay) / slowest
    z = np.array([1.0, 0.0])
    factors: list = []
    modes: list = []
    times: list = []
    nfev = 0
    angle_total = 0.0
    for _ in range(8):
        ang = math.atan2(z[1], z[0])
        r = np.linalg.norm(z)
        probe = r * np.array([math.cos(ang - 1e-7), math.sin(ang - 1e-7)])
        mode = sys.worst_case_mode(probe)
        events = []
        for ln in lines:
            ev: Any = (lambda n: (lambda t, y: float(n @ y)))(ln)
            ev.terminal = True
            on_line = abs(ln @ z) <= 1e-9 * r * np.linalg.norm(ln)
            # leaving a line we start on: only a crossing back counts
            ev.direction = -float(np.sign(ln @ (A[mode] @ z))) if on_line else 0.0
            events.append(ev)
        scale = max(1.0, math.sqrt(sys.K(mode)))
        w = max(abs(complex(e).imag) for e in np.atleast_1d(sys.eigenvalues(mode)))
        sol = solve_ivp(lambda t, y: A[mode] @ y, (0.0, t_cap), z, method=method, rtol=rtol,
                        atol=rtol * 1e-3 * np.array([1.0, scale]) * r, events=events,
                        max_step=math.pi / (4 * w) if w > 0 else np.inf)
        nfev += sol.nfev
        hits = [(te[-1], ye[-1]) for te, ye in zip(sol.t_events, sol.y_events) if len(te)]
        if sol.status != 1 or not hits:
            return RotationResult(float("nan"), tuple(factors), tuple(modes), tuple(times),
                                  float("nan"), True, nfev)
        t_hit, z_new = min(hits, key=lambda h: h[0])
        if np.linalg.norm(z_new) < max_decay * r:
            # the trajectory sank onto a ray (visible eigenvector) and crossed only by round-off
            return RotationResult(float("nan"), tuple(factors), tuple(modes), tuple(times),
                                  float("nan"), True, nfev)
        factors.append(float(np.linalg.norm(z_new) / r))
        modes.append(mode)
        times.append(float(t_hit))
        a0, a1 = math.atan2(z[1], z[0]), math.atan2(z_new[1], z_new[0])
        angle_total += (a0 - a1) % (2 * math.pi)
        z = z_new
        if angle_total > 2 * math.pi - 1e-6:
            break
    return RotationResult(float(np.prod(factors)), tuple(factors), tuple(modes), tuple(times),
                          float(sum(times)), False, nfev)


# ---------------------------------------------------------------------------
# ISS estimate (Theorem 2) and the report
# ---------------------------------------------------------------------------
def expm2(A: np.ndarray, ts) -> np.ndarray:
    """``expm(A t)`` for a real 2x2 ``A`` and many ``t`` at once (Cayley-Hamilton, exact incl. q = 0).

    ``e^{At} = e^{st} [(cosh qt - s sinh(qt)/q) I + sinh(qt)/q A]``, ``s = tr A/2``, ``q^2 = s^2 - det A``.
    """
    ts = np.atleast_1d(np.asarray(ts, float))
    s = 0.5 * np.trace(A)
    q = np.emath.sqrt(s * s - np.linalg.det(A) + 0j)
    qt = q * ts
    ep, em = np.exp((s + q) * ts), np.exp((s - q) * ts)
    e_ch = 0.5 * (ep + em)
    small = np.abs(qt) < 1e-3
    x2 = np.where(small, qt * qt, 0)
    series = np.exp(s * ts) * ts * (1 + x2 / 6 + x2 * x2 / 120 + x2**3 / 5040)
    e_sh = np.where(small, series, (ep - em) / (2 * np.where(small, 1, q)))
    c0 = (e_ch - s * e_sh).real
    c1 = e_sh.real
    return c0[:, None, None] * np.eye(2)[None] + c1[:, None, None] * A[None]


def _sector_exit(sys: SwitchedErrorSystem, mode: int, z: np.ndarray) -> float | None:
    """Time at which the flow of ``A_mode`` from ``z`` leaves the cone of ``mode`` (None: never)."""
    from scipy.optimize import brentq

    A = sys.A(mode)
    D = sys.A(1) - sys.A(2)
    sgn = 1.0 if mode == 1 else -1.0
    ev = sys.eigenvalues(mode)
    w = max(abs(complex(e).imag) for e in ev)
    slow = min(abs(complex(e).real) for e in ev)
    horizon = math.pi / w if w > 0 else 4.0 / slow
    cap = 60.0 / slow + horizon

    def g(tau):
        zz = expm2(A, [tau])[0] @ z
        return sgn * (zz @ D @ zz)

    t_lo = 0.0
    while t_lo < cap:
        ts = np.linspace(t_lo, t_lo + horizon, 257)[1:]
        Z = expm2(A, ts) @ z
        G = sgn * np.einsum("ki,ij,kj->k", Z, D, Z)
        bad = np.flatnonzero(G < 0)
        if bad.size:
            k = int(bad[0])
            a = t_lo if k == 0 else ts[k - 1]
            return brentq(g, a, ts[k], xtol=1e-15, rtol=1e-14) if g(a) > 0 else float(a)
        t_lo += horizon
        horizon *= 2
    return None


def worst_case_flow(sys: SwitchedErrorSystem, z0, t_end: float, n: int = 400):
    """Exact trajectory of ``Sigma^w`` on ``n`` uniform times in ``[0, t_end]`` (sector exits by root finding)."""
    z = np.asarray(z0, float).copy()
    ts = np.linspace(0.0, t_end, n)
    out = np.empty((n, 2))
    t, k = 0.0, 0
    for _ in range(10000):
        ang = math.atan2(z[1], z[0])
        probe = np.array([math.cos(ang - 1e-7), math.sin(ang - 1e-7)])
        mode = sys.worst_case_mode(probe)
        A = sys.A(mode)
        tau = _sector_exit(sys, mode, z)
        seg_end = t_end if tau is None else min(t_end, t + tau)
        sel = (ts >= t) & (ts <= seg_end)
        if np.any(sel):
            out[sel] = expm2(A, ts[sel] - t) @ z
            k = int(np.flatnonzero(sel)[-1]) + 1
        if tau is None or t + tau >= t_end or k >= n:
            break
        z = expm2(A, [tau])[0] @ z
        t += tau
    if k < n:
        out[k:] = out[k - 1] if k > 0 else z
    return ts, out


@dataclass(frozen=True)
class ISSBound:
    """``|z(t)| <= c e^{-rate (t - t0)} |z0| + gain sup|N w|`` (Theorem 2), ``gain = c / rate``."""

    c: float
    rate: float
    gain: float
    method: str


def iss_bound(sys: SwitchedErrorSystem, *, n_angles: int = 72, margin: float = 0.02) -> ISSBound:
    """Constants of Theorem 2 estimated from the worst-case system ``Sigma^w``.

    The decay rate is ``-ln(Lambda)/T`` (rotation period ``T``) when trajectories
    rotate, or the slowest visible eigenvalue when one captures them, reduced by
    ``margin``; ``c`` is the largest ``|z(t)| e^{rate t}`` over ``n_angles`` unit
    initial conditions and two rotations (a sampled estimate, not a proof).
    """
    vis = visible_eigenvectors(sys)
    if vis:
        rate = min(-v.eigenvalue for v in vis)
        horizon = 12.0 / rate
        method = "visible eigenvector"
    else:
        rot = lambda_numerical(sys)
        if not rot.Lambda < 1:
            raise StabilityError(f"Sigma^w is not GUAS (Lambda = {rot.Lambda:.6g} >= 1): no ISS bound",
                                 diagnostics={"Lambda": rot.Lambda})
        rate = -math.log(rot.Lambda) / rot.period
        horizon = 2.0 * rot.period
        method = "rotation"
    rate *= 1.0 - margin
    c = 1.0
    for th in np.linspace(0.0, math.pi, n_angles, endpoint=False):
        ts, zs = worst_case_flow(sys, [math.cos(th), math.sin(th)], horizon, n=200)
        c = max(c, float(np.max(np.linalg.norm(zs, axis=1) * np.exp(rate * ts))))
    return ISSBound(c=c, rate=rate, gain=c / rate, method=method)


@dataclass(frozen=True)
class StabilityReport:
    """Theorem 1 / Theorem 2 verdict for one parameter set."""

    system: SwitchedErrorSystem
    eigenvalues: dict
    damping: dict
    visible: list
    conditions: dict
    Lambda1: float | None
    Lambda2: float | None
    Lambda: float | None
    Lambda_appendix_b: float | None
    Lambda_numerical: float | None
    rotation_period: float | None
    guas: bool
    case: str
    iss: ISSBound | None = None
    notes: list = field(default_factory=list)

    def to_dict(self) -> dict:
        s = self.system
        d = {
            "K1": s.K1, "B1": s.B1, "K2": s.K2, "B2": s.B2, "dK": s.dK, "dB": s.dB,
            "eigenvalues": {k: [complex(e) if isinstance(e, complex) else float(e) for e in v]
                            for k, v in self.eigenvalues.items()},
            "damping": self.damping,
            "visible_eigenvector": bool(self.visible),
            "visible_eigenvectors": [asdict_v(v) for v in self.visible],
            "theorem1_conditions": self.conditions,
            "Lambda1": self.Lambda1, "Lambda2": self.Lambda2, "Lambda": self.Lambda,
            "Lambda_appendix_b": self.Lambda_appendix_b, "Lambda_numerical": self.Lambda_numerical,
            "rotation_period": self.rotation_period, "guas": self.guas, "case": self.case,
            "notes": list(self.notes),
        }
        if self.iss is not None:
            d["iss"] = {"c": self.iss.c, "rate": self.iss.rate, "gain": self.iss.gain, "method": self.iss.method}
        return d

    def summary(self) -> str:
        s = self.system
        lines = [
            f"switched error system 002 (9)-(11): K1 = {s.K1:.6g}, B1 = {s.B1:.6g}, K2 = {s.K2:.6g}, B2 = {s.B2:.6g}",
            f"  subsystem 1 ({self.damping[1]}): eigenvalues {_fmt_ev(self.eigenvalues[1])}",
            f"  subsystem 2 ({self.damping[2]}): eigenvalues {_fmt_ev(self.eigenvalues[2])}",
        ]
        if self.visible:
            for v in self.visible:
                lines.append(f"  visible eigenvector in cone S_{v.cone}: v = ({v.vector[0]:.4g}, {v.vector[1]:.4g}), "
                             f"lambda = {v.eigenvalue:.6g}")
        else:
            lines.append("  no visible eigenvector (trajectories of Sigma^w rotate)")
        if self.Lambda is not None:
            lines.append(f"  Lambda1 = {self.Lambda1:.6g}, Lambda2 = {self.Lambda2:.6g}, "
                         f"Lambda = Lambda1^2 Lambda2^2 = {self.Lambda:.6g} (closed form (14)-(16))")
            lines.append(f"  Lambda by App. B (33)-(35) = {self.Lambda_appendix_b:.10g}, "
                         f"by integration of Sigma^w = {self.Lambda_numerical:.10g}, period {self.rotation_period:.6g} s")
        lines.append(f"  GUAS of Sigma^w (Theorem 1 {self.case}): {'yes' if self.guas else 'NO'}")
        if self.iss is not None:
            lines.append(f"  ISS (Theorem 2): |z(t)| <= {self.iss.c:.4g} e^(-{self.iss.rate:.4g} t)|z0| "
                         f"+ {self.iss.gain:.4g} sup|w|  ({self.iss.method}, sampled estimate)")
        lines.extend(f"  note: {n}" for n in self.notes)
        return "\n".join(lines)

    def phase_portrait(self, *, n_rot: float = 2.0, n: int = 4000) -> dict:
        """What the phase portrait shows: the real eigenpairs of ``A_1``, ``A_2`` and the worst-case
        trajectory from ``(1, 0)`` over ``n_rot`` rotation periods."""
        T = (self.rotation_period or 0.05) * n_rot
        _, z = worst_case_flow(self.system, [1.0, 0.0], T, n=n)
        return {"eigenvectors": {i: eigenvectors(self.system, i) for i in (1, 2)}, "z": z}

    def plot(self, ax=None, *, n_rot: float = 2.0):
        """Phase portrait of a worst-case trajectory with the switching lines and eigenvectors (draws only:
        the data come from :meth:`phase_portrait`)."""
        from ..plot.switched import plot_phase_portrait

        return plot_phase_portrait(self, self.phase_portrait(n_rot=n_rot), ax=ax)


def _fmt_ev(ev) -> str:
    return ", ".join(f"{complex(e).real:.6g}{complex(e).imag:+.6g}j" if isinstance(e, complex)
                     else f"{float(e):.6g}" for e in ev)


def analyze(sys: SwitchedErrorSystem, *, with_iss: bool = True, n_angles: int = 72) -> StabilityReport:
    """Theorem 1 (visible eigenvectors, Lambda three ways) and Theorem 2 (ISS constants)."""
    _require_applicable(sys)
    vis = visible_eigenvectors(sys)
    conds = theorem1_conditions(sys)
    notes = []
    if bool(vis) != any(conds.values()):
        notes.append("geometric visibility check and Theorem 1 i inequalities disagree "
                     f"(geometric: {bool(vis)}, inequalities: {conds})")
    ev = {1: list(sys.eigenvalues(1)), 2: list(sys.eigenvalues(2))}
    damping = {1: sys.damping_case(1), 2: sys.damping_case(2)}
    if vis:
        guas = all(v.eigenvalue < 0 for v in vis)
        report = StabilityReport(sys, ev, damping, vis, conds, None, None, None, None, None, None,
                                 guas, "i", None, notes)
    else:
        l1, l2, lam = lambda_closed_form(sys)
        lam_b = lambda_appendix_b(sys)[2]
        rot = lambda_numerical(sys)
        if not math.isclose(lam, rot.Lambda, rel_tol=1e-6):
            notes.append(f"closed form Lambda = {lam:.10g} and integrated Lambda = {rot.Lambda:.10g} "
                         "differ by more than 1e-6 relative")
        report = StabilityReport(sys, ev, damping, vis, conds, l1, l2, lam, lam_b, rot.Lambda, rot.period,
                                 bool(lam < 1), "ii", None, notes)
    if with_iss and report.guas:
        report = dataclasses.replace(report, iss=iss_bound(sys, n_angles=n_angles))
    return report
