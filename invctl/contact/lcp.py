"""Linear complementarity problems ``0 <= z  _|_  w = A z + b >= 0``.

Two families of solvers:

* exact numeric solvers for the contact LCP (000 (7)) and the impact LCP
  (000 (4)): complete enumeration of active sets (``m <= 12``) and Lemke's
  complementary pivoting (any size), with a uniqueness check (P-matrix test;
  000 Assumption 2 makes the Delassus matrix positive definite, hence P);
* exact symbolic solvers for use *inside* a compiled time step, written in
  CasADi SX as straight-line code (fixed iteration budget, ``if_else``
  selection, no branches) with a convergence flag: enumeration of the
  ``2^m`` active sets (tiny ``m``), block principal pivoting
  (:func:`pivot_sx`, any ``m``) and Lemke with the lexicographic ratio test
  (:func:`lemke_sx`); :func:`lcp_sx` chooses.  Projected Gauss-Seidel is
  kept for comparisons (inexact).
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..errors import ContactError, DimensionError


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
        z = _lemke_or_none(A.copy(), b.copy(), max_iter)
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
    """Closed-form solve of a k x k system (k <= 2) by Cramer's rule; QR beyond."""
    k = A.shape[0]
    if k == 1:
        return b / A[0, 0]
    if k == 2:
        det = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
        return ca.vertcat(A[1, 1] * b[0] - A[0, 1] * b[1], A[0, 0] * b[1] - A[1, 0] * b[0]) / det
    return ca.solve(A, b)


def default_max_pivots(m: int) -> int:
    """Pivot budget of :func:`lemke_sx`: ``m + 4 + m // 2``.

    Lemke's method needs at least ``p + 1`` pivots for a solution with ``p``
    positive entries.  On random symmetric positive definite and non-symmetric
    P-matrix LCPs (half of them with ``b < 0``) all 8000 draws per size 1-16
    but one (23 pivots at size 12, budget 22) needed no more;
    tests/test_lcp_compiled.py re-measures it for sizes 1-10.  A solve that
    exceeds it is flagged, never accepted.
    """
    return m + 4 + m // 2


def _residual_ok(A, b, z, tol):
    """``max |min(z, A z + b)| <= tol * (1 + |b| + |A| |z|)`` (symbolic flag)."""
    w = ca.mtimes(A, z) + b
    res = ca.mmax(ca.fabs(ca.fmin(z, w)))
    scale = 1 + ca.mmax(ca.fabs(b)) + ca.mmax(ca.fabs(A)) * ca.mmax(ca.fabs(z))
    return res <= tol * scale, res


def _budget(given, default: int, what: str) -> int:
    if given is None:
        return default
    if given < 1:
        raise ContactError(f"{what} must be >= 1, got {given}")
    return given


def _scaled(A, b):
    """``A / sa``, ``b / sb`` of max-norm 1 (the straight-line solvers' tolerances are relative) and ``sa``, ``sb``."""
    sa = ca.fmax(ca.mmax(ca.fabs(A)), 1e-300)
    sb = ca.fmax(ca.mmax(ca.fabs(b)), 1e-300)
    return A / sa, b / sb, sa, sb


