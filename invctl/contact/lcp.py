"""Linear complementarity problems ``0 <= z  _|_  w = A z + b >= 0``.

Two families of solvers:

* exact numeric solvers for the contact LCP (000 (7)) and the impact LCP
  (000 (4)): complete enumeration of active sets (``m <= 12``) and Lemke's
  complementary pivoting (any size), with a uniqueness check (P-matrix test;
  000 Assumption 2 makes the Delassus matrix positive definite, hence P);
* a branch-free symbolic solver (:func:`lcp_sx`) for use *inside* a compiled
  time step: enumeration of the ``2^m`` active sets with ``if_else``
  selection, exact (no iteration error) for a P-matrix, practical for
  ``m <= 4`` contacts (16 candidate systems).  For more contacts
  :func:`lcp_sx` falls back to a fixed number of projected Gauss-Seidel
  sweeps, whose residual is reported by the stepper; the enumeration is the
  default and the one tested against the exact solver.
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..errors import ContactError, DimensionError

__all__ = ["LCPSolution", "solve_lcp", "is_p_matrix", "lcp_sx", "lcp_residual"]


@dataclass(frozen=True)
class LCPSolution:
    """Solution of ``0 <= z _|_ A z + b >= 0``.

    Attributes
    ----------
    z, w : ndarray
        The solution and ``w = A z + b``.
    active : ndarray of bool
        ``z > 0`` pattern (the active contacts).
    residual : float
        ``max(|min(z, w)|)`` (zero for an exact solution).
    unique : bool or None
        True when ``A`` is a P-matrix (unique solution for every ``b``);
        None when not checked (too large).
    method : str
        ``"enumeration"`` or ``"lemke"``.
    """

    z: np.ndarray
    w: np.ndarray
    active: np.ndarray
    residual: float
    unique: bool | None
    method: str


def lcp_residual(A, b, z) -> float:
    """``max |min(z, A z + b)|``: zero iff ``z`` solves the LCP."""
    z = np.asarray(z, float)
    w = np.asarray(A, float) @ z + np.asarray(b, float)
    return float(np.max(np.abs(np.minimum(z, w)))) if z.size else 0.0


def is_p_matrix(A, *, tol: float = 0.0, max_size: int = 12) -> bool | None:
    """True iff every principal minor of ``A`` is positive (P-matrix).

    A symmetric ``A`` is tested by Cholesky (P <=> positive definite).
    Returns None when ``A`` is non-symmetric and larger than ``max_size``.
    """
    A = np.asarray(A, float)
    m = A.shape[0]
    if m == 0:
        return True
    if np.allclose(A, A.T, rtol=1e-12, atol=1e-14 * max(1.0, np.abs(A).max())):
        ev = np.linalg.eigvalsh(0.5 * (A + A.T))
        return bool(ev.min() > tol * max(1.0, abs(ev.max())))
    if m > max_size:
        return None
    for k in range(1, m + 1):
        for idx in itertools.combinations(range(m), k):
            if np.linalg.det(A[np.ix_(idx, idx)]) <= tol:
                return False
    return True


def _enumerate(A, b, tol):
    m = b.size
    best = None
    for k in range(m + 1):
        for S in itertools.combinations(range(m), k):
            z = np.zeros(m)
            if k:
                S = list(S)
                try:
                    z[S] = np.linalg.solve(A[np.ix_(S, S)], -b[S])
                except np.linalg.LinAlgError:
                    continue
            w = A @ z + b
            scale = tol * (1.0 + np.abs(b).max() + np.abs(A).max() * np.abs(z).max())
            if z.min(initial=0.0) >= -scale and w.min() >= -scale:
                res = float(np.max(np.abs(np.minimum(z, w))))
                if best is None or res < best[1]:
                    best = (z, res)
                if res <= scale:
                    return best[0]
    return None if best is None else best[0]


def _lemke(A, b, max_iter):
    """Lemke's algorithm with covering vector e = 1 (Cottle-Pang-Stone 4.4.5).

    Columns of ``[I, -A, -e]`` are (w, z, z0); the basis is refactorized at
    every pivot (small problems).  Returns None on ray termination.
    """
    m = b.size
    if b.min() >= 0:
        return np.zeros(m)
    big = np.hstack([np.eye(m), -A, -np.ones((m, 1))])
    basis = list(range(m))
    r = int(np.argmin(b))
    leaving = basis[r]
    basis[r] = 2 * m
    for _ in range(max_iter):
        B = big[:, basis]
        xB = np.linalg.solve(B, b)
        if leaving == 2 * m:
            break
        entering = leaving + m if leaving < m else leaving - m
        d = np.linalg.solve(B, big[:, entering])
        mask = d > 1e-13 * max(1.0, np.abs(d).max())
        if not mask.any():
            return None
        ratios = np.full(m, np.inf)
        ratios[mask] = xB[mask] / d[mask]
        tmin = ratios.min()
        ties = np.flatnonzero(ratios <= tmin + 1e-12 * max(1.0, abs(tmin)))
        r = int(ties[0])
        for i in ties:
            if basis[i] == 2 * m:
                r = int(i)
        leaving = basis[r]
        basis[r] = entering
    else:
        return None
    B = big[:, basis]
    xB = np.linalg.solve(B, b)
    z = np.zeros(m)
    for i, j in enumerate(basis):
        if m <= j < 2 * m:
            z[j - m] = xB[i]
    return z


def solve_lcp(A, b, *, method: str = "auto", tol: float = 1e-10, check_unique: bool = True,
              max_iter: int = 1000) -> LCPSolution:
    """Solve ``0 <= z _|_ w = A z + b >= 0`` exactly (small problems).

    Parameters
    ----------
    A : (m, m) array_like
        LCP matrix (a Delassus matrix in contact mechanics).
    b : (m,) array_like
        LCP vector.
    method : {"auto", "enumeration", "lemke"}
        ``auto``: enumeration for ``m <= 10``, Lemke otherwise, enumeration
        again if Lemke ends on a ray.
    tol : float
        Relative tolerance of the final residual check.
    check_unique : bool
        Test the P-matrix property (unique solution, 000 Assumption 2).

    Raises
    ------
    ContactError
        No solution was found, or the residual check failed; ``partial``
        holds the best iterate.
    """
    A = np.atleast_2d(np.asarray(A, float))
    b = np.atleast_1d(np.asarray(b, float)).ravel()
    m = b.size
    if A.shape != (m, m):
        raise DimensionError(f"solve_lcp: A has shape {A.shape}, b has length {m}")
    if m == 0:
        return LCPSolution(np.zeros(0), np.zeros(0), np.zeros(0, bool), 0.0, True, "empty")
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(b))):
        raise ContactError("solve_lcp: A or b contains NaN/inf (check the contact Jacobians and mass matrix)")
    unique = is_p_matrix(A) if check_unique else None
    z = None
    used = method
    if method in ("auto", "lemke") and (method == "lemke" or m > 10):
        z = _lemke(A.copy(), b.copy(), max_iter)
        used = "lemke"
    if z is None and method != "lemke":
        if m > 16:
            raise ContactError(f"solve_lcp: enumeration of 2^{m} active sets is too costly; use method='lemke'")
        z = _enumerate(A, b, tol)
        used = "enumeration"
    if z is None:
        raise ContactError(
            f"solve_lcp ({used}): no solution found for an LCP of size {m} "
            f"(P-matrix: {unique}); the contact problem may be ill-posed (dependent constraints, 000 Assumption 2)",
            diagnostics={"A": A.tolist(), "b": b.tolist()},
        )
    z = np.maximum(z, 0.0)
    w = A @ z + b
    res = float(np.max(np.abs(np.minimum(z, w))))
    scale = 1.0 + np.abs(b).max() + np.abs(A).max() * np.abs(z).max()
    if res > tol * scale:
        raise ContactError(
            f"solve_lcp ({used}): residual {res:.3g} exceeds {tol:.1e} x scale {scale:.3g}",
            partial=z, diagnostics={"residual": res},
        )
    return LCPSolution(z, w, z > 0, res, unique, used)


# ---------------------------------------------------------------- symbolic

def _solve_small(A, b):
    """Closed-form solve of a k x k system (k <= 3) by Cramer's rule; QR beyond."""
    k = A.shape[0]
    if k == 1:
        return b / A[0, 0]
    if k == 2:
        det = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
        return ca.vertcat(A[1, 1] * b[0] - A[0, 1] * b[1], A[0, 0] * b[1] - A[1, 0] * b[0]) / det
    return ca.solve(A, b)


