"""A reference from sampled (noisy) data: a penalized smoothing spline with exact derivatives.

For smoothness ``k`` the fit minimizes, per output,

    (1/N) sum_i w_i (y_i - f(t_i))^2 + lam int_0^1 (f^(m)(s))^2 ds,   s = (t - t_1)/(t_N - t_1),

over splines ``f`` of degree ``d = 2m - 1`` with ``m = floor((k + 3)/2)`` (so ``f`` is
C^{d-1}, ``d - 1 >= k``: cubic for k <= 2, quintic for k <= 4, ...).  With a knot at
every distinct sample (``N - 1 <= max_pieces``) this is the classical smoothing spline
of order ``m``; with more samples the knots sit at ``max_pieces + 1`` sample quantiles
(a penalized regression spline, O'Sullivan 1986), which keeps the SX expression small.

``ends="rest"`` constrains the derivatives ``1..k`` to vanish at the first and last
sample, so the signal held constant outside the data is C^k everywhere (what the
inversion's pre- and post-actuation needs).  ``ends="free"`` leaves them free
(natural end conditions): C^{d-1} on the data interval but only C^0 across its ends.

The smoothing parameter ``lam`` is chosen per output (Demmler-Reinsch basis, a log grid
of 241 values refined by Brent's method) by

* ``smoothing="gcv"``: generalized cross-validation ``N RSS / (N - 1.4 tr H)^2`` (Craven and
  Wahba 1979, with the factor 1.4 of Kim and Gu 2004 against GCV's occasional
  undersmoothing; no noise level needed);
* ``smoothing="noise"`` with ``noise=sigma``: the unbiased risk estimate (Mallows' C_p)
  ``RSS/N + 2 sigma^2 tr H / N`` for a known noise standard deviation;
* ``smoothing=<float>``: this ``lam`` (>= 0) as it is.
"""
from __future__ import annotations

import math

import casadi as ca
import numpy as np
import scipy.linalg as sla
from scipy.interpolate import BSpline
from scipy.optimize import minimize_scalar

from ..errors import ReferenceSignalError
from .piecewise import check_continuity, ppoly_expr
from .signals import Reference

#: GCV with inflated degrees of freedom (Kim and Gu 2004): 1.0 is plain GCV
GCV_GAMMA = 1.4


def penalty_order(k: int) -> int:
    """Order ``m`` of the derivative penalty for a C^k fit: the spline has degree ``2m - 1``."""
    return (int(k) + 3) // 2


def _basis(knots: np.ndarray, d: int) -> BSpline:
    n = knots.size - d - 1
    return BSpline(knots, np.eye(n), d)


def _penalty(basis: BSpline, breaks: np.ndarray, m: int) -> np.ndarray:
    """``Omega_ij = int_0^1 B_i^(m) B_j^(m) ds`` exactly (Gauss-Legendre, degree 2(d - m))."""
    nq = max(1, basis.k - m + 1)
    x, w = np.polynomial.legendre.leggauss(nq)
    a, b = breaks[:-1, None], breaks[1:, None]
    xs = (0.5 * (b - a) * (x + 1) + a).ravel()
    ws = (0.5 * (b - a) * w).ravel()
    D = basis(xs, nu=m)
    return D.T @ (ws[:, None] * D)


def _samples(t, y, weights):
    t = np.asarray(t, float)
    if t.ndim != 1 or t.size < 2 or not np.all(np.isfinite(t)):
        raise ReferenceSignalError(f"from_samples: t must be a finite 1-D array of >= 2 times, got shape {t.shape}")
    Y = np.asarray(y, float)
    if Y.ndim == 1:
        Y = Y[:, None]
    if Y.ndim != 2 or Y.shape[0] != t.size:
        hint = "; time runs along axis 1: pass y.T" if Y.ndim == 2 and Y.shape[1] == t.size else ""
        raise ReferenceSignalError(f"from_samples: y must have shape ({t.size},) or ({t.size}, m) "
                                   f"(one row per sample time), got {Y.shape}{hint}")
    bad = np.flatnonzero(~np.all(np.isfinite(Y), axis=1))
    if bad.size:
        raise ReferenceSignalError(f"from_samples: y is not finite at {bad.size} samples, first at t = {t[bad[0]]:g}; "
                                   "drop those samples")
    w = np.ones(t.size) if weights is None else np.asarray(weights, float).ravel()
    if w.shape != t.shape or not np.all(np.isfinite(w)) or np.any(w <= 0):
        raise ReferenceSignalError(f"from_samples: weights must be {t.size} positive finite numbers")
    order = np.argsort(t, kind="stable")
    return t[order], Y[order], w[order] / w.mean(), order


