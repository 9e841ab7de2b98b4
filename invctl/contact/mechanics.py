"""Gap functions, Delassus matrices, the contact LCP and Moreau's impact law.

Sign conventions follow :class:`invctl.model.Model`: the dynamics are
``M(q) v' = f(q, v) + B(q) u + G(q)^T lam_b + W(q) lam_n`` with the gap
gradients ``W = grad f(q) = (d gaps / dq)^T`` (n x m_u), i.e. 000 (1) with
``f = -C v - g``, ``E = B`` and ``grad h = G^T``.

* Delassus matrix (7): ``D = W^T M^{-1} W``; with bilateral constraints (8):
  ``D_c = W^T M^{-1} [I - G^T (G M^{-1} G^T)^{-1} G M^{-1}] W``.
* Contact LCP (7): ``0 <= lam' _|_ D lam' + w >= 0`` with
  ``w = d/dt(W^T) v + W^T a_free`` (``a_free``: acceleration without contact
  forces, bilateral constraints enforced).
* Moreau's impact law (4)/(5): ``v+ = v- + M^{-1} W p`` with
  ``0 <= W^T v+ + e W^T v-  _|_  p >= 0`` on the contacts with ``f_i = 0``
  and ``W_i^T v- <= 0``; for a common ``e`` the kinetic energy changes by
  ``-1/2 (1-e)/(1+e) sigma^T M sigma``, ``sigma = v+ - v-`` (000 (39)).
"""
from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..errors import ContactError, DimensionError, ModelError
from .lcp import solve_lcp


def energy_loss_39(sigma, M, e: float) -> float:
    """Kinetic energy jump ``-1/2 (1-e)/(1+e) sigma^T M sigma`` of 000 (39)."""
    sigma = np.asarray(sigma, float).ravel()
    return float(-0.5 * (1.0 - e) / (1.0 + e) * sigma @ np.asarray(M, float) @ sigma)


@dataclass(frozen=True)
class ImpactResult:
    """Outcome of Moreau's impact law at one instant.

    Attributes
    ----------
    v_plus : ndarray
        Post-impact velocity.
    p : ndarray
        Impulses of all contacts (zero for contacts not involved).
    involved : ndarray of bool
        Contacts in the impact LCP (``f_i = 0`` and ``W_i^T v- <= 0``).
    kinetic_jump : float
        ``T(v+) - T(v-)`` (never positive for ``e`` in [0, 1]).
    predicted_jump : float or None
        ``-1/2 (1-e)/(1+e) sigma^T M sigma`` (000 (39)) when all involved
        contacts share one ``e``; None otherwise.
    unique : bool or None
        Uniqueness of the impact LCP (P-matrix test).
    """

    v_plus: np.ndarray
    p: np.ndarray
    involved: np.ndarray
    kinetic_jump: float
    predicted_jump: float | None
    unique: bool | None


@dataclass(frozen=True)
class ContactForces:
    """Solution of the contact LCP (7) at one state."""

    lam: np.ndarray
    D: np.ndarray
    w: np.ndarray
    active: np.ndarray
    acceleration: np.ndarray
    unique: bool | None


