"""Lyapunov monitoring for systems with clearances, 000 (37), (39), (50)-(55).

* :func:`lyapunov_report` -- ``V(t)`` history of a contact simulation, its
  jumps at impact steps and its largest increase (000 (39)/(55) say ``V``
  never increases for the PD (36) law and, under (52)/(54), for PD+ (48));
* :func:`impact_jump_51` -- the predicted jump (51) of ``V`` at an impact;
* :func:`equilibrium_check` -- Lemma 2: rest points of the closed loop (40)-(41);
* :func:`desired_velocity_condition` -- conditions (52)/(54): the desired
  velocity must lie in the tangent cone ``T_{T_Phi(q)}(w)``, i.e.
  ``grad f_i^T qd_dot >= 0`` for every contact with ``f_i(q) = 0`` and
  ``grad f_i^T w = 0``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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
    """Jumps of ``tr.V`` at the impact steps of a :class:`ContactTrajectory` (for decimated or event
    records from the run's exact accumulators, which see every step)."""
    if not getattr(tr, "complete", True):
        dV_max = tr.max_V_increase  # a run that did not monitor V: RecordingError naming the option
        st = tr.stats
        jumps = np.asarray(st.get("impact_dV", np.zeros(0)), float)
        return LyapunovReport(max(0.0, dV_max), max(0.0, float(st["dV_max_impact"])),
                              max(0.0, float(st["dV_max_smooth"])), jumps, int(st.get("n_impacts", jumps.size)),
                              float(tr.V[0]), float(tr.V[-1]))
    dV = np.diff(tr.V)
    imp = np.any(tr.impact_mask(), axis=0)  # (contacts, steps) -> steps
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


@dataclass(frozen=True)
class EquilibriumCheck:
    """Lemma 2 of 000 at one configuration.

    Attributes
    ----------
    is_equilibrium : bool
    residual : float
        ``min_{lam >= 0} |G(q*) - sum_{i in I} lam_i grad f_i|`` (NNLS).
    lam : ndarray
        Multipliers of the closed contacts (NNLS solution).
    closed : ndarray of int
        Contacts with ``f_i(q*) <= gap_tol``.
    projector_residual : float
        ``|(I - W D^{-1} W^T M^{-1}) G|`` (the equivalent form of Lemma 2 (ii)
        for independent constraints; printed with ``D`` in place of ``D^{-1}``).
    """

    is_equilibrium: bool
    residual: float
    lam: np.ndarray
    closed: np.ndarray
    projector_residual: float


def equilibrium_check(cs, q, G, *, gap_tol: float = 1e-9, rtol: float = 1e-8, theta=None) -> EquilibriumCheck:
    """Is ``q`` a rest point of ``M q'' + G(q) = grad f lam`` (000 (40)-(41), Lemma 2)?

    ``G`` is the closed-loop potential force at ``q`` (e.g. ``(Kp (q1 - q1d), G_4, G_5)``).
    Interior points (no closed gap) are equilibria iff ``G = 0`` (Lemma 2 (i)); boundary points
    iff ``G`` is a non-negative combination of the closed contacts' normals (Lemma 2 (ii)).
    """
    from scipy.optimize import nnls

    G = np.asarray(G, float).ravel()
    g = cs.gaps(q, theta)
    closed = np.flatnonzero(g <= gap_tol)
    scale = max(1.0, float(np.linalg.norm(G)))
    if closed.size == 0:
        res = float(np.linalg.norm(G))
        return EquilibriumCheck(res <= rtol * scale, res, np.zeros(0), closed, res)
    W = cs.gradients(q, theta)[:, closed]
    lam, res = nnls(W, G)
    M = cs.model.evaluate("M", q) if theta is None else np.array(cs.model.function("M")(q, theta))
    MiW = np.linalg.solve(M, W)
    D = W.T @ MiW
    proj = np.eye(G.size) - W @ np.linalg.solve(D, MiW.T) if np.linalg.matrix_rank(D) == D.shape[0] else None
    pres = float(np.linalg.norm(proj @ G)) if proj is not None else float("nan")
    return EquilibriumCheck(bool(res <= rtol * scale), float(res), lam, closed, pres)