def _knots(s: np.ndarray, max_pieces: int) -> np.ndarray:
    u = np.unique(s)
    if u.size - 1 > max_pieces:
        u = np.unique(np.quantile(u, np.linspace(0.0, 1.0, max_pieces + 1)))
    u[0], u[-1] = 0.0, 1.0
    return u


class _Fit:
    """The penalized least-squares problem in Demmler-Reinsch form, shared by all outputs.

    Coefficients ``z = E0 u + E1 v``: ``E0`` spans the unpenalized polynomials (known
    exactly, so a large ``lam`` cannot leak into them through rounding), ``E1`` the rest.
    ``u`` is eliminated by a weighted projection ``Pi`` onto the complement of ``X E0``;
    for ``v``, with ``F = X1^T X1 + kappa P11 = R^T R`` (positive definite also when the
    basis is richer than the data) and ``R^-T X1^T X1 R^-1 = V diag(alpha) V^T``, the
    penalty is ``diag((1 - alpha)/kappa)`` in the same basis: for any ``lam`` the fit is
    ``a = b / (alpha + N lam (1 - alpha)/kappa)``, ``b = (X1 R^-1 V)^T Pi W^1/2 y``.
    """

    def __init__(self, X: np.ndarray, w: np.ndarray, Pm: np.ndarray, E0: np.ndarray):
        N = X.shape[0]
        sw = np.sqrt(w)
        E1 = sla.null_space(E0.T)
        X0, X1 = sw[:, None] * (X @ E0), sw[:, None] * (X @ E1)
        Q0, R0 = np.linalg.qr(X0)
        if np.min(np.abs(np.diag(R0)), initial=np.inf) <= 1e-10 * max(np.max(np.abs(R0)), 1e-300):
            raise ReferenceSignalError("from_samples: the samples do not determine the fit (too few distinct "
                                       "times for the spline degree)")
        X1p = X1 - Q0 @ (Q0.T @ X1)
        A = X1p.T @ X1p
        P11 = E1.T @ Pm @ E1
        kappa = np.trace(A) / max(np.trace(P11), 1e-300)
        F = A + kappa * P11
        R = sla.cholesky(0.5 * (F + F.T))
        Rinv = sla.solve_triangular(R, np.eye(R.shape[0]))
        Mt = Rinv.T @ A @ Rinv
        alpha, V = sla.eigh(0.5 * (Mt + Mt.T))
        self.alpha = np.clip(alpha, 0.0, 1.0)
        self.pen = (1.0 - self.alpha) / kappa
        self.T = Rinv @ V
        self.Q = X1p @ self.T
        self.N, self.m0, self.sw = N, E0.shape[1], sw
        self.E0, self.E1, self.Q0, self.R0, self.X1 = E0, E1, Q0, R0, X1

    def gains(self, lam) -> np.ndarray:
        lam = np.atleast_1d(np.asarray(lam, float))
        den = self.alpha[:, None] + self.N * lam[None, :] * self.pen[:, None]
        out = np.zeros_like(den)
        ok = den > 1e-14
        out[ok] = 1.0 / den[ok]
        return out

    def project(self, y: np.ndarray):
        """``(W^1/2 y, Pi W^1/2 y, b)`` for one output."""
        ys = self.sw * y
        yp = ys - self.Q0 @ (self.Q0.T @ ys)
        return ys, yp, self.Q.T @ yp

    def scores(self, b, yp, lam, rule, sigma):
        g = self.gains(lam)
        rss = np.sum((yp[:, None] - self.Q @ (b[:, None] * g)) ** 2, axis=0)
        edf = self.m0 + self.alpha @ g
        if rule == "gcv":
            dof = self.N - GCV_GAMMA * edf
            score = self.N * rss / np.maximum(dof, 1e-9) ** 2
            score[dof < 0.5] = np.inf
        else:
            score = rss / self.N + 2.0 * sigma**2 * edf / self.N
        return score, rss, edf

    def coefficients(self, ys, b, lam) -> np.ndarray:
        """Spline coefficients (in the constrained coordinates ``z``) for one output."""
        v = self.T @ (b * self.gains(lam)[:, 0])
        u = sla.solve_triangular(self.R0, self.Q0.T @ (ys - self.X1 @ v))
        return self.E0 @ u + self.E1 @ v


