"""Static equilibria of 003 (1) with given outputs ``h(q) = y``.

An equilibrium has ``v = 0`` and satisfies the constraints and the force
balance; the servo-constraint inversion fixes them at ``T0``/``Tf`` (003 (36))
and the analysis linearizes there (zeros, operating points along a reference).
"""
from __future__ import annotations

import casadi as ca
import numpy as np

from ..errors import ReferenceSignalError


class EquilibriumSolver:
    """Equilibria of 003 (1) with the servo constraints: ``v = 0``,

        g(q) = 0,   j(q) = 0,   h(q) = y,   f(q, 0) + G^T lam + J^T mu + B u = 0,

    solved for ``(q, lam, mu, u)`` by Gauss-Newton with exact Jacobians.
    """

    def __init__(self, model):
        self.model = model
        md = model
        n, l, p, m = md.n, md.ell, md.p, md.m
        w = ca.SX.sym("w", n + l + p + m)
        y = ca.SX.sym("y", m)
        q = w[:n]
        lam, mu, u = w[n:n + l], w[n + l:n + l + p], w[n + l + p:]
        zero_v = ca.SX.zeros(n)
        sub = lambda e: ca.substitute([ca.SX(e)], [md.q, md.v], [q, zero_v])[0]  # noqa: E731
        bal = sub(md.f) + ca.mtimes(sub(md.B), u)
        if l:
            bal = bal + ca.mtimes(sub(md.G).T, lam)
        if p:
            bal = bal + ca.mtimes(sub(md.J).T, mu)
        res = ca.vertcat(sub(md.g) if l else ca.SX(0, 1), sub(md.j) if p else ca.SX(0, 1), sub(md.h) - y, bal)
        self._F = ca.Function("equilibrium", [w, y, md.theta], [res, ca.jacobian(res, w)])
        self.sizes = (n, l, p, m)

    def solve(self, y, guess_q=None, guess_w=None, *, theta=None, tol: float = 1e-12, max_iter: int = 50,
              where: str = ""):
        """Equilibrium at output ``y``: returns ``X`` (q, 0, lam, mu, u) and the residual norm.

        Raises
        ------
        ReferenceSignalError
            No equilibrium found (``y`` outside the reachable workspace or a bad guess).
        """
        n, l, p, m = self.sizes
        th = self.model.theta_values if theta is None else np.asarray(theta, float)
        if guess_w is not None:
            w = np.array(guess_w, float).ravel()
        else:
            w = np.zeros(n + l + p + m)
            if guess_q is not None:
                w[:n] = np.asarray(guess_q, float).ravel()
        y = np.asarray(y, float).ravel()
        res = np.inf
        for _ in range(max_iter):
            r, Jm = self._F(w, y, th)
            r, Jm = np.array(r).ravel(), np.array(Jm)
            res = float(np.max(np.abs(r))) if r.size else 0.0
            if res < tol:
                break
            dw = np.linalg.lstsq(Jm, -r, rcond=None)[0]
            step = 1.0
            for _ in range(30):
                r2 = np.array(self._F(w + step * dw, y, th)[0]).ravel()
                if np.max(np.abs(r2)) < (1 - 1e-4 * step) * res:
                    break
                step *= 0.5
            w = w + step * dw
        if not np.isfinite(res) or res > max(1e3 * tol, 1e-9):
            raise ReferenceSignalError(
                f"no equilibrium with h(q) = y_ref = {np.round(y, 6).tolist()}{where}: the servo and loop "
                f"constraints are not solvable (residual {res:.3g} after {max_iter} Gauss-Newton steps). "
                "The reference is probably outside the reachable workspace; check y_ref or give a better "
                "initial configuration", diagnostics={"residual": res, "y": y.tolist()})
        X = np.concatenate([w[:n], np.zeros(n), w[n:]])
        return X, res

    def solve_many(self, Y, W0, *, theta=None, tol: float = 1e-12, max_iter: int = 30):
        """Newton on many equilibria at once (outputs ``Y`` (m, K), guesses ``W0`` (n+l+p+m, K)):
        one mapped evaluation and one batched dense solve per iteration, a halving line search
        per point.  Returns ``(W, residuals)``; points that do not converge keep their last
        iterate and a residual above ``tol`` (the caller decides)."""
        th = self.model.theta_values if theta is None else np.asarray(theta, float)
        Y = np.atleast_2d(np.asarray(Y, float))
        W = np.array(W0, float)
        nw, K = W.shape
        F = self._F.map(K)

        def evaluate(Wv):
            r, Jm = F(Wv, Y, th)
            return np.array(r), np.array(Jm).reshape(nw, K, nw).transpose(1, 0, 2)

        r, Jm = evaluate(W)
        res = np.max(np.abs(r), axis=0)
        for _ in range(max_iter):
            if np.all(res < tol):
                break
            try:
                dW = -np.linalg.solve(Jm, r.T[:, :, None])[:, :, 0].T
            except np.linalg.LinAlgError:
                dW = -np.stack([np.linalg.lstsq(Jm[k], r[:, k], rcond=None)[0] for k in range(K)], axis=1)
            step = np.where(res < tol, 0.0, 1.0)
            for _ in range(30):
                r2, J2 = evaluate(W + step * dW)
                res2 = np.max(np.abs(r2), axis=0)
                bad = (step > 0) & ~(res2 < (1 - 1e-4 * step) * res)
                if not np.any(bad):
                    break
                step = np.where(bad, 0.5 * step, step)
            W, r, Jm, res = W + step * dW, r2, J2, res2
        return W, res
