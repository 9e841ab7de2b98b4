"""Persistent-contact ("pre-loading") control, 000 Sect. 3, (9)-(13).

With the active gaps ``f'`` (``m_u'`` of them), ``W = grad f'``,
``D = W^T M^{-1} W`` (7), the contact multiplier is ``lam' = w_hat - E_hat tau``
with

    E_hat = D^{-1} W^T M^{-1} E,                       (11)
    w_hat = D^{-1} (-d/dt(W^T) v - W^T M^{-1} f)       (f = -C v - g here)

A desired multiplier ``lam' = beta > 0`` is reachable for every ``beta`` iff
``rank E_hat = m_u'`` (Lemma 1, which needs ``p >= m_u'``, Corollary 1); the
law (13) is

    tau = E_hat^+ (w_hat - beta) + (I - E_hat^+ E_hat) tau_bar.

Bilateral constraints are not supported here (the paper sets ``m_b = 0``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import casadi as ca
import numpy as np

from ..contact.mechanics import ContactSystem
from ..errors import ModelError, PreloadInfeasible
from .pdplus import FeedbackLaw


def preload_terms(model, active: Sequence[int]):
    """Symbolic ``(E_hat, w_hat, D, W)`` of (11) for the active gaps."""
    if model.ell:
        raise ModelError("pre-loading control (000 (11)-(13)) is implemented for m_b = 0 (no bilateral constraints)")
    cs = ContactSystem(model)
    active = [int(i) for i in active]
    W = cs.W[:, active]
    Wdv = cs.Wdot_v[active]
    MiW = ca.solve(model.M, W)
    D = ca.mtimes(W.T, MiW)
    Ehat = ca.solve(D, ca.mtimes(MiW.T, model.B))
    what = ca.solve(D, -Wdv - ca.mtimes(MiW.T, model.f))
    return Ehat, what, D, W


@dataclass(frozen=True)
class PreloadCheck:
    """Numbers of Lemma 1 at one state."""

    E_hat: np.ndarray
    w_hat: np.ndarray
    rank: int
    m_active: int
    p: int
    sigma_min: float
    feasible: bool


def preload_check(model, q, v, active: Sequence[int], *, rtol: float = 1e-9, raise_: bool = True) -> PreloadCheck:
    """Existence check of Lemma 1 / Corollary 1 at ``(q, v)``.

    Raises
    ------
    PreloadInfeasible
        ``p < m_u'`` (Corollary 1) or ``rank E_hat < m_u'`` (Lemma 1).
    """
    active = [int(i) for i in active]
    p, mu = model.m, len(active)
    if p < mu:
        if raise_:
            raise PreloadInfeasible(
                f"pre-loading {mu} contacts {active} needs at least {mu} inputs (000 Corollary 1), model has p = {p}; "
                "add actuators or keep fewer contacts closed", diagnostics={"p": p, "m_active": mu})
    Ehat, what, _, _ = preload_terms(model, active)
    fn = ca.Function("pre", [model.q, model.v, model.theta], [Ehat, what])
    E, w = fn(np.asarray(q, float), np.asarray(v, float), model.theta_values)
    E = np.array(E).reshape(mu, p)
    w = np.array(w).ravel()
    s = np.linalg.svd(E, compute_uv=False) if E.size else np.zeros(0)
    smin = float(s.min()) if s.size >= mu and mu else 0.0
    rank = int(np.sum(s > rtol * max(1.0, s.max(initial=0.0))))
    feasible = p >= mu and rank == mu
    if not feasible and raise_:
        raise PreloadInfeasible(
            f"000 Lemma 1 fails: rank(E_hat) = {rank} < m_u' = {mu} for contacts {active} "
            f"(smallest singular value {smin:.3g}); the inputs cannot set every contact multiplier",
            diagnostics={"rank": rank, "sigma_min": smin, "E_hat": E.tolist()})
    return PreloadCheck(E, w, rank, mu, p, smin, feasible)


def preload_law(model, active: Sequence[int], *, beta, tau_bar=None, Kp=None, Kv=None, y_d=None) -> FeedbackLaw:
    """The pre-loading law (13) keeping contacts ``active`` closed with ``lam' = beta``.

    ``tau_bar`` (the free part, projected on ``ker E_hat``) is either a
    callable ``tau_bar(model, t, kappa_rest) -> SX`` or, by default, a
    collocated PD ``-Kp (B^T q - y_d) - Kv B^T v`` with gains carried as law
    parameters (``beta*``, ``Kp*``, ``Kv*``, ``yd*``).
    """
    active = [int(i) for i in active]
    mu, p = len(active), model.m
    if p < mu:
        raise PreloadInfeasible(f"pre-loading {mu} contacts needs p >= {mu} inputs (000 Corollary 1), model has p = {p}",
                                diagnostics={"p": p, "m_active": mu})
    beta = np.broadcast_to(np.asarray(beta, float), (mu,))
    if np.any(beta <= 0):
        raise PreloadInfeasible(f"desired multipliers beta must be positive (000 (11)), got {beta.tolist()}")
    Kp = np.broadcast_to(np.asarray(0.0 if Kp is None else Kp, float), (p,))
    Kv = np.broadcast_to(np.asarray(0.0 if Kv is None else Kv, float), (p,))
    y_d = np.broadcast_to(np.asarray(0.0 if y_d is None else y_d, float), (p,))
    names = tuple([f"beta{i + 1}" for i in range(mu)] + [f"Kp{j + 1}" for j in range(p)]
                  + [f"Kv{j + 1}" for j in range(p)] + [f"yd{j + 1}" for j in range(p)])

    def build(model, t, kappa):
        Ehat, what, _, _ = preload_terms(model, active)
        b = kappa[0:mu]
        kp, kv, yd = kappa[mu:mu + p], kappa[mu + p:mu + 2 * p], kappa[mu + 2 * p:mu + 3 * p]
        Epinv = ca.mtimes(Ehat.T, ca.inv(ca.mtimes(Ehat, Ehat.T)))
        if callable(tau_bar):
            tb = ca.SX(tau_bar(model, t, kappa))
        else:
            tb = -kp * (ca.mtimes(model.B.T, model.q) - yd) - kv * ca.mtimes(model.B.T, model.v)
        u = ca.mtimes(Epinv, what - b) + tb - ca.mtimes(Epinv, ca.mtimes(Ehat, tb))
        V = 0.5 * ca.mtimes([model.v.T, model.M, model.v])
        return u, V

    return FeedbackLaw("preload", names, tuple(np.r_[beta, Kp, Kv, y_d]), build,
                       {"active": active, "lyapunov": False})
