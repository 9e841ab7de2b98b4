"""Piecewise polynomials of time as CasADi SX expressions, with exact AD derivatives.

A piecewise signal on breaks ``b_0 < ... < b_P`` is written as *one* polynomial
whose coefficients are selected by the active piece::

    act_i = [t >= b_i] - [t >= b_(i+1)]       (0 or 1, exactly one is 1)
    c_j   = sum_i act_i c_(i,j)                 (exact: one non-zero term)
    y     = sum_j c_j tau^j,  tau = (t - b_sel) / h_sel

The selected coefficients are piecewise constant, so AD differentiates only the
single Horner polynomial: the derivatives of order ``r`` cost ``O(P (d + 1))``
selections once plus ``O(r d)`` operations, instead of ``O(r P d)`` for a chain of
``if_else`` over the pieces (about 10x fewer instructions for 50 pieces of
degree 9 and derivatives up to order 4; see ``benchmarks/bench_references.py``).
Before ``b_0`` and after ``b_P`` the signal is held constant (two extra "pieces"
with ``1/h = 0``), as every :class:`~invctl.reference.Reference` is.

Local coordinates ``tau`` in ``[0, 1)`` keep the coefficients of the size of the
signal (``c_j = y^(j)(b_i) h_i^j / j!``).
"""
from __future__ import annotations

import math

import casadi as ca
import numpy as np

from ..errors import ReferenceSignalError


def select_rows(t: ca.SX, breaks, table) -> list[ca.SX]:
    """The row of ``table`` that belongs to the piece containing ``t``, one SX per column.

    ``table`` has ``P + 2`` rows for ``P + 1`` breaks: row 0 for ``t < b_0``, row
    ``i + 1`` for ``b_i <= t < b_(i+1)``, row ``P + 1`` for ``t >= b_P``.
    """
    b = np.asarray(breaks, float).ravel()
    table = np.asarray(table, float)
    if table.ndim != 2 or table.shape[0] != b.size + 1:
        raise ReferenceSignalError(f"select_rows: table needs {b.size + 1} rows for {b.size} breaks, "
                                   f"got shape {table.shape}")
    if b.size < 1 or np.any(np.diff(b) <= 0) or not np.all(np.isfinite(b)):
        raise ReferenceSignalError(f"breakpoints must be finite and strictly increasing, got {b.tolist()}")
    geq = t >= ca.DM(b)                                    # (P + 1) comparisons
    act = ca.vertcat(1 - geq[0], geq[:-1] - geq[1:], geq[-1])  # one-hot piece indicator
    sel = ca.mtimes(ca.DM(table.T), act)                   # structural zeros of the table drop out
    return [sel[j] for j in range(table.shape[1])]


def _horner(tau: ca.SX, coeffs) -> ca.SX:
    y = coeffs[-1]
    for c in reversed(coeffs[:-1]):
        y = y * tau + c
    return y


def ppoly_expr(t: ca.SX, breaks, coeffs) -> ca.SX:
    """A piecewise polynomial as an SX column, constant outside ``[b_0, b_P]``.

    Parameters
    ----------
    t : casadi.SX
        Scalar time symbol.
    breaks : array_like, shape (P + 1,)
        Strictly increasing breakpoints.
    coeffs : array_like, shape (P, d + 1, m)
        ``coeffs[i, j, r]``: coefficient of ``tau^j`` of output ``r`` on piece ``i``,
        ``tau = (t - b_i) / (b_(i+1) - b_i)``.
    """
    b = np.asarray(breaks, float).ravel()
    c = np.asarray(coeffs, float)
    if c.ndim == 2:
        c = c[:, :, None]
    if c.ndim != 3 or c.shape[0] != b.size - 1 or c.shape[1] < 1:
        raise ReferenceSignalError(f"ppoly_expr: coefficients of shape (P, d + 1, m) = ({b.size - 1}, ., .) "
                                   f"expected for {b.size} breaks, got {c.shape}")
    if not np.all(np.isfinite(c)):
        raise ReferenceSignalError("ppoly_expr: non-finite polynomial coefficients")
    P, D, m = c.shape
    h = np.diff(b)
    table = np.zeros((P + 2, 2 + D * m))
    table[:, 0] = np.r_[b[0], b]
    table[1:-1, 1] = 1.0 / h
    table[1:-1, 2:] = c.reshape(P, D * m)
    table[0, 2:2 + m] = c[0, 0, :]                # value at b_0
    table[-1, 2:2 + m] = c[-1].sum(axis=0)        # value at b_P (tau = 1 on the last piece)
    sel = select_rows(t, b, table)
    tau = (t - sel[0]) * sel[1]
    return ca.vertcat(*[_horner(tau, [sel[2 + j * m + r] for j in range(D)]) for r in range(m)])


