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

from typing import Any

from dataclasses import dataclass
from functools import cached_property

import casadi as ca
import numpy as np

from ..errors import DimensionError, ModelError

_CACHE_ATTR = "_analysis_cache"


def cache_of(model) -> dict:
    """The store of objects derived from a model's symbols (analysis and inversion; made with the model,
    or on first use for objects that are not :class:`~invctl.model.Model` instances).

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
        ``M^-1 [J^T G^T B]`` and ``M^-1 f`` (solves with the shared LDL^T factors of ``M``,
        :func:`mass_solver`).
    blocks : tuple of int
        ``(p, l, m)``: sizes of ``O1``, ``O2``, ``O3``.
    """

    model: Any
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


def mass_solver(model):
    """The :class:`~invctl.model.linalg.SymmetricSolver` of ``model.M`` (one symbolic LDL^T, cached):
    every ``M^-1`` of the analysis is a solve with these factors, O(n^2) per right-hand side."""
    from ..model.linalg import SymmetricSolver

    return cached(model, "mass_solver", lambda: SymmetricSolver(model.M))


def auxiliary_system(model) -> AuxiliarySystem:
    """The auxiliary ODE (10) of ``model`` (cached)."""

    def build():
        n = model.n
        Bt = ca.horzcat(model.J.T, model.G.T, ca.SX(model.B))
        solver = mass_solver(model)
        MinvBt = solver.solve(Bt)
        Minvf = solver.solve(model.f)
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
#: Half-width (per coordinate, in the units of q) of the neighbourhood of operating points that is
#: sampled when a model declares no region: 0.1 rad is about 6 degrees, 0.1 m a tenth of a metre-sized
#: mechanism, i.e. the tracking errors a feedback (003 Sect. 5 funnels) is designed to keep.
NEIGHBOURHOOD_RADIUS = 0.1
#: Velocities are sampled in [-1, 1] around the points' velocities, as the box used without points
#: and the default ``OperatingRegion.v_scale``.
NEIGHBOURHOOD_V_RADIUS = 1.0


def as_points(model, points) -> list:
    """``points`` (``q`` rows, ``(q, v)`` tuples, or an iterable of them) as a list of ``(q, v)``."""
    out = []
    for pt in points if points is not None else ():
        if isinstance(pt, tuple) and len(pt) == 2:
            qp, vp = pt
        else:
            qp, vp = pt, np.zeros(model.n)
        qp, vp = np.asarray(qp, float).ravel(), np.asarray(vp, float).ravel()
        if qp.size != model.n or vp.size != model.n:
            raise DimensionError(f"{model.name}: a sample point needs q and v of length n = {model.n}, got "
                                 f"{qp.size} and {vp.size}")
        out.append((qp, vp))
    return out


def _radius(model, radius, default, name) -> np.ndarray:
    try:
        r = np.broadcast_to(np.asarray(default if radius is None else radius, float), (model.n,)).copy()
    except (ValueError, TypeError):
        r = None
    if r is None or not np.all(np.isfinite(r)) or np.any(r < 0):
        raise DimensionError(f"{model.name}: {name} must be a non-negative number or n = {model.n} numbers, "
                             f"got {radius!r}")
    return r


def neighbourhood_samples(model, points, count: int, rng=0, *, radius=None, v_radius=None):
    """``count`` samples ``(q, v)`` of the tube around the polyline through ``points``.

    A base point is drawn uniformly along the polyline ``points[0] -> points[1] -> ...`` (the
    equilibria along a reference, in order; one point gives a box), then offset uniformly by
    ``|dq_i| <= radius`` and ``|dv_i| <= v_radius`` (defaults :data:`NEIGHBOURHOOD_RADIUS`,
    :data:`NEIGHBOURHOOD_V_RADIUS`; scalars or one value per coordinate).  The tube is
    connected, so a sign change of ``det Gamma`` on it still implies a singular point in it.
    """
    pts = as_points(model, points)
    if not pts:
        raise ModelError(f"{model.name}: sampling a neighbourhood needs at least one operating point")
    rq = _radius(model, radius, NEIGHBOURHOOD_RADIUS, "radius")
    rv = _radius(model, v_radius, NEIGHBOURHOOD_V_RADIUS, "v_radius")
    P = np.array([p[0] for p in pts])
    V = np.array([p[1] for p in pts])
    gen = np.random.default_rng(rng)
    if len(pts) == 1:
        qb, vb = np.repeat(P, count, axis=0), np.repeat(V, count, axis=0)
    else:
        s = gen.uniform(0.0, len(pts) - 1, count)
        i = np.minimum(s.astype(int), len(pts) - 2)
        w = (s - i)[:, None]
        qb, vb = (1 - w) * P[i] + w * P[i + 1], (1 - w) * V[i] + w * V[i + 1]
    return qb + gen.uniform(-1, 1, qb.shape) * rq, vb + gen.uniform(-1, 1, vb.shape) * rv


