"""The new output (41) of 003 Sect. 5: rows ``K_1..K_m`` satisfying (A1), and (A1) along trajectories.

(A1) asks for ``q <= m``, ``k_1 + .. + k_q = k``, rows ``K_i`` (length k, i <= q) with the zero conditions
``K_i Q~^j P~ = 0`` (``j <= k_i - 2``) and free rows ``K_(q+1..m)`` (length m) such that the symmetric part of
``rho D S~(w)`` is positive definite, ``D = [K_i Q~^(k_i-1) P~ (i <= q); K_i (i > q)]`` (the stacked matrix).
With an output/input pairing ``E`` (``e_bar_i`` drives input ``pairing[i]``) the matrix is ``rho D S~ E``.

:func:`design_new_output` takes ``k_i`` = the controllability (Kronecker) indices of ``(Q~, P~)`` and

* **identity / permutation**: if every ``e_c(i)^T`` is reachable as ``K_i Q~^(k_i-1) P~`` and ``rho S~`` is
  definite at all given points, ``D`` is the identity up to the pairing (the remark after (A2): in the
  colocated case ``S~`` is positive definite, so ``D = I_m`` satisfies (A1)); the pairing lets an eta2 row
  replace any output (e.g. an unstable mode driven by the second output only);
* **high-gain** otherwise: the eta2 rows are the projections of the rows of ``(S~(w0) E)^-1`` onto what the
  zero conditions allow, scaled to ``(D S~(w0) E)_ii = 1``; the free rows complete ``D S~(w0) E`` to
  ``[[A1, A2], [-A2^T, I]]`` (symmetric part ``diag(sym A1, I)``); a Nelder-Mead refinement then maximizes the
  relative margin ``min_w lambda_min(sym(D S~(w) E)) / ||D||_2`` over the points (the size of a perturbation
  of ``S~``, e.g. by plant mismatch, that (A1) survives).  All pairings are tried; the best is kept.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import permutations

import numpy as np
import scipy.linalg as sla
from scipy.optimize import minimize

from ..analysis import schur_complement
from ..errors import FeedbackDesignError, ParameterError

_RANK_TOL = 1e-9
_MAX_PAIRINGS = 720      # try every output/input pairing up to m = 6

# ----------------------------------------------------------------------------- the new output (41)
def controllability_indices(Q, P, tol: float = _RANK_TOL) -> tuple:
    """Controllability indices of ``(Q, P)`` (Luenberger's selection in crate order ``p_1, .., p_m,
    Q p_1, ..``): ``kappa_l`` = number of independent vectors ``Q^j p_l``; their sum is the rank of the
    controllability matrix (``k`` iff controllable)."""
    Q, P = np.atleast_2d(np.asarray(Q, float)), np.atleast_2d(np.asarray(P, float))
    k, m = P.shape
    basis, kappa, active = np.zeros((k, 0)), [0] * m, [True] * m
    QjP = P.copy()
    for _ in range(k):
        for col in range(m):
            if not active[col]:
                continue
            v = QjP[:, col]
            nv = np.linalg.norm(v)
            cand = np.column_stack([basis, v / nv]) if nv > 0 else basis
            if nv > 0 and cand.shape[1] <= k and np.linalg.svd(cand, compute_uv=False)[-1] > tol:
                basis, kappa[col] = cand, kappa[col] + 1
            else:
                active[col] = False
        QjP = Q @ QjP
    return tuple(kappa)


def _row_space(Qt, Pt, s):
    """``N`` (rows spanning ``{K : K Q~^j P~ = 0, j < s-1}``) and ``M = N Q~^(s-1) P~``."""
    k = Qt.shape[0]
    if s == 1:
        N = np.eye(k)
    else:
        C = np.hstack([np.linalg.matrix_power(Qt, j) @ Pt for j in range(s - 1)])
        N = sla.null_space(C.T, rcond=1e-10).T
    return N, N @ np.linalg.matrix_power(Qt, s - 1) @ Pt


@dataclass(frozen=True)
class NewOutput:
    """Result of :func:`design_new_output`: the rows of (41) and their (A1) margins.

    ``margins[0]`` is ``lambda_min(sym(rho D S~ E))`` at the design point, then one per extra point;
    ``relative_margin = min(margins) / ||D||_2``; ``flatness_rank`` is the rank of the rows
    ``K_i Q~^j`` (``j < k_i``), which must be k (eta2 is then a function of y_new and its derivatives)."""

    K: tuple
    k_i: tuple
    rho: int
    pairing: tuple
    construction: str
    D: np.ndarray
    margins: np.ndarray
    relative_margin: float
    zero_residual: float
    flatness_rank: int
    indices: tuple
    note: str = ""

    @property
    def margin(self) -> float:
        return float(self.margins[0])

    @property
    def E(self) -> np.ndarray:
        return _pairing_matrix(self.pairing)


def _pairing_matrix(p):
    E = np.zeros((len(p), len(p)))
    E[list(p), np.arange(len(p))] = 1.0
    return E


def _margins(D, S_all, E, rho=1):
    G = rho * np.einsum("ij,njk,kl->nil", D, S_all, E)
    return np.linalg.eigvalsh(0.5 * (G + G.transpose(0, 2, 1)))[:, 0]


def _finish(Qt, Pt, K, k_i, rho, pairing, construction, S_all, indices, note=""):
    q = len(k_i)
    m = S_all.shape[1]
    rows = [K[i] @ np.linalg.matrix_power(Qt, k_i[i] - 1) @ Pt for i in range(q)] + list(K[q:])
    D = np.vstack(rows) if rows else np.zeros((0, m))
    zero = max([float(np.abs(K[i] @ np.linalg.matrix_power(Qt, j) @ Pt).max())
                for i in range(q) for j in range(k_i[i] - 1)] + [0.0])
    obs = [K[i] @ np.linalg.matrix_power(Qt, j) for i in range(q) for j in range(k_i[i])]
    rank = int(np.linalg.matrix_rank(np.vstack(obs), tol=1e-9 * max(1.0, np.abs(np.vstack(obs)).max()))) if obs else 0
    mg = _margins(D, S_all, _pairing_matrix(pairing), rho)
    rel = float(mg.min() / np.linalg.norm(D, 2))
    return NewOutput(tuple(np.asarray(Ki, float) for Ki in K), tuple(k_i), int(rho), tuple(pairing), construction,
                     D, mg, rel, zero, rank, tuple(indices), note)


def design_new_output(Q_tilde, P_tilde, S, *, S_points=None, k_i=None, K=None, rho=None, pairing=None,
                      refine: bool = True) -> NewOutput:
    """Rows ``K_1..K_m`` of the new output (41) satisfying (A1) (003 Sect. 5).

    Parameters
    ----------
    Q_tilde, P_tilde : array_like
        ``Q~`` (k x k) and ``P~`` (k x m) of (39)/(40); ``k = 0`` for minimum-phase systems.
    S : array_like
        ``S~`` (m x m) of (16) at the design point.
    S_points : array_like, optional
        ``S~`` at further points, shape (N, m, m): the margin is checked (and refined) on all of them.
    k_i, K, rho, pairing : optional
        Given values are kept (``K`` given: only the margins are computed).
    refine : bool
        Refine the high-gain construction by Nelder-Mead on the relative margin.

    Raises
    ------
    FeedbackDesignError
        ``(Q~, P~)`` is not controllable (an unstable mode that no output redefinition removes), or no
        row choice makes ``rho D S~ E`` positive definite at the design point.
    """
    S = np.atleast_2d(np.asarray(S, float))
    m = S.shape[0]
    Pt = np.asarray(P_tilde, float).reshape(-1, m)
    k = Pt.shape[0]
    Qt = np.asarray(Q_tilde, float).reshape(k, k)
    S_all = np.concatenate([S[None], np.asarray(S_points, float).reshape(-1, m, m)]) if S_points is not None \
        and np.size(S_points) else S[None]
    indices = controllability_indices(Qt, Pt) if k else ()
    if k and sum(indices) < k:
        raise FeedbackDesignError(
            f"(A1) cannot hold: (Q~, P~) is not controllable (controllability indices {indices}, rank "
            f"{sum(indices)} < k = {k}): an unstable mode of the internal dynamics is not influenced by y, so no "
            "new output (41) removes it; choose other outputs", diagnostics={"indices": indices})
    if K is not None:
        K = [np.atleast_1d(np.asarray(Ki, float)).ravel() for Ki in K]
        if k_i is None:
            q = sum(1 for Ki in K if Ki.size == k) if k != m else 1
            k_i = [1] * q
        pairing = tuple(range(m)) if pairing is None else tuple(int(x) for x in pairing)
        res = _finish(Qt, Pt, K, [int(x) for x in k_i], 1 if rho is None else rho, pairing, "given", S_all,
                      indices, "K given")
        if rho is None and res.margins[0] < 0:
            res = _finish(Qt, Pt, K, res.k_i, -1, pairing, "given", S_all, indices, "K given")
        return res
    if k_i is None:
        k_i = sorted((x for x in indices if x), reverse=True)
    k_i = [int(x) for x in k_i]
    q = len(k_i)
    if k and (q > m or sum(k_i) != k or min(k_i) < 1):
        raise ParameterError(f"(A1): need 1 <= q <= m = {m} integers k_i >= 1 with sum k = {k}, got k_i = {k_i}")
    spaces = {s: _row_space(Qt, Pt, s) for s in set(k_i)}
    given_pairing = None if pairing is None else tuple(int(x) for x in pairing)
    if given_pairing is not None:
        candidates = [given_pairing[:q]]
    elif math.perm(m, q) <= _MAX_PAIRINGS:
        candidates = list(permutations(range(m), q))
    else:                        # many inputs: the identity, and one eta2 row at a time moved to another input
        candidates = [tuple(range(q))] + [tuple(j if i2 == i else i2 for i2 in range(q))
                                          for i in range(q) for j in range(q, m)]

    def full(c):
        return given_pairing if given_pairing is not None else tuple(c) + tuple(x for x in range(m) if x not in c)

    # -- construction 1: stacked matrix = I_m (up to the pairing), valid where rho S~ is definite
    for c in candidates:
        K, ok = [], True
        for i in range(q):
            N, M = spaces[k_i[i]]
            e = np.eye(m)[c[i]]
            a = np.linalg.lstsq(M.T, e, rcond=None)[0]
            if np.abs(a @ M - e).max() > 1e-10:
                ok = False
                break
            K.append(a @ N)
        if not ok:
            continue
        p = full(c)
        K += [np.eye(m)[p[i]] for i in range(q, m)]
        r = rho if rho is not None else (1 if np.linalg.eigvalsh(0.5 * (S + S.T))[0] > 0 else -1)
        res = _finish(Qt, Pt, K, k_i, r, p, "identity" if p == tuple(range(m)) else "permutation", S_all, indices,
                      "stacked matrix = I_m up to the pairing; rho S~ is positive definite at the design points "
                      "(the colocated remark after (A2))")
        if res.margins.min() > 0:
            return res
    # -- construction 2: rows from S~(w0)^-1, free rows completing D S~ E, refined over the points
    best = None
    for c in candidates:
        p = full(c)
        SE = S[:, list(p)]
        try:
            SEinv = np.linalg.inv(SE)
        except np.linalg.LinAlgError:
            raise FeedbackDesignError("S~ is singular at the design point: the relative degree does not exist "
                                      "there") from None
        coeffs, ds, ok = [], [], True
        for i in range(q):
            N, M = spaces[k_i[i]]
            a = np.linalg.lstsq(M.T, SEinv[i], rcond=None)[0]
            d = a @ M
            aii = float(d @ SE[:, i])
            if abs(aii) <= 1e-9 * np.linalg.norm(d) * np.linalg.norm(SE) or not np.isfinite(aii):
                ok = False
                break
            coeffs.append(a / aii)
            ds.append(d / aii)
        if not ok:
            continue
        A = np.vstack(ds) @ SE if q else np.zeros((0, m))
        if q and np.linalg.eigvalsh(0.5 * (A[:, :q] + A[:, :q].T))[0] <= 0:
            continue
        R = np.hstack([-A[:, q:].T, np.eye(m - q)]) @ SEinv
        K = [a @ spaces[k_i[i]][0] for i, a in enumerate(coeffs)] + list(R)
        res = _finish(Qt, Pt, K, k_i, 1, p, "high-gain", S_all, indices,
                      "eta2 rows: projections of the rows of (S~(w0) E)^-1 onto the zero conditions; free rows "
                      "complete D S~(w0) E to [[A1, A2], [-A2^T, I]]")
        if refine:
            res = _refine(Qt, Pt, res, spaces, S_all, indices) or res
        if best is None or res.relative_margin > best.relative_margin:
            best = res
    if best is None or best.margins[0] <= 0:
        raise FeedbackDesignError(
            f"(A1): no choice of rows K_i with k_i = {k_i} makes the symmetric part of rho [stacked] S~ E positive "
            f"definite at the design point (tried {len(candidates)} output/input pairings); the linearized unstable "
            "internal dynamics cannot be removed by (41) for this output", diagnostics={"k_i": k_i})
    if rho is not None and rho != best.rho:
        best = _finish(Qt, Pt, [-Ki for Ki in best.K], k_i, rho, best.pairing, best.construction, S_all, indices,
                       best.note + "; rows negated for the given rho")
    return best


#: cost evaluations of one Nelder-Mead refinement: the iteration limit alone (600 per coefficient) let a
#: five-input arm (25 coefficients) take 71 000 evaluations and 200 s over its pairing candidates; the
#: shipped scenes need at most a few hundred (crane: 169)
REFINE_MAX_EVALUATIONS = 3000


def _refine(Qt, Pt, res, spaces, S_all, indices):
    """Maximize ``min_w lambda_min(sym(D S~(w) E)) / ||D||_2`` over the eta2-row coefficients and free rows."""
    q, m = len(res.k_i), S_all.shape[1]
    E = res.E
    Ns = [spaces[s][0] for s in res.k_i]
    Ms = [spaces[s][1] for s in res.k_i]
    sizes = [N.shape[0] for N in Ns]
    a0 = [np.linalg.lstsq(N.T, Ki, rcond=None)[0] for N, Ki in zip(Ns, res.K[:q])]
    x0 = np.concatenate(a0 + [np.ravel(res.K[q:])]) if (a0 or m > q) else np.zeros(0)

    def unpack(x, bases):
        """The rows of ``x``: its eta2-row coefficients times ``bases`` (``Ms``: the rows of D; ``Ns``: the
        rows of K), then the free rows."""
        rows, off = [], 0
        for B, n in zip(bases, sizes):
            rows.append(x[off:off + n] @ B)
            off += n
        return rows + list(x[off:].reshape(m - q, m))

    def cost(x):
        D = np.vstack(unpack(x, Ms)) if (Ms or m > q) else np.zeros((0, m))
        nrm = np.linalg.norm(D, 2)
        return 1e3 if nrm == 0 else -_margins(D, S_all, E).min() / nrm

    out = minimize(cost, x0, method="Nelder-Mead",
                   options={"maxiter": 600 * x0.size, "maxfev": REFINE_MAX_EVALUATIONS, "xatol": 1e-10,
                            "fatol": 1e-12})
    if not -out.fun > res.relative_margin:
        return None
    D = np.vstack(unpack(out.x, Ms))
    K = unpack(out.x / float(np.mean(np.diag(D @ S_all[0] @ E))), Ns)  # unit mean diagonal of D S~(w0) E
    return _finish(Qt, Pt, K, res.k_i, 1, res.pairing, "high-gain", S_all, indices,
                   res.note + f"; refined by Nelder-Mead over {S_all.shape[0]} points (relative margin "
                   f"{res.relative_margin:.3g} -> {-out.fun:.3g})")


def _S_batch(model, pts):
    if not pts:
        return np.zeros((0, model.m, model.m))
    q = np.array([p[0] for p in pts]).T
    v = np.array([p[1] for p in pts]).T
    N = q.shape[1]
    S = schur_complement(model).map(N)(q, v, np.tile(model.theta_values[:, None], (1, N)))
    return np.array(S).reshape(model.m, N, model.m).transpose(1, 0, 2)


# ----------------------------------------------------------------------------- (A1) along a trajectory
@dataclass(frozen=True)
class A1Margin:
    """``lambda_min(sym(rho [stacked] S~(q, v) E))`` along a trajectory ((A1) needs it > 0)."""

    eigenvalues: np.ndarray
    min_eig: float
    index: int
    t_min: float
    fraction_positive: float
    relative: float

    def to_dict(self) -> dict:
        return {"min_eig": self.min_eig, "t_min": self.t_min, "fraction_positive": self.fraction_positive,
                "relative": self.relative}


def a1_margin_along(design_or_controller, model, q, v, *, t=None) -> A1Margin:
    """(A1) along states ``q, v`` (shape (n, N)) for a :class:`FunnelDesign` or an
    :class:`NMPFunnelController` (``S~`` of ``model``: the reference model, or a plant to see the true margin)."""
    obj = design_or_controller
    D, E, rho = obj.decoupling_matrix, obj.pairing_matrix, obj.rho
    q = np.asarray(q, float).reshape(model.n, -1)
    v = np.asarray(v, float).reshape(model.n, -1)
    S = _S_batch(model, list(zip(q.T, v.T)))
    ev = _margins(D, S, E, rho)
    i = int(np.argmin(ev))
    tt = np.arange(ev.size, dtype=float) if t is None else np.asarray(t, float).ravel()
    return A1Margin(ev, float(ev[i]), i, float(tt[i]), float(np.mean(ev > 0)),
                    float(ev[i] / np.linalg.norm(D, 2)))
