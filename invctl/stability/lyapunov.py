"""Lyapunov monitoring for systems with clearances, 000 (37), (39), (50)-(55).

* :func:`lyapunov_report` -- ``V(t)`` history of a contact simulation, its
  jumps at impact steps and its largest increase (000 (39)/(55) say ``V``
  never increases for the PD (36) law and, under (52)/(54), for PD+ (48));
* :func:`impact_jump_51` -- the predicted jump (51) of ``V`` at an impact;
* :func:`desired_velocity_condition` -- conditions (52)/(54): the desired
  velocity must lie in the tangent cone ``T_{T_Phi(q)}(w)``, i.e.
  ``grad f_i^T qd_dot >= 0`` for every contact with ``f_i(q) = 0`` and
  ``grad f_i^T w = 0``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["LyapunovReport", "lyapunov_report", "impact_jump_51", "desired_velocity_condition"]


@dataclass(frozen=True)
class LyapunovReport:
    """Summary of ``V`` along a trajectory.

    Attributes
    ----------
    max_increase : float
        Largest one-step increase of ``V``.
    max_increase_impacts, max_increase_smooth : float
        The same restricted to impact steps / the other steps.
    impact_jumps : ndarray
        ``V(t_k+) - V(t_k-)`` over the impact steps.
    n_impacts : int
    V0, V_end : float
    """

    max_increase: float
    max_increase_impacts: float
    max_increase_smooth: float
    impact_jumps: np.ndarray
    n_impacts: int
    V0: float
    V_end: float


def lyapunov_report(tr) -> LyapunovReport:
    """Jumps of ``tr.V`` at the impact steps of a :class:`ContactTrajectory`."""
    dV = np.diff(tr.V)
    imp = np.any(tr.impact_mask(), axis=1)
    jumps = dV[imp]
    smooth = dV[~imp]
    return LyapunovReport(float(np.max(dV, initial=0.0)), float(np.max(jumps, initial=0.0)),
                          float(np.max(smooth, initial=0.0)), jumps, int(imp.sum()), float(tr.V[0]), float(tr.V[-1]))


def impact_jump_51(M, sigma, e: float, qd_dot=None) -> float:
    """``sigma_V = -1/2 (1-e)/(1+e) sigma^T M sigma - qd_dot^T M sigma`` (000 (51))."""
    M = np.asarray(M, float)
    sigma = np.asarray(sigma, float).ravel()
    out = -0.5 * (1 - e) / (1 + e) * sigma @ M @ sigma
    if qd_dot is not None:
        out -= np.asarray(qd_dot, float).ravel() @ M @ sigma
    return float(out)


def desired_velocity_condition(cs, q, w, qd_dot, *, gap_tol: float = 1e-9, vel_tol: float = 1e-9,
                               theta=None):
    """Check 000 (52) (impacts, ``w = (v+ + e v-)/(1+e)``) or (54) (persistent
    contact, ``w = v``).

    Returns
    -------
    ok : bool
    margins : ndarray
        ``grad f_i^T qd_dot`` over the contacts of ``K(w)`` (must be >= 0).
    K : ndarray of int
        The contacts with ``f_i = 0`` and ``grad f_i^T w = 0``.
    """
    W = cs.gradients(q, theta)
    g = cs.gaps(q, theta)
    w = np.asarray(w, float).ravel()
    K = np.flatnonzero((g <= gap_tol) & (np.abs(W.T @ w) <= vel_tol))
    margins = W[:, K].T @ np.asarray(qd_dot, float).ravel()
    return bool(np.all(margins >= -vel_tol)), margins, K