def uses_neighbourhood(model, points, radius) -> bool:
    """True if :func:`region_samples` draws from the neighbourhood of ``points`` (see there)."""
    return bool(points is not None and len(as_points(model, points)) and (model.region is None or radius is not None))


def sampling_domain(model, points=None, radius=None, v_radius=None) -> str:
    """Where :func:`region_samples` draws its samples, in words (for reports)."""
    if uses_neighbourhood(model, points, radius):
        rq = _radius(model, radius, NEIGHBOURHOOD_RADIUS, "radius")
        rv = _radius(model, v_radius, NEIGHBOURHOOD_V_RADIUS, "v_radius")
        fmt = lambda r: f"{r[0]:.3g}" if np.all(r == r[0]) else str(np.round(r, 4).tolist())  # noqa: E731
        k = len(as_points(model, points))
        where = f"the neighbourhood |dq_i| <= {fmt(rq)}, |dv_i| <= {fmt(rv)} of {k} operating point(s)"
        if model.region is not None:
            where += f" within {model.region.description or 'the operating region'}"
        return where
    if model.region is not None:
        return model.region.description or "the operating region"
    return "the box |q_i|, |v_i| <= 1 (no region declared)"


def region_samples(model, samples: int, rng=0, points=None, *, radius=None,
                   v_radius=None) -> tuple[np.ndarray, np.ndarray]:
    """``(q, v)`` sample points (rows): ``samples`` drawn points, then ``points`` themselves.

    The drawn points come from

    * the model's operating region (``model.region``) if it declares one and ``radius`` is None;
    * otherwise, if ``points`` are given, the neighbourhood of the points
      (:func:`neighbourhood_samples`; intersected with the region if one is declared);
    * otherwise the box ``[-1, 1]`` in every ``q`` and ``v``.
    """
    pts = as_points(model, points)
    qs, vs = [], []
    if samples:
        if uses_neighbourhood(model, pts, radius):
            q, v = _neighbourhood_in_region(model, pts, samples, rng, radius, v_radius)
        elif model.region is not None:
            q, v = model.region.sample(samples, rng)
        else:
            gen = np.random.default_rng(rng)
            q, v = gen.uniform(-1, 1, (samples, model.n)), gen.uniform(-1, 1, (samples, model.n))
        qs.append(q)
        vs.append(v)
    for qp, vp in pts:
        qs.append(qp.reshape(1, model.n))
        vs.append(vp.reshape(1, model.n))
    if not qs:
        raise ModelError("no sample points: give samples > 0 or points")
    return np.vstack(qs), np.vstack(vs)


def _neighbourhood_in_region(model, pts, samples, rng, radius, v_radius, max_rounds: int = 50):
    if model.region is None:
        return neighbourhood_samples(model, pts, samples, rng, radius=radius, v_radius=v_radius)
    gen = np.random.default_rng(rng)
    keep_q, keep_v, have = [], [], 0
    for _ in range(max_rounds):
        q, v = neighbourhood_samples(model, pts, 4 * samples, gen, radius=radius, v_radius=v_radius)
        ok = np.array([model.region.contains(qk) for qk in q])
        keep_q.append(q[ok])
        keep_v.append(v[ok])
        have += int(ok.sum())
        if have >= samples:
            return np.vstack(keep_q)[:samples], np.vstack(keep_v)[:samples]
    raise ModelError(f"{model.name}: could not draw {samples} samples of the neighbourhood of the operating points "
                     f"inside {model.region.description or 'the operating region'} (got {have}); the points lie "
                     "outside the region or the radius is too small to meet it")


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