def lemke_sx(A, b, *, max_pivots: int | None = None, piv_tol: float = 1e-12, lex_tol: float = 1e-12,
             res_tol: float = 1e-9):
    """Lemke's complementary pivoting in CasADi SX, straight-line (no branches).

    Solves ``0 <= z  _|_  w = A z + b >= 0`` (000 (4)/(7)) with covering
    vector ``e = 1`` and the lexicographic ratio test (Cottle, Pang, Stone,
    *The Linear Complementarity Problem*, Sect. 4.9), which excludes cycling
    on degenerate problems (``b_i = 0``, ties).  Every one of the
    ``max_pivots`` pivots is evaluated; after termination (``z0`` leaves the
    basis) the remaining ones are masked out with ``if_else``, so the
    expression compiles to straight-line C.

    The basis inverse ``B^{-1}`` (m x m) is kept explicitly and updated by a
    rank-one (product-form) pivot; the problem is scaled by ``max|A|`` and
    ``max|b|`` first so that the tolerances are relative.

    Returns
    -------
    z : casadi.SX
        The solution (entries clipped at 0), or the last iterate.
    ok : casadi.SX
        1 when Lemke terminated within ``max_pivots`` pivots without a ray
        and the residual ``max |min(z, A z + b)|`` is below ``res_tol``
        times the problem scale; 0 otherwise (the caller must not accept z).
    pivots : casadi.SX
        Number of pivots performed.

    Notes
    -----
    For a P-matrix (000 Assumption 2 makes the Delassus matrix positive
    definite) Lemke's method with the lexicographic rule always terminates
    with the unique solution; the pivot budget (default
    :func:`default_max_pivots`) bounds the straight-line code.
    """
    A, b, m = ca.SX(A), ca.SX(b), ca.SX(b).shape[0]
    if m == 0:
        return ca.SX(0, 1), ca.SX(1), ca.SX(0)
    max_pivots = _budget(max_pivots, default_max_pivots(m), "lemke_sx: max_pivots")
    As, bs, sa, sb = _scaled(A, b)
    Binv = ca.SX.eye(m)
    beta = ca.SX(bs)
    lab = ca.SX(ca.DM(list(range(m))))
    z0 = 2 * m
    done = ca.mmin(bs) >= 0  # z = 0 solves the LCP: no pivot at all
    # first pivot: z0 enters with column -e; the row of the lexicographically smallest
    # (b_i, e_i^T) leaves, i.e. the last index among the exact minima of b
    best, idx = bs[0], ca.SX(0)
    for i in range(1, m):
        take = bs[i] <= best
        best = ca.if_else(take, bs[i], best)
        idx = ca.if_else(take, i, idx)
    go = 1 - done
    Binv, beta, lab, leave = _pivot(Binv, beta, lab, -ca.SX.ones(m), idx, z0, go)
    ent = idx + m
    pivots = go
    ray = ca.SX(0)
    rows = ca.DM(list(range(m)))
    for _ in range(max_pivots - 1):
        go = (1 - done) * (1 - ray)
        s_w = ca.vertcat(*[ent == j for j in range(m)])
        s_z = ca.vertcat(*[ent == m + j for j in range(m)])
        a = s_w - ca.mtimes(As, s_z) - (ent == z0)
        d = ca.mtimes(Binv, a)
        valid = d > piv_tol
        inv = ca.if_else(valid, 1 / ca.if_else(valid, d, 1), 0)
        # lexicographic minimum of the rows (beta_i, Binv_i) / d_i over d_i > 0, column by column
        cand = valid
        cols = [beta * inv] + [Binv[:, j] * inv for j in range(m)]
        mins = []
        for c in cols:
            mn = ca.mmin(ca.if_else(cand, c, ca.inf))
            mins.append(mn)
            cand = cand * (c <= mn + lex_tol)
        first = mins[0]
        any_valid = ca.mmax(valid)
        r = _last_index(cand)
        # z0 leaves whenever it ties for the minimum ratio: termination, solution found
        is_z0 = lab == z0
        z0_ok = ca.mmax(is_z0 * valid * (beta * inv <= first + lex_tol))
        r = ca.if_else(z0_ok, ca.dot(is_z0, rows), r)
        ray = ray + go * (1 - any_valid)
        go = go * any_valid
        Binv, beta, lab, leave = _pivot(Binv, beta, lab, d, r, ent, go)
        pivots = pivots + go
        done = done + go * (leave == z0)
        ent = ca.if_else(go, ca.if_else(leave < m, leave + m, leave - m), ent)
    z = ca.vertcat(*[ca.dot(lab == m + j, beta) for j in range(m)])
    z = ca.fmax(z, 0) * (sb / sa)
    res_ok, _ = _residual_ok(A, b, z, res_tol)
    ok = (done > 0) * (ray == 0) * res_ok
    return z, ok, pivots


def _last_index(mask):
    """Index of the last nonzero entry of a 0/1 column (0 if none)."""
    idx = ca.SX(0)
    for i in range(mask.shape[0]):
        idx = ca.if_else(mask[i], i, idx)
    return idx


def _pivot(Binv, beta, lab, d, r, ent, go):
    """Pivot on row ``r`` (symbolic index) with entering column ``d = B^{-1} a``;
    no change where ``go`` is 0.  Returns the leaving label too."""
    m = beta.shape[0]
    e = ca.vertcat(*[r == i for i in range(m)])
    piv = ca.if_else(go, ca.dot(e, d), 1)
    rowB = ca.mtimes(e.T, Binv) / piv
    rowb = ca.dot(e, beta) / piv
    u = go * (d - e)
    leave = ca.dot(e, lab)
    Binv = Binv - ca.mtimes(u, rowB)
    beta = beta - u * rowb
    lab = lab + go * e * (ent - lab)
    return Binv, beta, lab, leave