def lcp_sx(A, b, *, tol: float = 1e-13, max_enum: int = 4, pgs_sweeps: int = 50):
    """Branch-free symbolic LCP solution ``z(A, b)`` for a compiled step.

    For ``m <= max_enum`` every active set ``S`` (largest first) gives a
    candidate ``z_S = -A_SS^{-1} b_S``; the first candidate with
    ``z_S >= 0`` and ``(A z + b)_{not S} >= -tol (1 + |b|)`` is selected with
    ``if_else``.  For a P-matrix exactly one candidate is valid (up to ties at
    degenerate points where candidates coincide), so the result equals the
    exact solution to round-off.  For larger ``m``, ``pgs_sweeps`` projected
    Gauss-Seidel sweeps are used (converges for symmetric positive definite
    ``A``; accuracy depends on conditioning -- check the returned residual).

    Returns
    -------
    z : casadi.SX
    """
    A = ca.SX(A)
    b = ca.SX(b)
    m = b.shape[0]
    if m == 0:
        return ca.SX(0, 1)
    if m > max_enum:
        z = ca.SX.zeros(m)
        for _ in range(pgs_sweeps):
            for i in range(m):
                r = b[i] + ca.mtimes(A[i, :], z) - A[i, i] * z[i]
                z[i] = ca.fmax(0, -r / A[i, i])
        return z
    scale = 1.0 + ca.norm_inf(b)
    z = ca.SX.zeros(m)  # empty set is the last resort (selected when nothing else is valid)
    subsets = [S for k in range(m, 0, -1) for S in itertools.combinations(range(m), k)]
    for S in reversed(subsets):
        S = list(S)
        zS = _solve_small(A[S, S], -b[S])
        cand = ca.SX.zeros(m)
        for j, i in enumerate(S):
            cand[i] = zS[j]
        ok = 1
        for j in range(len(S)):
            ok = ok * (zS[j] >= 0)
        others = [i for i in range(m) if i not in S]
        if others:
            w = ca.mtimes(A[others, S], zS) + b[others]
            for j in range(len(others)):
                ok = ok * (w[j] >= -tol * scale)
        z = ca.if_else(ok, cand, z)
    return z