class ContactSystem:
    """Contact view of a :class:`~invctl.model.Model` with ``gaps``.

    Parameters
    ----------
    model : Model
        A model whose ``gaps`` are the unilateral constraints ``f_i(q) >= 0``;
        bilateral constraints ``g(q) = 0`` are taken into account (8).
    gap_tol : float
        A gap is considered closed when ``f_i <= gap_tol``.
    vel_tol : float
        A normal velocity is considered zero when ``|W_i^T v| <= vel_tol``.
    """

    def __init__(self, model, *, gap_tol: float = 1e-12, vel_tol: float = 1e-10):
        if not model.gaps:
            raise ModelError(f"model {model.name!r} has no unilateral constraints (gaps); nothing to contact")
        if model.p:
            raise ModelError(f"model {model.name!r}: non-holonomic constraints are not supported by contact mechanics")
        self.model = model
        self.gap_tol = float(gap_tol)
        self.vel_tol = float(vel_tol)
        q, v, th = model.q, model.v, model.theta
        self.gap = ca.vertcat(*[gp.expr for gp in model.gaps])
        self.W = ca.jacobian(self.gap, q).T
        self.Wdot_v = ca.mtimes(ca.jacobian(ca.mtimes(self.W.T, v), q), v)
        e = []
        for gp in model.gaps:
            r = gp.restitution
            e.append(model.params[r] if isinstance(r, str) else ca.SX(float(r)))
        self.e = ca.vertcat(*e)
        self.f_gap = ca.Function("gaps", [q, th], [self.gap], ["q", "theta"], ["gaps"])
        self.f_W = ca.Function("W", [q, th], [self.W], ["q", "theta"], ["W"])
        self.f_Wdot_v = ca.Function("Wdot_v", [q, v, th], [self.Wdot_v], ["q", "v", "theta"], ["Wdot_v"])
        self.f_e = ca.Function("restitution", [th], [self.e], ["theta"], ["e"])
        self.names = [gp.name for gp in model.gaps]

    @property
    def m_u(self) -> int:
        """Number of unilateral constraints."""
        return self.gap.shape[0]

    # -------------------------------------------------------------- evaluation
    def _theta(self, theta=None):
        return self.model.theta_values if theta is None else np.asarray(theta, float)

    def _q(self, q):
        q = np.asarray(q, float).ravel()
        if q.size != self.model.n:
            raise DimensionError(f"q has length {q.size}, model {self.model.name!r} has n = {self.model.n}")
        return q

    def gaps(self, q, theta=None) -> np.ndarray:
        """Gap values ``f(q)``."""
        return np.array(self.f_gap(self._q(q), self._theta(theta))).ravel()

    def gradients(self, q, theta=None) -> np.ndarray:
        """``grad f(q)`` (n x m_u), columns are the contact normals in q-space."""
        return np.array(self.f_W(self._q(q), self._theta(theta))).reshape(self.model.n, self.m_u)

    def restitution(self, theta=None) -> np.ndarray:
        """Restitution coefficients of the contacts."""
        return np.array(self.f_e(self._theta(theta))).ravel()

    def _mass_and_constraints(self, q, theta):
        th = self._theta(theta)
        M = np.array(self.model.function("M")(q, th))
        G = np.array(self.model.function("G")(q, th)).reshape(self.model.ell, self.model.n)
        return M, G

    def _projected_inverse(self, M, G):
        """``Pi = M^-1 - M^-1 G^T (G M^-1 G^T)^-1 G M^-1`` (000 (8))."""
        Minv = np.linalg.inv(M)
        if G.shape[0] == 0:
            return Minv
        S = G @ Minv @ G.T
        if np.linalg.matrix_rank(S) < S.shape[0]:
            raise ContactError("bilateral constraints are dependent (G M^-1 G^T singular; 000 Assumption 2)")
        return Minv - Minv @ G.T @ np.linalg.solve(S, G @ Minv)

    def delassus(self, q, active=None, theta=None) -> np.ndarray:
        """Delassus matrix (7), or (8) with bilateral constraints, of the contacts ``active``
        (indices or bool mask; default all)."""
        q = self._q(q)
        M, G = self._mass_and_constraints(q, theta)
        W = self.gradients(q, theta)
        idx = self._index(active)
        Wa = W[:, idx]
        return Wa.T @ self._projected_inverse(M, G) @ Wa

    def _index(self, active):
        if active is None:
            return np.arange(self.m_u)
        a = np.asarray(active)
        return np.flatnonzero(a) if a.dtype == bool else a.astype(int)

    def check_independence(self, q, active=None, theta=None) -> float:
        """Smallest eigenvalue of the (bilateral-projected) Delassus matrix of the
        active contacts; raises :class:`ContactError` when it is not positive
        (000 Assumption 2 violated: the contact LCP may have several solutions)."""
        D = self.delassus(q, active, theta)
        if D.size == 0:
            return np.inf
        ev = float(np.linalg.eigvalsh(0.5 * (D + D.T)).min())
        if ev <= 1e-12 * max(1.0, np.abs(D).max()):
            raise ContactError(
                f"000 Assumption 2 fails at q = {np.round(q, 6).tolist()}: active constraints are dependent "
                f"(smallest Delassus eigenvalue {ev:.3g})", diagnostics={"min_eig": ev})
        return ev

    def closed(self, q, theta=None) -> np.ndarray:
        """Mask of closed gaps ``f_i(q) <= gap_tol``."""
        return self.gaps(q, theta) <= self.gap_tol

    # ---------------------------------------------------------- contact LCP
    def contact_forces(self, q, v, u=None, *, active=None, theta=None) -> ContactForces:
        """Solve the contact LCP (7) (with (8) when bilateral constraints exist).

        ``active`` defaults to the contacts with a closed gap and zero normal
        velocity (those that can carry a force without an impact).
        """
        q = self._q(q)
        v = np.asarray(v, float).ravel()
        th = self._theta(theta)
        mdl = self.model
        u = np.zeros(mdl.m) if u is None else np.asarray(u, float).ravel()
        W = self.gradients(q, th)
        if active is None:
            active = self.closed(q, th) & (np.abs(W.T @ v) <= self.vel_tol)
        idx = self._index(active)
        M, G = self._mass_and_constraints(q, th)
        Pi = self._projected_inverse(M, G)
        F = np.array(mdl.function("f")(q, v, th)).ravel() + np.array(mdl.function("B")(q, th)).reshape(mdl.n, mdl.m) @ u
        Minv = np.linalg.inv(M)
        a_free = Pi @ F
        if mdl.ell:
            Gdot_v = np.array(ca.Function("gdv", [mdl.q, mdl.v, mdl.theta], [
                ca.mtimes(ca.jacobian(ca.mtimes(mdl.G, mdl.v), mdl.q), mdl.v)])(q, v, th)).ravel()
            S = G @ Minv @ G.T
            a_free = a_free - Minv @ G.T @ np.linalg.solve(S, Gdot_v)
        Wa = W[:, idx]
        D = Wa.T @ Pi @ Wa
        w = np.array(self.f_Wdot_v(q, v, th)).ravel()[idx] + Wa.T @ a_free
        sol = solve_lcp(D, w)
        lam = np.zeros(self.m_u)
        lam[idx] = sol.z
        acc = a_free + Pi @ Wa @ sol.z
        mask = np.zeros(self.m_u, bool)
        mask[idx] = sol.active
        return ContactForces(lam, D, w, mask, acc, sol.unique)

    # ---------------------------------------------------------- impact law
    def impact(self, q, v_minus, *, theta=None, e=None, involved=None) -> ImpactResult:
        """Moreau's impact law (4)/(5) for single or simultaneous impacts.

        Parameters
        ----------
        q, v_minus : array_like
            Configuration and pre-impact velocity.
        e : float or array, optional
            Restitution coefficient(s); default: the model's.
        involved : mask or indices, optional
            Contacts in the impact LCP; default: closed gaps with
            ``W_i^T v- <= vel_tol`` (000 (4)).
        """
        q = self._q(q)
        v = np.asarray(v_minus, float).ravel()
        th = self._theta(theta)
        W = self.gradients(q, th)
        U = W.T @ v
        if involved is None:
            involved = self.closed(q, th) & (U <= self.vel_tol)
        idx = self._index(involved)
        ev = self.restitution(th) if e is None else np.broadcast_to(np.asarray(e, float), (self.m_u,)).copy()
        if np.any((ev < 0) | (ev > 1)):
            raise ContactError(f"restitution coefficients must lie in [0, 1], got {ev.tolist()}")
        M, G = self._mass_and_constraints(q, th)
        Pi = self._projected_inverse(M, G)
        Wa = W[:, idx]
        D = Wa.T @ Pi @ Wa
        b = (1.0 + ev[idx]) * U[idx]
        sol = solve_lcp(D, b)
        p = np.zeros(self.m_u)
        p[idx] = sol.z
        vp = v + Pi @ Wa @ sol.z
        sigma = vp - v
        jump = float(0.5 * vp @ M @ vp - 0.5 * v @ M @ v)
        ee = ev[idx][sol.z > 0]
        pred = energy_loss_39(sigma, M, float(ee[0])) if ee.size and np.allclose(ee, ee[0]) else (0.0 if not ee.size else None)
        mask = np.zeros(self.m_u, bool)
        mask[idx] = True
        return ImpactResult(vp, p, mask, jump, pred, sol.unique)