def smoothstep_coefficients(k: int) -> np.ndarray:
    """Coefficients of ``1, u, ..., u^k`` in ``S_k(s) = s^(k+1) sum_j C(k+j, j) (1-s)^j``, ``u = 1 - s``.

    ``S_k`` is the polynomial of degree ``2k + 1`` rising from 0 to 1 with derivatives
    ``1..k`` zero at ``s = 0`` and ``s = 1``; all terms are positive on ``[0, 1]``
    (no cancellation, unlike the monomial form whose coefficients grow like ``16^k``).
    """
    return np.array([math.comb(k + j, j) for j in range(k + 1)], float)


def smoothstep(s: ca.SX, k: int) -> ca.SX:
    """``S_k(s)`` for ``s`` in ``[0, 1]`` (no clipping); ``k = 4`` is the law of 003 Sect. 6."""
    return s ** (k + 1) * _horner(1 - s, [float(a) for a in smoothstep_coefficients(k)])


def continuity_jumps(ref, times, order: int) -> np.ndarray:
    """Jumps ``max_r |y_r^(j)(t+) - y_r^(j)(t-)|`` at ``times`` for ``j = 0..order``: shape ``(order + 1, len(times))``.

    One-sided limits are taken numerically, one ulp either side of each time, through
    the compiled AD derivatives of ``ref`` (one mapped call).
    """
    times = np.atleast_1d(np.asarray(times, float))
    tt = np.concatenate([np.nextafter(times, -np.inf), np.nextafter(times, np.inf)])
    outs = ref.function(order).map(tt.size)(tt[None, :])
    outs = outs if isinstance(outs, (list, tuple)) else [outs]
    n = times.size
    jumps = np.zeros((order + 1, n))
    for j, o in enumerate(outs):
        o = np.array(o).reshape(ref.m, 2 * n)
        jumps[j] = np.max(np.abs(o[:, n:] - o[:, :n]), axis=0)
    return jumps


def check_continuity(ref, times, order: int, rtol: float = 1e-6, where: str = "") -> dict:
    """Raise :class:`ReferenceSignalError` if a derivative ``0..order`` of ``ref`` jumps at ``times``.

    A jump counts when it exceeds ``rtol`` times the largest ``|y^(j)|`` on a grid over
    ``[t0, tf]`` (rounding in the coefficients is ~1e-12 of that), or, for a derivative
    that is nearly zero everywhere, 1e-9 of ``max |y| (10 / h_min)^j`` (its rounding
    level, ``h_min`` the shortest piece).  Returns the diagnostics
    ``{"max_jump": [...], "scale": [...], "relative": [...]}`` per order.
    """
    times = np.atleast_1d(np.asarray(times, float))
    jumps = continuity_jumps(ref, times, order)
    grid = np.unique(np.concatenate([np.linspace(ref.t0, ref.tf, 401), times]))
    outs = ref.function(order).map(grid.size)(grid[None, :])
    outs = outs if isinstance(outs, (list, tuple)) else [outs]
    scale = np.array([float(np.max(np.abs(np.array(o)))) for o in outs])
    h_min = float(np.min(np.diff(np.unique(np.r_[ref.t0, times, ref.tf])), initial=ref.tf - ref.t0))
    h_min = h_min if h_min > 0 else 1.0
    floor = 1e-9 * max(scale[0], 1e-300) * (10.0 / h_min) ** np.arange(order + 1)
    rel = jumps.max(axis=1) / np.maximum(scale, floor)
    info = {"max_jump": jumps.max(axis=1).tolist(), "scale": scale.tolist(), "relative": rel.tolist()}
    bad = np.flatnonzero(rel > rtol)
    if bad.size:
        j = int(bad[0])
        i = int(np.argmax(jumps[j]))
        raise ReferenceSignalError(
            f"{where or ref.name}: derivative {j} jumps by {jumps[j, i]:.3g} at t = {times[i]:.6g} "
            f"(relative {rel[j]:.3g} > {rtol:g}); the polynomial pieces are not C^{order} there: "
            "the data may be too close to singular (try fewer pieces or more smoothing)",
            diagnostics=info)
    return info
