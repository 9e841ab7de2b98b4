"""The clearance-free system of an open system with clearances, 000 Sect. 2.2 (6).

Closing the clearances gives holonomic constraints ``g(q) = 0`` (two per joint with clearance).
With ``q`` split into independent coordinates ``q_wc`` (``dim q_wc = n - rank dg/dq``) and the
rest ``q_bar = Omega(q_wc)`` (000's coordinate partitioning, ``z_2 = q_wc``), the clearance-free
dynamics (6) are

    M_wc(q_wc) q_wc'' = f_wc(q_wc, q_wc') + E_wc(q_wc) tau,
    M_wc = J^T M(q) J,   E_wc = J^T E(q),   f_wc = J^T (f(q, J q_wc') - M(q) J' q_wc'),

with ``J = dq/dq_wc`` (identity rows for ``q_wc``, ``dOmega/dq_wc = -(dg/dq_bar)^-1 dg/dq_wc`` for
``q_bar``, by the implicit function theorem; the constraint forces drop out because ``dg/dq J = 0``).
Since the open system's ``M`` is block-diagonal over its subsystems,
``M_wc = sum_i J_i^T M_i J_i`` (``J_i`` the rows of ``J`` of subsystem ``S_i``): with
``q_wc = q_1`` this is 000's ``M_wc = M_1 + dOmega/dz_2^T blockdiag(M_2, M_3) dOmega/dz_2``.
``Omega`` itself is evaluated by Newton's method on ``g(q_bar, q_wc) = 0``.
"""
from __future__ import annotations

from typing import Sequence

import casadi as ca
import numpy as np

from ..errors import ContactError, DimensionError, ModelError


