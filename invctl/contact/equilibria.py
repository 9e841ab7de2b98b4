"""Rest points of a Lagrangian complementarity system under a static feedback, 000 (40)-(41), Lemma 2.

With the closed-loop static force ``F(q) = f(q, 0) + B(q) u(q, 0)`` (e.g. for PD + gravity
compensation (36): ``-(K_p (q_1 - q_1d), G_4(q_4), G_5(q_5))``), the equilibria are the solutions of
the generalized equation

    F(q) + grad f(q) lam = 0,   0 <= f(q)  _|_  lam >= 0,                     (40)

i.e. ``0 in -F(q) + N_Phi(q)`` (41).  :func:`static_equilibrium` solves it from a starting
configuration (for instance the end of a run) by an active-set Newton method whose steps are
minimum-norm least-squares steps, so that where the solutions form a continuum (no potential acts
on some bodies: journals anywhere in their bearings, 000 after (41)) it returns a nearby point of
the set; ``Equilibrium.dimension`` is the local dimension of the solution set (the nullity of the
Newton matrix at the solution: 0 for an isolated equilibrium).  :func:`equilibrium_points` collects
the distinct equilibria reached from several starts.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import casadi as ca
import numpy as np

from ..errors import ContactError, DimensionError


@dataclass(frozen=True)
class Equilibrium:
    """A solution of (40).

    Attributes
    ----------
    q : ndarray
    lam : ndarray
        Multipliers of all contacts (zero off the active set).
    active : ndarray of int
        Contacts with ``f_i(q) = 0`` carrying ``lam_i >= 0``.
    residual : float
        ``|F(q) + grad f lam|`` (max norm).
    gap_min : float
        Smallest gap (>= -tol).
    dimension : int
        Local dimension of the set of equilibria at ``q``.
    distance : float
        ``|q - q_start|`` (Euclidean).
    """

    q: np.ndarray
    lam: np.ndarray
    active: np.ndarray
    residual: float
    gap_min: float
    dimension: int
    distance: float


def static_force(model, u) -> ca.SX:
    """``F(q) = f(q, 0) + B(q) u(q, 0)`` for an input expression ``u`` in ``model.q, model.v`` (and
    parameters), without time dependence."""
    zero = ca.SX.zeros(model.n)
    return ca.substitute(model.f + ca.mtimes(model.B, ca.SX(u)), model.v, zero)


def static_equilibrium(model, force, q_start, *, theta=None, active_tol: float = 1e-6, tol: float = 1e-10,
                       max_iter: int = 60, max_changes: int = 30) -> Equilibrium:
    """The equilibrium (40) next to ``q_start`` (module docstring).

    Parameters
    ----------
    force : casadi.SX
        ``F(q)`` in ``model.q`` and ``model.theta`` (see :func:`static_force`).
    active_tol : float
        Contacts with ``f_i(q_start) <= active_tol`` start in the active set.

    Raises
    ------
    ContactError
        Newton does not converge or the active-set search cycles; ``partial`` is the last iterate.
    """
    n, mu = model.n, len(model.gaps)
    th = model.theta_values if theta is None else np.asarray(theta, float)
    q = np.array(q_start, float).ravel()
    if q.size != n:
        raise DimensionError(f"q_start has length {q.size}, model has n = {n}")
    q0 = q.copy()
    F = ca.SX(force)
    gap = ca.vertcat(*[g.expr for g in model.gaps]) if mu else ca.SX(0, 1)
    W = ca.jacobian(gap, model.q).T
    lam_s = ca.SX.sym("lam", mu)
    R = F + ca.mtimes(W, lam_s)
    fn = ca.Function("eq", [model.q, lam_s, model.theta], [R, ca.jacobian(R, model.q), gap, W])
    g0 = np.array(fn(q, np.zeros(mu), th)[2]).ravel()
    active = sorted(np.flatnonzero(g0 <= active_tol).tolist())
    lam = np.zeros(mu)
    seen = set()
    for _ in range(max_changes):
        A = list(active)
        res = np.inf
        for _ in range(max_iter):
            r, Rq, g, Wn = (np.array(a) for a in fn(q, lam, th))
            r, g = r.ravel(), g.ravel()
            Wa = Wn.reshape(n, mu)[:, A]
            rhs = np.concatenate([r, g[A]])
            res = float(np.max(np.abs(rhs), initial=0.0))
            if res <= tol * max(1.0, np.abs(lam).max()):
                break
            K = np.block([[Rq, Wa], [Wa.T, np.zeros((len(A), len(A)))]])
            step, *_ = np.linalg.lstsq(K, -rhs, rcond=None)
            q = q + step[:n]
            lam[A] += step[n:]
        else:
            raise ContactError(f"static equilibrium: Newton did not converge (residual {res:.3g}) with active set {A}",
                               partial=q, diagnostics={"residual": res, "active": A})
        g = np.array(fn(q, lam, th)[2]).ravel()
        neg = [i for i in A if lam[i] < -tol * max(1.0, np.abs(lam).max())]
        viol = [i for i in range(mu) if i not in A and g[i] < -tol]
        if not neg and not viol:
            K = np.block([[Rq, Wa], [Wa.T, np.zeros((len(A), len(A)))]])
            s = np.linalg.svd(K, compute_uv=False)
            dim = int(np.count_nonzero(s <= 1e-8 * max(1.0, s.max())))
            lam[[i for i in range(mu) if i not in A]] = 0.0
            return Equilibrium(q, np.maximum(lam, 0.0), np.array(A, int), res, float(g.min(initial=np.inf)), dim,
                               float(np.linalg.norm(q - q0)))
        if neg:
            i = min(neg, key=lambda i: lam[i])
            active.remove(i)
            lam[i] = 0.0
        else:
            active = sorted(active + [min(viol, key=lambda i: g[i])])
        key = tuple(active)
        if key in seen:
            raise ContactError(f"static equilibrium: the active-set search cycles at {key}", partial=q)
        seen.add(key)
    raise ContactError("static equilibrium: too many active-set changes", partial=q)


def equilibrium_points(model, force, starts: Sequence, *, theta=None, same_tol: float = 1e-7, **kw) -> list:
    """Distinct equilibria (40) reached from ``starts`` (failures are skipped), sorted by the norm
    of their multipliers."""
    found: list[Equilibrium] = []
    for qs in starts:
        try:
            e = static_equilibrium(model, force, qs, theta=theta, **kw)
        except ContactError:
            continue
        if all(np.linalg.norm(e.q - o.q) > same_tol for o in found):
            found.append(e)
    return sorted(found, key=lambda e: float(np.linalg.norm(e.lam)))