def _lu_solve_sx(M, r):
    """``M^{-1} r`` by Gaussian elimination without row exchanges (straight-line).

    Valid when every leading principal minor is nonzero; for the masked
    matrices of :func:`pivot_sx` they are principal minors of a P-matrix.
    """
    m = r.shape[0]
    M = ca.SX(M)
    r = ca.SX(r)
    for k in range(m - 1):
        inv = 1 / M[k, k]
        for i in range(k + 1, m):
            f = M[i, k] * inv
            M[i, k + 1:] = M[i, k + 1:] - f * M[k, k + 1:]
            r[i] = r[i] - f * r[k]
    x = ca.SX.zeros(m)
    for i in range(m - 1, -1, -1):
        acc = r[i]
        if i + 1 < m:
            acc = acc - ca.dot(M[i, i + 1:].T, x[i + 1:])
        x[i] = acc / M[i, i]
    return x


def default_pivot_iters(m: int) -> int:
    """Iteration budget of :func:`pivot_sx`: ``5 + m // 4``.

    Cold-started from ``b < 0`` on random P-matrix LCPs (symmetric positive
    definite and non-symmetric, half of them with ``b < 0``; 20000 draws per
    size 1-16) the 99.9th percentile of the iteration count was 3-8, within
    this budget; the mean was 1-4.  The rare long runs of Murty's single
    pivots (up to 21 iterations seen) are flagged, never accepted.
    tests/test_lcp_compiled.py re-measures it on 1000 draws per size.
    """
    return 5 + m // 4


def pivot_sx(A, b, *, start=None, max_iter: int | None = None, p_max: int = 3, tol: float = 1e-11,
             res_tol: float = 1e-9):
    """Block principal pivoting in CasADi SX (Judice-Pires), straight-line.

    Solves ``0 <= z  _|_  w = A z + b >= 0`` for a P-matrix ``A`` by
    guessing the set ``F`` of positive ``z``, solving
    ``A_FF z_F = -b_F`` exactly and exchanging the infeasible indices
    (``z_i < 0`` in ``F``, ``w_i < 0`` outside): all of them while their
    number decreases (at most ``p_max`` times without decrease), otherwise
    only the largest one (Murty's single principal pivot, which cannot
    cycle on a P-matrix).  Each iteration is one LU solve of the masked
    matrix ``diag(s) A diag(s) + diag(1 - s)``; ``max_iter`` iterations are
    evaluated and frozen after convergence with ``if_else``.

    Parameters
    ----------
    start : casadi.SX, optional
        0/1 guess of ``F`` (a warm start, e.g. the previous step's loaded
        contacts); default ``b < 0``.

    Returns
    -------
    z, ok, iters : casadi.SX
        ``ok`` is 1 when an iterate had no infeasible index and the residual
        ``max |min(z, A z + b)|`` is below ``res_tol`` times the problem
        scale; 0 otherwise (the caller must not accept ``z``).

    Notes
    -----
    Judice, Pires, *A block principal pivoting algorithm for large-scale
    strictly monotone linear complementarity problems*, Comput. Oper. Res.
    21 (1994); Murty, *Note on a Bard-type scheme for solving the
    complementarity problem*, Opsearch 11 (1974).
    """
    A, b, m = ca.SX(A), ca.SX(b), ca.SX(b).shape[0]
    if m == 0:
        return ca.SX(0, 1), ca.SX(1), ca.SX(0)
    max_iter = _budget(max_iter, default_pivot_iters(m), "pivot_sx: max_iter")
    As, bs, sa, sb = _scaled(A, b)
    s = ca.SX(bs < 0) if start is None else ca.SX(start)
    best = ca.SX(m + 1)
    p = ca.SX(p_max)
    done = ca.SX(0)
    iters = ca.SX(0)
    z = ca.SX.zeros(m)
    for _ in range(max_iter):
        Ms = (s @ s.T) * As + ca.diag(1 - s)
        zi = s * _lu_solve_sx(Ms, -s * bs)
        wi = (1 - s) * (ca.mtimes(As, zi) + bs)
        bad = s * (zi < -tol) + (1 - s) * (wi < -tol)
        nbad = ca.sum1(bad)
        conv = nbad == 0
        z = ca.if_else(done, z, zi)
        iters = iters + (1 - done)
        better = nbad < best
        block = better + (1 - better) * (p > 0)
        last = _last_index(bad)
        single = ca.vertcat(*[last == i for i in range(m)]) * bad
        flip = ca.if_else(block, bad, single)
        go = (1 - done) * (1 - conv)
        s = s + go * flip * (1 - 2 * s)
        p = ca.if_else(go * better, p_max, ca.if_else(go * (1 - better) * (p > 0), p - 1, p))
        best = ca.if_else(go * better, nbad, best)
        done = ca.fmax(done, conv)
    z = ca.fmax(z, 0) * (sb / sa)
    res_ok, _ = _residual_ok(A, b, z, res_tol)
    return z, done * res_ok, iters