def _choose(fit: _Fit, b, yp, rule, sigma):
    both = (fit.alpha > 1e-12) & (fit.pen > 1e-12 * max(fit.pen.max(), 1e-300))
    if not np.any(both):
        return 0.0
    ratio = fit.pen[both] / fit.alpha[both]
    lo = -math.log10(fit.N * ratio.max()) - 3.0
    hi = -math.log10(fit.N * ratio.min()) + 3.0
    grid = np.linspace(lo, hi, 241)
    score = fit.scores(b, yp, 10.0**grid, rule, sigma)[0]
    i = int(np.argmin(score))
    a, c = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
    res = minimize_scalar(lambda x: fit.scores(b, yp, 10.0**x, rule, sigma)[0][0], bounds=(a, c),
                          method="bounded", options={"xatol": 1e-4})
    best = res.x if res.fun <= score[i] else grid[i]
    return float(10.0**best)


def _polynomials(basis: BSpline, knots: np.ndarray, degree: int) -> np.ndarray:
    """B-spline coefficients of ``1, s, ..., s^degree`` (Greville interpolation, exact)."""
    d = basis.k
    nb = knots.size - d - 1
    gr = np.array([knots[i + 1:i + d + 1].mean() for i in range(nb)])
    return np.linalg.solve(basis(gr), gr[:, None] ** np.arange(degree + 1)[None, :])


