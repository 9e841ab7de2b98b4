"""Static equilibria of 003 (1) with given outputs ``h(q) = y``.

An equilibrium has ``v = 0`` and satisfies the constraints and the force
balance; the servo-constraint inversion fixes them at ``T0``/``Tf`` (003 (36))
and the analysis linearizes there (zeros, operating points along a reference).
"""
from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..errors import ReferenceSignalError
from .auxiliary import cached


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
        self._Fd = ca.Function("equilibrium_dense", [w, y, md.theta], [res, ca.densify(ca.jacobian(res, w))])
        self.sizes = (n, l, p, m)
        self._one = None  # _Fd through buffers (numpy in and out, no DM conversions)
        self._maps: dict = {}  # _Fd mapped over K points through buffers, once per K (re-solves of a held inversion)

    def _at(self, K: int):
        """``_Fd`` at one point (``K = 0``) or mapped over ``K`` points (theta shared), called through
        buffers: numpy in and out, no ``DM`` conversions (built once per ``K``)."""
        from ..inversion.servo import Buffered, dense_map

        if K:
            if K not in self._maps:
                self._maps[K] = Buffered(dense_map(self._Fd, K, (2,)))
            return self._maps[K]
        if self._one is None:
            self._one = Buffered(self._Fd)
        return self._one

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

        F = self._at(0)

        def evaluate(w):
            r, Jm = F(w, y, th)
            r = r.ravel()
            return r, Jm, float(np.max(np.abs(r))) if r.size else 0.0

        r, Jm, res = evaluate(w)
        for _ in range(max_iter):
            if res < tol:
                break
            dw = np.linalg.lstsq(Jm, -r, rcond=None)[0]
            step = 1.0
            for _ in range(30):
                r2 = F(w + step * dw, y, th)[0].ravel()
                if np.max(np.abs(r2)) < (1 - 1e-4 * step) * res:
                    break
                step *= 0.5
            w = w + step * dw
            r, Jm, res = evaluate(w)    # the residual reported is the one of the last iterate
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
        F = self._at(K)

        def evaluate(Wv):
            r, Jm = F(Wv, Y, th)
            return r, Jm.reshape(nw, K, nw).transpose(1, 0, 2)

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


@dataclass(frozen=True)
class OperatingPoints:
    """Equilibria along a reference (see :func:`operating_points`).

    Iterating yields the configurations ``q`` (rows), so ``relative_degree(model, points=ops)``
    and ``lin.check_A1(..., points=ops)`` analyse the neighbourhood of the path of equilibria.

    Attributes
    ----------
    t : ndarray (K,)
        Times at which the reference was sampled (``t0 .. tf``).
    y, q, lam, mu, u : ndarray
        Outputs ``(K, m)``, configurations ``(K, n)``, multipliers ``(K, l)``, ``(K, p)`` and holding
        inputs ``(K, m)``.
    residual : ndarray (K,)
        Max-norm residual of the equilibrium equations at each point.
    in_region : ndarray of bool or None
        Whether each ``q`` lies in ``model.region`` (None without a region).
    """

    t: np.ndarray
    y: np.ndarray
    q: np.ndarray
    lam: np.ndarray
    mu: np.ndarray
    u: np.ndarray
    residual: np.ndarray
    in_region: np.ndarray | None = None

    def __len__(self) -> int:
        return self.q.shape[0]

    def __iter__(self):
        return iter(self.q)

    @property
    def start(self) -> np.ndarray:
        return self.q[0]

    @property
    def end(self) -> np.ndarray:
        return self.q[-1]


def operating_points(model, reference, count: int = 5, *, guess_q=None, tol: float = 1e-12) -> OperatingPoints:
    """The equilibria with ``h(q) = y_ref(t)`` at ``count`` times from ``reference.t0`` to ``reference.tf``.

    Continuation: each equilibrium is found by :class:`EquilibriumSolver` (Gauss-Newton) from
    the previous one moved along the tangent of the equilibrium path (``dw/dy`` from the
    Jacobian), so the branch chosen at the start (near ``guess_q``) is followed.  The first
    and last points are the start and end equilibria of the reference (003 (36)).

    Parameters
    ----------
    reference : Reference
        ``reference(t)`` returns ``y_ref`` as an ``(m, N)`` array; ``t0``, ``tf`` bound the transition.
    count : int
        Number of points (>= 2).
    guess_q : array (n), optional
        Start of Newton at ``t0`` (default zeros; pass a configuration on the intended branch,
        e.g. the scene's initial configuration, for mechanisms with several assembly modes).

    Raises
    ------
    ReferenceSignalError
        No equilibrium at some point (the reference leaves the reachable set or the branch
        ends); the points found before are kept in ``exc.partial``.
    """
    n, l, p, m = model.n, model.ell, model.p, model.m
    if int(count) != count or count < 2:
        raise ReferenceSignalError(f"operating_points needs count >= 2 (the start and end equilibria), got {count!r}")
    if not (callable(reference) and hasattr(reference, "t0") and hasattr(reference, "tf")):
        raise ReferenceSignalError(f"operating_points needs a Reference (callable with t0 and tf), got "
                                   f"{type(reference).__name__}")
    count = int(count)
    t = np.linspace(reference.t0, reference.tf, count)
    Y = np.asarray(reference(t), float).reshape(-1, count).T
    if Y.shape[1] != m:
        raise ReferenceSignalError(f"{model.name}: the reference has {Y.shape[1]} components, the model {m} outputs")
    solver = _solver(model)
    th = model.theta_values
    w = np.zeros(n + l + p + m)
    if guess_q is not None:
        gq = np.asarray(guess_q, float).ravel()
        if gq.size != n:
            raise ReferenceSignalError(f"{model.name}: guess_q has {gq.size} entries, expected n = {n}")
        w[:n] = gq
    W: list = []
    res: list = []
    sel = np.zeros((l + p + m + n, m))
    sel[l + p:l + p + m] = np.eye(m)        # d residual / d y = -sel
    for k in range(count):
        if k:
            Jw = solver._at(0)(w, Y[k - 1], th)[1]
            w = w + np.linalg.lstsq(Jw, sel @ (Y[k] - Y[k - 1]), rcond=None)[0]
        try:
            X, r = solver.solve(Y[k], guess_w=w, theta=th, tol=tol,
                                where=f" at t = {t[k]:.6g} (operating point {k + 1} of {count})")
        except ReferenceSignalError as exc:
            raise ReferenceSignalError(str(exc), partial=_points(model, t[:k], Y[:k], W, res),
                                       diagnostics=exc.diagnostics) from None
        w = np.concatenate([X[:n], X[2 * n:]])
        W.append(w)
        res.append(r)
    return _points(model, t, Y, W, res)


def _points(model, t, Y, W, res) -> OperatingPoints:
    n, l, p = model.n, model.ell, model.p
    W = np.array(W).reshape(len(W), -1)
    q = W[:, :n]
    inside = None if model.region is None else np.array([model.region.contains(qk) for qk in q], bool)
    return OperatingPoints(t=np.asarray(t), y=np.asarray(Y), q=q, lam=W[:, n:n + l], mu=W[:, n + l:n + l + p],
                           u=W[:, n + l + p:], residual=np.asarray(res, float), in_region=inside)


def _solver(model) -> EquilibriumSolver:
    """One solver per symbolic model (the residual Function does not depend on parameter values)."""
    return cached(model, ("equilibrium_solver",), lambda: EquilibriumSolver(model))