def _enumeration_sx(A, b, tol):
    """All ``2^m`` active sets, the first valid candidate (largest sets first)
    selected with ``if_else``; returns ``(z, any_valid)``."""
    m = b.shape[0]
    scale = 1.0 + ca.norm_inf(b)
    z = ca.SX.zeros(m)  # empty set is the last resort (selected when nothing else is valid)
    found = ca.mmin(b) >= -tol * scale
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
        found = found + ok
    return z, found > 0


def _pgs_sx(A, b, sweeps):
    m = b.shape[0]
    z = ca.SX.zeros(m)
    for _ in range(sweeps):
        for i in range(m):
            r = b[i] + ca.mtimes(A[i, :], z) - A[i, i] * z[i]
            z[i] = ca.fmax(0, -r / A[i, i])
    return z


def lcp_sx(A, b, *, tol: float = 1e-13, max_enum: int = 4, pgs_sweeps: int = 50, method: str = "auto",
           max_iter: int | None = None, start=None, res_tol: float = 1e-9, with_flag: bool = False):
    """Branch-free symbolic LCP solution ``z(A, b)`` for a compiled step.

    Parameters
    ----------
    method : {"auto", "enumeration", "pivoting", "lemke", "pgs"}
        ``enumeration``: every active set ``S`` gives a candidate
        ``z_S = -A_SS^{-1} b_S``; the first with ``z_S >= 0`` and
        ``(A z + b)_{not S} >= -tol (1 + |b|)`` is selected with ``if_else``
        (exact for a P-matrix, ``2^m`` candidates).  ``pivoting``:
        :func:`pivot_sx` (block principal pivoting, ``max_iter`` LU solves).
        ``lemke``: :func:`lemke_sx` (``max_iter`` pivots).  ``pgs``:
        ``pgs_sweeps`` projected Gauss-Seidel sweeps (inexact; for
        comparisons).  ``auto``: enumeration for ``m <= max_enum``,
        pivoting beyond.
    start : casadi.SX, optional
        Warm start of ``pivoting`` (0/1 guess of the positive entries).
    with_flag : bool
        Also return ``ok``: 1 when ``z`` solves the LCP (a valid candidate,
        a converged pivoting method) with a residual below ``res_tol`` times
        the problem scale.  Without the flag a failure goes unnoticed: use
        it in anything that runs unattended.

    Returns
    -------
    z : casadi.SX, or ``(z, ok)`` when ``with_flag``.
    """
    A = ca.SX(A)
    b = ca.SX(b)
    m = b.shape[0]
    if method not in ("auto", "enumeration", "pivoting", "lemke", "pgs"):
        raise ContactError(f"lcp_sx: method must be 'auto', 'enumeration', 'pivoting', 'lemke' or 'pgs', "
                           f"got {method!r}")
    if m == 0:
        z, ok = ca.SX(0, 1), ca.SX(1)
    elif method == "pgs":
        z = _pgs_sx(A, b, pgs_sweeps)
        ok, _ = _residual_ok(A, b, z, res_tol)
    elif method == "enumeration" or (method == "auto" and m <= max_enum):
        if m > 12:
            raise ContactError(f"lcp_sx: enumeration of 2^{m} active sets is too large; use method='pivoting'")
        z, found = _enumeration_sx(A, b, tol)
        ok = found * _residual_ok(A, b, z, res_tol)[0]
    elif method == "lemke":
        z, ok, _ = lemke_sx(A, b, max_pivots=max_iter, res_tol=res_tol)
    else:
        z, ok, _ = pivot_sx(A, b, start=start, max_iter=max_iter, res_tol=res_tol)
    return (z, ok) if with_flag else z


def _lemke_or_none(A, b, max_iter):
    """:func:`_lemke`, with a pivot onto a singular basis (degenerate, non-P-matrix LCPs) ending like a ray: None."""
    try:
        return _lemke(A, b, max_iter)
    except np.linalg.LinAlgError:
        return None
