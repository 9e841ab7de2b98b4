"""References users write down: rest-to-rest moves and paths through waypoints."""
from __future__ import annotations

import math

import casadi as ca
import numpy as np

from ..errors import ReferenceSignalError
from .piecewise import check_continuity, ppoly_expr, select_rows, smoothstep
from .signals import Reference

#: beyond this the rest-to-rest polynomial (degree 2k + 1) is no longer a sensible reference
MAX_SMOOTHNESS = 12


def _smoothness(k) -> int:
    if isinstance(k, bool) or int(k) != k or not 0 <= int(k) <= MAX_SMOOTHNESS:
        raise ReferenceSignalError(f"smoothness must be an integer in [0, {MAX_SMOOTHNESS}], got {k!r}")
    return int(k)


def _vector(y, what: str) -> np.ndarray:
    y = np.atleast_1d(np.asarray(y, float))
    if y.ndim != 1 or not np.all(np.isfinite(y)):
        raise ReferenceSignalError(f"{what} must be a finite scalar or vector, got {np.asarray(y).tolist()}")
    return y


def rest_to_rest(y0, yf, t0: float, tf: float, smoothness: int = 4, *, name: str = "y_ref") -> Reference:
    """Move from ``y0`` (at rest) to ``yf`` (at rest) during ``[t0, tf]``, constant outside.

    ``y(t) = y0 + (yf - y0) S_k(s)``, ``s = (t - t0)/(tf - t0)``, with ``S_k`` the
    polynomial of degree ``2k + 1`` whose derivatives ``1..k`` vanish at both ends
    (:func:`~invctl.reference.piecewise.smoothstep`).  The glued signal is C^k
    (and in W^{k+1,inf}); ``k = 4`` is the timing law of 003 Sect. 6
    (:func:`poly9_timing_law`).

    Parameters
    ----------
    y0, yf : float or array_like (m,)
        Start and end values (a scalar broadcasts against a vector).
    t0, tf : float
        Start and end of the move, ``t0 < tf``.
    smoothness : int
        ``k``: number of continuous derivatives (0 = linear ramp).
    name : str
        Used in messages.
    """
    k = _smoothness(smoothness)
    y0, yf = _vector(y0, "y0"), _vector(yf, "yf")
    if y0.size != yf.size and min(y0.size, yf.size) != 1:
        raise ReferenceSignalError(f"rest_to_rest: y0 has {y0.size} components, yf has {yf.size}")
    y0, yf = np.broadcast_arrays(y0, yf)
    t0, tf = float(t0), float(tf)
    if not (np.isfinite(t0) and np.isfinite(tf) and tf > t0):
        raise ReferenceSignalError(f"rest_to_rest needs finite t0 < tf, got t0={t0}, tf={tf}")
    t = ca.SX.sym("t")
    s = (t - t0) / (tf - t0)
    S = ca.if_else(s <= 0, 0, ca.if_else(s >= 1, 1, smoothstep(s, k)))
    expr = ca.DM(y0) + ca.DM(yf - y0) * S
    return Reference(t, expr, t0, tf, k, name, diagnostics={"kind": "rest_to_rest", "degree": 2 * k + 1})


def _waypoint_values(times: np.ndarray, values) -> np.ndarray:
    v = np.asarray(values, float)
    n = times.size
    if v.ndim == 1:
        v = v[:, None]
    if v.ndim != 2 or v.shape[0] != n:
        hint = "; time runs along axis 1: pass values.T" if v.ndim == 2 and v.shape[1] == n else ""
        raise ReferenceSignalError(f"waypoints: values must have shape ({n},) or ({n}, m) (one row per "
                                   f"waypoint time), got {v.shape}{hint}")
    if not np.all(np.isfinite(v)):
        raise ReferenceSignalError("waypoints: values must be finite")
    return v


def waypoints(times, values, smoothness: int = 4, *, stop: bool = False, name: str = "y_ref",
              tol: float = 1e-9) -> Reference:
    """A path through waypoints, C^k everywhere, at rest at the first and last one.

    Parameters
    ----------
    times : array_like (N,)
        Strictly increasing waypoint times, ``N >= 2``.
    values : array_like (N,) or (N, m)
        ``values[i]`` is passed at ``times[i]``.
    smoothness : int
        ``k``: number of continuous derivatives of the reference.
    stop : bool
        False: the interpolating spline of degree ``2k + 1`` with derivatives
        ``1..k`` zero at the first and last waypoint (C^{2k} inside; unique; for
        ``N = 2`` it is :func:`rest_to_rest`).  True: a rest-to-rest move between
        consecutive waypoints (the path stops at every waypoint; no overshoot).
    name : str
        Used in messages.
    tol : float
        Accepted interpolation error at the waypoints, relative to ``max |values|``.

    Returns
    -------
    Reference
        Constant before ``times[0]`` and after ``times[-1]``; ``diagnostics`` holds
        the interpolation error and the continuity check at the waypoints.
    """
    k = _smoothness(smoothness)
    tb = np.asarray(times, float).ravel()
    if tb.size < 2 or not np.all(np.isfinite(tb)) or np.any(np.diff(tb) <= 0):
        raise ReferenceSignalError(f"waypoints: times must be finite and strictly increasing, at least 2, "
                                   f"got {np.asarray(times).tolist()}")
    v = _waypoint_values(tb, values)
    P, m = tb.size - 1, v.shape[1]
    t = ca.SX.sym("t")
    degree = 2 * k + 1
    if stop:
        table = np.zeros((P + 2, 2 + 2 * m))
        table[:, 0] = np.r_[tb[0], tb]
        table[1:-1, 1] = 1.0 / np.diff(tb)
        table[1:-1, 2:2 + m] = v[:-1]
        table[1:-1, 2 + m:] = np.diff(v, axis=0)
        table[0, 2:2 + m], table[-1, 2:2 + m] = v[0], v[-1]
        sel = select_rows(t, tb, table)
        S = smoothstep((t - sel[0]) * sel[1], k)
        expr = ca.vertcat(*[sel[2 + r] + sel[2 + m + r] * S for r in range(m)])
    else:
        from scipy.interpolate import make_interp_spline

        if k == 0:
            spl = make_interp_spline(tb, v, k=1)
        else:
            rest = [(j, np.zeros(m)) for j in range(1, k + 1)]
            spl = make_interp_spline(tb, v, k=degree, bc_type=(rest, rest))
        h = np.diff(tb)
        coeffs = np.stack([spl(tb[:-1], nu=j) * (h ** j / math.factorial(j))[:, None] for j in range(degree + 1)],
                          axis=1)
        coeffs[:, 0, :] = v[:-1]  # interpolation conditions exactly
        expr = ppoly_expr(t, tb, coeffs)
    ref = Reference(t, expr, tb[0], tb[-1], k, name,
                    diagnostics={"kind": "waypoints", "stop": bool(stop), "degree": degree, "pieces": P,
                                 "breaks": tb.copy()})
    err = float(np.max(np.abs(ref(tb) - v.T)))
    ref.diagnostics["interpolation_error"] = err
    if not err <= tol * max(1.0, float(np.max(np.abs(v)))):
        raise ReferenceSignalError(
            f"{name}: the path misses a waypoint by {err:.3g} (> {tol:g} relative); the interpolation "
            "is ill-conditioned (very uneven waypoint spacing or high smoothness): use stop=True, "
            "a lower smoothness or more even times", partial=ref, diagnostics=ref.diagnostics)
    ref.diagnostics["continuity"] = check_continuity(ref, tb, k, where=name)
    return ref