def from_samples(t, y, smoothness: int = 4, *, smoothing="gcv", noise: float | None = None, weights=None,
                 ends: str = "rest", max_pieces: int = 50, name: str = "y_ref") -> Reference:
    """A reference from samples ``y[i] ~ y_ref(t[i])``: a smoothing spline, C^k, exact AD derivatives.

    Parameters
    ----------
    t : array_like (N,)
        Sample times (any order; repeated times allowed).
    y : array_like (N,) or (N, m)
        ``y[i]`` is sampled at ``t[i]``.
    smoothness : int
        ``k``: continuous derivatives of the reference (spline degree ``2m - 1``,
        ``m = floor((k + 3)/2)``).
    smoothing : {"gcv", "noise"} or float
        Rule for the smoothing parameter (module docstring): generalized
        cross-validation, the unbiased risk for a known ``noise``, or a given ``lam``.
    noise : float, optional
        Standard deviation of the noise (with ``smoothing="noise"``).
    weights : array_like (N,), optional
        Relative weights of the samples (inverse noise variances).
    ends : {"rest", "free"}
        "rest": derivatives ``1..k`` vanish at the first and last sample (C^k
        everywhere); "free": natural ends (the held-constant reference is then C^0).
    max_pieces : int
        At most this many polynomial pieces (knots at sample quantiles beyond it).
    name : str
        Used in messages.

    Returns
    -------
    Reference
        ``diagnostics`` holds, per output, ``lam``, ``edf`` (effective degrees of
        freedom), ``score``, ``rms_residual``, ``max_residual``, ``sigma_hat``; the
        residuals ``y - y_ref(t)`` (shape ``(m, N)``, in the order given) and the
        continuity check at every knot.
    """
    if isinstance(smoothness, bool) or int(smoothness) != smoothness or not 0 <= int(smoothness) <= 10:
        raise ReferenceSignalError(f"smoothness must be an integer in [0, 10], got {smoothness!r}")
    k = int(smoothness)
    if ends not in ("rest", "free"):
        raise ReferenceSignalError(f"ends must be 'rest' or 'free', got {ends!r}")
    if isinstance(smoothing, str):
        if smoothing not in ("gcv", "noise"):
            raise ReferenceSignalError(f"smoothing must be 'gcv', 'noise' or a number >= 0, got {smoothing!r}")
        if smoothing == "noise" and not (noise is not None and np.isfinite(noise) and noise > 0):
            raise ReferenceSignalError(f"smoothing='noise' needs noise=sigma > 0 (the noise standard deviation), "
                                       f"got noise={noise!r}")
        if smoothing == "gcv" and noise is not None:
            raise ReferenceSignalError("noise is used only with smoothing='noise'; GCV estimates it")
    elif isinstance(smoothing, bool) or not (isinstance(smoothing, (int, float, np.number)) and np.isfinite(smoothing)
                                             and float(smoothing) >= 0):
        raise ReferenceSignalError(f"smoothing must be 'gcv', 'noise' or a number >= 0, got {smoothing!r}")
    if int(max_pieces) != max_pieces or max_pieces < 1:
        raise ReferenceSignalError(f"max_pieces must be a positive integer, got {max_pieces!r}")
    t, Y, w, order = _samples(t, y, weights)
    N, mo = Y.shape
    a, L = t[0], t[-1] - t[0]
    if not L > 0:
        raise ReferenceSignalError("from_samples: all samples are at the same time")
    m = penalty_order(k)
    d = 2 * m - 1
    s = (t - a) / L
    br = _knots(s, int(max_pieces))
    knots = np.r_[[0.0] * d, br, [1.0] * d]
    basis = _basis(knots, d)
    nb = knots.size - d - 1
    C = np.vstack([basis(np.array([e]), nu=j) for j in range(1, k + 1) for e in (0.0, 1.0)]) \
        if ends == "rest" and k > 0 else np.zeros((0, nb))
    Z = sla.null_space(C) if C.shape[0] else np.eye(nb)
    # unpenalized part: polynomials of degree < m; with rest ends only constants satisfy the constraints
    m0 = 1 if C.shape[0] else m
    if N < m + 1 or Z.shape[1] <= m0:
        raise ReferenceSignalError(f"from_samples: {N} samples are too few for a C^{k} fit "
                                   f"(degree {d}; at least {m + 1} are needed)")
    E0 = sla.orth(Z.T @ _polynomials(basis, knots, m0 - 1))
    fit = _Fit(basis(s) @ Z, w, Z.T @ _penalty(basis, br, m) @ Z, E0)
    rule = smoothing if isinstance(smoothing, str) else "given"
    coef = np.zeros((nb, mo))
    per = []
    for r in range(mo):
        ys, yp, b = fit.project(Y[:, r])
        lam = float(smoothing) if rule == "given" else _choose(fit, b, yp, rule, noise)
        coef[:, r] = Z @ fit.coefficients(ys, b, lam)
        score, rss, edf = (float(v[0]) for v in fit.scores(b, yp, lam, "gcv" if rule != "noise" else rule, noise))
        per.append({"lam": lam, "edf": edf, "score": score,
                    "sigma_hat": math.sqrt(rss / max(N - edf, 1e-9))})
    spl = BSpline(knots, coef, d)
    P = br.size - 1
    h = np.diff(br)
    coeffs = np.stack([spl(br[:-1], nu=j) * (h**j / math.factorial(j))[:, None] for j in range(d + 1)], axis=1)
    tt = ca.SX.sym("t")
    expr = ppoly_expr(tt, a + L * br, coeffs)
    diag = {"kind": "from_samples", "rule": rule, "noise": noise, "ends": ends, "degree": d, "penalty_order": m,
            "pieces": P, "breaks": a + L * br, "samples": N, "interior_smoothness": d - 1}
    ref = Reference(tt, expr, a, t[-1], k if ends == "rest" else 0, name, diagnostics=diag)
    diag = ref.diagnostics
    resid = Y.T - ref(t)
    direct = Y.T - spl(s).T
    for r, p in enumerate(per):
        p.update(rms_residual=float(np.sqrt(np.mean(resid[r] ** 2))), max_residual=float(np.max(np.abs(resid[r]))))
    unsorted = np.empty_like(resid)
    unsorted[:, order] = resid
    diag.update(outputs=per, residuals=unsorted)
    gap = float(np.max(np.abs(resid - direct)))
    if not gap <= 1e-9 * max(1.0, float(np.max(np.abs(Y)))):
        raise ReferenceSignalError(f"{name}: the SX reference differs from the fitted spline by {gap:.3g} at the "
                                   "samples (ill-conditioned fit): lower max_pieces or the smoothness",
                                   partial=ref, diagnostics=diag)
    check_at = a + L * br if ends == "rest" else a + L * br[1:-1]
    diag["continuity"] = check_continuity(ref, check_at, k, where=name) if check_at.size else {}
    return ref