class ClearanceFree:
    """The clearance-free system (6) of ``model`` under the closure constraints ``closure``.

    Parameters
    ----------
    model : Model
        The open system (000 (1)).
    closure : casadi.SX
        ``g(q)``: the constraints that close the clearances, in ``model.q`` and ``model.theta``
        (:attr:`invctl.contact.linkage.Linkage.closure` for linkage models).
    independent : sequence of int
        Indices of ``q_wc`` in ``q``; the others are ``q_bar = Omega(q_wc)``.
    """

    def __init__(self, model, closure, independent: Sequence[int]):
        self.model = model
        g = ca.SX(closure)
        n = model.n
        self.independent = [int(i) for i in independent]
        if len(set(self.independent)) != len(self.independent) or not all(0 <= i < n for i in self.independent):
            raise DimensionError(f"independent coordinates {list(independent)} must be distinct indices in [0, {n})")
        self.dependent = [i for i in range(n) if i not in self.independent]
        if g.shape[0] != len(self.dependent):
            raise ModelError(f"{g.shape[0]} closure constraints for {len(self.dependent)} dependent coordinates: "
                             "choose as many independent coordinates as the clearance-free system has DoFs "
                             f"(n - rank dg/dq = {n} - {g.shape[0]} for independent constraints)")
        q, th = model.q, model.theta
        Gq = ca.jacobian(g, q)
        qd = ca.SX.sym("qd", n)
        gamma = ca.mtimes(ca.jacobian(ca.mtimes(Gq, qd), q), qd)   # d/dt(dg/dq) q'
        self._g = ca.Function("closure", [q, th], [g, Gq])
        self._gamma = ca.Function("closure_gamma", [q, qd, th], [gamma])
        self.k = len(self.independent)

    def _th(self, theta):
        return self.model.theta_values if theta is None else np.asarray(theta, float)

    def residual(self, q, theta=None) -> float:
        """``max |g(q)|``."""
        return float(np.max(np.abs(np.array(self._g(np.asarray(q, float), self._th(theta))[0])), initial=0.0))

    def configuration(self, q_wc, guess, *, theta=None, tol: float = 1e-12, max_iter: int = 50) -> np.ndarray:
        """``q`` with ``q[independent] = q_wc`` and ``g(q) = 0`` (Newton from ``guess`` on ``q_bar``).

        Raises
        ------
        ContactError
            Newton does not reach ``|g| <= tol`` (no closed configuration near ``guess``: the
            clearance-free mechanism cannot be assembled there); ``partial`` is the last iterate.
        """
        th = self._th(theta)
        q = np.array(guess, float).ravel().copy()
        if q.size != self.model.n:
            raise DimensionError(f"guess has length {q.size}, model has n = {self.model.n}")
        q[self.independent] = np.asarray(q_wc, float).ravel()
        dep = self.dependent
        res = np.inf
        for _ in range(max_iter):
            g, G = (np.array(a) for a in self._g(q, th))
            g = g.ravel()
            res = float(np.max(np.abs(g), initial=0.0))
            if res <= tol:
                return q
            step, *_ = np.linalg.lstsq(G[:, dep], -g, rcond=None)
            q[dep] += step
        raise ContactError(f"clearance-free configuration: Newton on the closure constraints stopped at |g| = "
                           f"{res:.3g} after {max_iter} iterations (q_wc = {np.round(q_wc, 6).tolist()}); start "
                           "from a closer guess or check that the mechanism can be assembled there",
                           partial=q, diagnostics={"residual": res})

    def jacobian(self, q, theta=None) -> np.ndarray:
        """``J = dq/dq_wc`` at a closed configuration ``q`` (n x k)."""
        th = self._th(theta)
        G = np.array(self._g(np.asarray(q, float), th)[1])
        dep, ind = self.dependent, self.independent
        Gd = G[:, dep]
        if np.linalg.matrix_rank(Gd) < len(dep):
            raise ContactError(f"dg/dq_bar is singular at q = {np.round(q, 6).tolist()}: the chosen independent "
                               f"coordinates {ind} do not parametrize the clearance-free system here")
        J = np.zeros((self.model.n, self.k))
        J[ind, range(self.k)] = 1.0
        J[dep, :] = -np.linalg.solve(Gd, G[:, ind])
        return J

    def mass_matrix(self, q, theta=None) -> np.ndarray:
        """``M_wc = J^T M J`` (000 (6))."""
        th = self._th(theta)
        J = self.jacobian(q, th)
        return J.T @ np.array(self.model.function("M")(np.asarray(q, float), th)) @ J

    def blocks(self, q, subsystems: Sequence[Sequence[int]], theta=None) -> list:
        """``J_i^T M_i J_i`` for each subsystem (coordinate indices); they sum to ``M_wc`` when ``M`` is
        block-diagonal over these subsystems."""
        th = self._th(theta)
        J = self.jacobian(q, th)
        M = np.array(self.model.function("M")(np.asarray(q, float), th))
        return [J[list(s)].T @ M[np.ix_(list(s), list(s))] @ J[list(s)] for s in subsystems]

    def input_matrix(self, q, theta=None) -> np.ndarray:
        """``E_wc = J^T E`` (000 (6))."""
        th = self._th(theta)
        B = np.array(self.model.function("B")(np.asarray(q, float), th)).reshape(self.model.n, self.model.m)
        return self.jacobian(q, th).T @ B

    def forces(self, q, v_wc, theta=None) -> np.ndarray:
        """``f_wc = J^T (f(q, J v_wc) - M J' v_wc)``: Coriolis, centrifugal and potential forces of (6)."""
        th = self._th(theta)
        q = np.asarray(q, float)
        J = self.jacobian(q, th)
        qd = J @ np.asarray(v_wc, float).ravel()
        G = np.array(self._g(q, th)[1])
        gam = np.array(self._gamma(q, qd, th)).ravel()
        acc = np.zeros(self.model.n)                # J' v_wc: q'' when q_wc'' = 0
        acc[self.dependent] = -np.linalg.solve(G[:, self.dependent], gam)
        M = np.array(self.model.function("M")(q, th))
        f = np.array(self.model.function("f")(q, qd, th)).ravel()
        return J.T @ (f - M @ acc)

    def assumption1(self, q, theta=None) -> dict:
        """000 Assumption 1: ``p >= dim q_wc`` and ``rank E_wc = dim q_wc``."""
        E = self.input_matrix(q, theta)
        rank = int(np.linalg.matrix_rank(E, tol=1e-9 * max(1.0, np.abs(E).max()))) if E.size else 0
        return {"dim_q_wc": self.k, "p": self.model.m, "rank_E_wc": rank,
                "holds": bool(self.model.m >= self.k and rank == self.k)}
