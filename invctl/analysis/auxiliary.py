"""The auxiliary ODE 003 (10) and the helpers every analysis step shares.

With ``x = (q, v)`` and ``u_aux = (mu, lam, u)`` the multibody DAE 003 (1)
without its constraints is the ODE

    x' = F(x) + K(x) u_aux,    y_aux = O(x) = (J v + j, g, h),

    F(x) = (v, M^-1 f),    K(x) = diag(I, M^-1) [0; J^T  G^T  B].

Everything here is symbolic in ``(q, v, theta)``; derivations are cached on
the model (shared by ``with_params`` copies, which share the symbols), so a
scene that never asks for them never pays for them.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import casadi as ca
import numpy as np

from ..errors import DimensionError, ModelError

_CACHE_ATTR = "_analysis_cache"


def cache_of(model) -> dict:
    """The analysis cache of a model (created on first use).

    Symbolic entries depend only on the symbols and are valid for every
    ``with_params`` copy; numeric entries must key on ``theta_values``.
    """
    cache = model.__dict__.get(_CACHE_ATTR)
    if cache is None:
        cache = {}
        model.__dict__[_CACHE_ATTR] = cache
    return cache


def cached(model, key, build):
    cache = cache_of(model)
    if key not in cache:
        cache[key] = build()
    return cache[key]


@dataclass(frozen=True)
class AuxiliarySystem:
    """The auxiliary ODE (10) of a model, as CasADi SX expressions.

    Attributes
    ----------
    x : casadi.SX
        ``(q, v)``.
    F, K : casadi.SX
        Drift (2n) and input matrix (2n x (p + l + m)).
    O : casadi.SX
        Auxiliary output ``(J v + j, g, h)``.
    Bt : casadi.SX
        ``[J^T, G^T, B]`` (n x (p + l + m)).
    MinvBt, Minvf : casadi.SX
        ``M^-1 [J^T G^T B]`` and ``M^-1 f`` (symbolic solves).
    blocks : tuple of int
        ``(p, l, m)``: sizes of ``O1``, ``O2``, ``O3``.
    """

    model: object
    x: ca.SX
    F: ca.SX
    K: ca.SX
    O: ca.SX
    Bt: ca.SX
    MinvBt: ca.SX
    Minvf: ca.SX
    blocks: tuple

    @property
    def n_aux(self) -> int:
        return self.O.shape[0]

    @cached_property
    def function(self) -> ca.Function:
        """``(q, v, u_aux, theta) -> (x_dot, y_aux)`` of (10)."""
        m = self.model
        ua = ca.SX.sym("u_aux", self.K.shape[1])
        return ca.Function(
            "aux_ode", [m.q, m.v, ua, m.theta], [self.F + ca.mtimes(self.K, ua), self.O],
            ["q", "v", "u_aux", "theta"], ["x_dot", "y_aux"],
        )

    def lie_F(self, expr: ca.SX) -> ca.SX:
        """``L_F expr = d expr/dq v + d expr/dv M^-1 f``."""
        m = self.model
        out = ca.mtimes(ca.jacobian(expr, m.q), m.v)
        dv = ca.jacobian(expr, m.v)
        if dv.nnz():
            out = out + ca.mtimes(dv, self.Minvf)
        return out

    def lie_K(self, expr: ca.SX) -> ca.SX:
        """``L_K expr = d expr/dv M^-1 [J^T G^T B]`` (the q-block of K is zero)."""
        return ca.mtimes(ca.jacobian(expr, self.model.v), self.MinvBt)


def auxiliary_system(model) -> AuxiliarySystem:
    """The auxiliary ODE (10) of ``model`` (cached)."""

    def build():
        n = model.n
        Bt = ca.horzcat(model.J.T, model.G.T, ca.SX(model.B))
        MinvBt = ca.solve(model.M, Bt)
        Minvf = ca.solve(model.M, model.f)
        F = ca.vertcat(model.v, Minvf)
        K = ca.vertcat(ca.SX(n, Bt.shape[1]), MinvBt)
        O = ca.vertcat(ca.mtimes(model.J, model.v) + model.j, model.g, model.h)
        return AuxiliarySystem(model, ca.vertcat(model.q, model.v), F, K, O, Bt, MinvBt, Minvf,
                               (model.p, model.ell, model.ny))

    if model.ny != model.m:
        raise DimensionError(
            f"model {model.name!r}: the analysis needs as many outputs as inputs (h has {model.ny}, "
            f"B has {model.m} columns); give the model an output h"
        )
    return cached(model, "aux", build)


# ----------------------------------------------------------------- sampling
def region_samples(model, samples: int, rng=0, points=None) -> tuple[np.ndarray, np.ndarray]:
    """``(q, v)`` sample points (rows) of the model's operating region, plus ``points``.

    Without a region, ``q`` and ``v`` are drawn from ``[-1, 1]``.
    """
    qs, vs = [], []
    if samples:
        if model.region is not None:
            q, v = model.region.sample(samples, rng)
        else:
            gen = np.random.default_rng(rng)
            q, v = gen.uniform(-1, 1, (samples, model.n)), gen.uniform(-1, 1, (samples, model.n))
        qs.append(q)
        vs.append(v)
    for pt in points or ():
        if isinstance(pt, tuple) and len(pt) == 2:
            qp, vp = pt
        else:
            qp, vp = pt, np.zeros(model.n)
        qs.append(np.asarray(qp, float).reshape(1, model.n))
        vs.append(np.asarray(vp, float).reshape(1, model.n))
    if not qs:
        raise ModelError("no sample points: give samples > 0 or points")
    return np.vstack(qs), np.vstack(vs)


def eval_batch(fn: ca.Function, *args, theta) -> list[np.ndarray]:
    """Evaluate a Function of ``(*args, theta)`` at N points (rows of each arg) at once.

    Returns one array per output with shape ``(N, rows, cols)``.
    """
    N = args[0].shape[0]
    mapped = fn.map(N)
    ins = [np.asarray(a, float).T for a in args] + [np.tile(np.asarray(theta, float)[:, None], (1, N))]
    outs = mapped(*ins)
    if not isinstance(outs, (list, tuple)):
        outs = [outs]
    res = []
    for k, o in enumerate(outs):
        r, c = fn.size_out(k)
        res.append(np.array(o).reshape(r, N, c).transpose(1, 0, 2))
    return res


def consistent_state(model, q, v=None, *, tol: float = 1e-12, max_iter: int = 50):
    """Project ``(q, v)`` onto the constraints: ``g(q) = 0`` (Gauss-Newton,
    least-norm steps) and ``J v + j = 0``, ``G v = 0`` (least-norm correction).

    Raises
    ------
    ModelError
        If Newton does not converge (the point is too far from the constraint manifold).
    """
    q = np.asarray(q, float).ravel().copy()
    v = np.zeros(model.n) if v is None else np.asarray(v, float).ravel().copy()
    th = model.theta_values
    if model.ell:
        g, G = model.function("g"), model.function("G")
        for _ in range(max_iter):
            r = np.array(g(q, th)).ravel()
            if np.max(np.abs(r)) < tol:
                break
            Gk = np.array(G(q, th))
            q -= np.linalg.lstsq(Gk, r, rcond=None)[0]
        else:
            raise ModelError(
                f"{model.name}: could not project q onto g(q) = 0 (residual {np.max(np.abs(r)):.3g}); "
                "start closer to a consistent configuration"
            )
    C = np.vstack([model.evaluate("J", q), model.evaluate("G", q)]) if (model.p + model.ell) else None
    if C is not None and C.size:
        rhs = np.concatenate([-model.evaluate("j", q).ravel(), np.zeros(model.ell)])
        v += np.linalg.lstsq(C, rhs - C @ v, rcond=None)[0]
    return q, v
