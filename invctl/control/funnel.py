"""Funnel functions phi of 003 (8)-(9) with derivatives by automatic differentiation.

The performance funnel is ``F_phi = {(t, e) : phi(t) ||e|| < 1}``; its boundary is
``1/phi``.  A funnel function must belong to

    Phi_k = { phi in C^k(R>=0 -> R) : phi, phi', ..., phi^(k) bounded,
              phi(t) > 0 for t > 0,  liminf_{t -> inf} phi(t) > 0 }            (9)

:class:`Funnel` holds ``phi`` as a CasADi expression of a scalar time symbol, so a
controller can embed it (and its exact derivatives) in a compiled right-hand side.
:meth:`Funnel.check` decides membership in ``Phi_k``: analytically for the
exponential family ``phi(t) = (p e^(-q t) + r)^(-1)`` of 003 Sect. 6, by sampling
(dense log-spaced grid up to a long horizon, with a tail-growth test) otherwise.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from ..errors import ParameterError


@dataclass(frozen=True)
class FunnelCheck:
    """Result of :meth:`Funnel.check` (membership in ``Phi_k`` of 003 (9)).

    Attributes
    ----------
    passed : bool
        All conditions hold.
    k : int
        Number of derivatives that must be bounded.
    method : str
        ``"analytic"`` (closed-form argument) or ``"sampled"``.
    bounds : tuple of float
        ``sup |phi^(j)|`` for ``j = 0..k`` (sampled; exact for the analytic case where known).
    min_positive : float
        ``min phi(t)`` over the sampled ``t > 0``.
    liminf : float
        Estimate (sampled) or exact value (analytic) of ``liminf phi``.
    problems : tuple of str
        What failed, in words.
    """

    passed: bool
    k: int
    method: str
    bounds: tuple
    min_positive: float
    liminf: float
    problems: tuple = field(default_factory=tuple)

    def to_dict(self) -> dict:
        return {"passed": self.passed, "k": self.k, "method": self.method, "bounds": list(self.bounds),
                "min_positive": self.min_positive, "liminf": self.liminf, "problems": list(self.problems)}


class Funnel:
    """A funnel function ``phi(t)`` given as a CasADi SX expression of ``t``.

    Parameters
    ----------
    t : casadi.SX
        Scalar time symbol.
    expr : casadi.SX
        Scalar expression of ``t`` (smooth on ``t >= 0``).
    name : str
        Used in messages and plots.
    params : dict, optional
        Parameters of a named family (``{"p":.., "q":.., "r":..}`` for the exponential one);
        enables the analytic membership check.
    """

    def __init__(self, t: ca.SX, expr, name: str = "phi", params: dict | None = None):
        expr = ca.SX(expr)
        if expr.numel() != 1:
            raise ParameterError(f"funnel {name!r}: phi must be a scalar expression of t, got shape {expr.shape}")
        stray = {s.name() for s in ca.symvar(expr)} - {t.name()}
        if stray:
            raise ParameterError(f"funnel {name!r}: phi depends on symbols {sorted(stray)} other than t")
        self.t = t
        self.expr = expr
        self.name = name
        self.params = dict(params or {})

    # ----------------------------------------------------------- construction
    @classmethod
    def exponential(cls, p: float, q: float, r: float, name: str = "phi") -> "Funnel":
        """``phi(t) = (p e^(-q t) + r)^(-1)`` (003 Sect. 6); boundary ``1/phi`` decays from ``p + r`` to ``r``."""
        p, q, r = float(p), float(q), float(r)
        if not (r > 0 and p >= 0 and q >= 0):
            raise ParameterError(
                f"exponential funnel {name!r}: need p >= 0, q >= 0, r > 0 (got p={p}, q={q}, r={r}); "
                "r is the final funnel width 1/liminf phi and must be positive")
        t = ca.SX.sym("t")
        return cls(t, 1.0 / (p * ca.exp(-q * t) + r), name, {"family": "exponential", "p": p, "q": q, "r": r})

    @classmethod
    def constant(cls, width: float, name: str = "phi") -> "Funnel":
        """A funnel of constant width ``1/phi = width``."""
        return cls.exponential(0.0, 0.0, width, name)

    @classmethod
    def from_callable(cls, fn, name: str = "phi") -> "Funnel":
        """``fn(t)`` built from CasADi operations (``ca.exp``, ``ca.sin``, ...) on an SX ``t``."""
        t = ca.SX.sym("t")
        return cls(t, fn(t), name)

    # -------------------------------------------------------------- evaluation
    def of(self, t) -> ca.SX | ca.MX:
        """The expression ``phi(t)`` with the time symbol replaced by ``t`` (SX or MX)."""
        return self.function(0)(t)[0] if isinstance(t, ca.MX) else ca.substitute(self.expr, self.t, t)

    def function(self, order: int = 0) -> ca.Function:
        """``t -> (phi, phi', ..., phi^(order))`` (outputs ``d0``..``d<order>``; built once per order)."""
        cache = self.__dict__.setdefault("_functions", {})
        if order not in cache:
            cache[order] = self._function(order)
        return cache[order]

    def _function(self, order: int) -> ca.Function:
        outs = [self.expr]
        for _ in range(order):
            outs.append(ca.jacobian(outs[-1], self.t))
        base = re.sub(r"_+", "_", re.sub(r"[^A-Za-z0-9]", "_", self.name)).strip("_") or "phi"
        base = base if base[0].isalpha() else "phi_" + base
        return ca.Function(f"{base}_d{order}", [self.t], outs, ["t"], [f"d{k}" for k in range(order + 1)])

    def __call__(self, t, order: int = 0) -> np.ndarray:
        """``phi^(order)`` at times ``t`` (1-D array)."""
        t = np.atleast_1d(np.asarray(t, float))
        out = self.function(order).map(t.size)(t[None, :])
        out = out[-1] if isinstance(out, (list, tuple)) else out
        return np.array(out).ravel()

    def boundary(self, t) -> np.ndarray:
        """The funnel boundary ``1/phi(t)``."""
        return 1.0 / self(t)

    # ---------------------------------------------------------------- (9) test
    def check(self, k: int, *, horizon: float = 1e4, samples: int = 4000, t_scale: float | None = None) -> FunnelCheck:
        """Membership of ``phi`` in ``Phi_k`` (003 (9)).

        For the exponential family the answer is analytic: with ``p >= 0``, ``q >= 0``,
        ``r > 0`` the denominator lies in ``[r, p + r]``, so ``phi`` is positive with
        ``liminf phi = 1/r``, and every derivative is a bounded combination of
        ``e^(-q t)`` and powers of ``phi``.  Otherwise ``phi`` and its derivatives are
        sampled on ``(0, horizon]`` (log-spaced from ``1e-6 t_scale``) and on a dense linear
        grid of the first ``20 t_scale`` seconds; bounded means finite and not growing over
        the last decade of the horizon (sup over ``[h/10, h]`` no larger than 1.5 times the
        sup over ``[h/100, h/10]`` plus a small absolute slack); ``liminf > 0`` means the
        minimum over the last decade is positive and at least half that of the decade before
        (a sampled test: a function decaying slower than that, e.g. ``1/log t``, passes).
        """
        k = int(k)
        if k < 0:
            raise ParameterError(f"Phi_k needs k >= 0, got {k}")
        sampled = self._sampled(k, horizon, samples, t_scale)
        if self.params.get("family") == "exponential":
            p, r = self.params["p"], self.params["r"]
            problems = []
            if not r > 0:
                problems.append(f"r = {r} must be > 0 (liminf phi = 1/r)")
            return FunnelCheck(not problems, k, "analytic", sampled.bounds, 1.0 / (p + r), 1.0 / r, tuple(problems))
        return sampled

    def _sampled(self, k, horizon, samples, t_scale) -> FunnelCheck:
        t_scale = float(t_scale) if t_scale else 1.0
        t_log = np.logspace(np.log10(1e-6 * t_scale), np.log10(horizon), samples)
        t_lin = np.linspace(0.0, 20 * t_scale, samples)
        ts = np.unique(np.concatenate([t_lin, t_log]))
        fn = self.function(k).map(ts.size)
        outs = fn(ts[None, :])
        outs = outs if isinstance(outs, (list, tuple)) else [outs]
        vals = [np.array(o).ravel() for o in outs]
        problems = []
        bounds = []
        for j, d in enumerate(vals):
            if not np.all(np.isfinite(d)):
                bad = ts[~np.isfinite(d)][0]
                problems.append(f"phi^({j}) is not finite at t = {bad:.3g}")
                bounds.append(float("inf"))
                continue
            tail = np.abs(d[ts >= horizon / 10]).max()
            before = np.abs(d[(ts >= horizon / 100) & (ts < horizon / 10)]).max()
            if tail > 1.5 * before + 1e-9 * max(1.0, np.abs(d).max()):
                problems.append(f"phi^({j}) grows over the horizon (sup {before:.3g} on [h/100, h/10], "
                                f"{tail:.3g} on [h/10, h]): not bounded")
            bounds.append(float(np.abs(d).max()))
        phi = vals[0]
        positive = phi[ts > 0]
        min_pos = float(positive.min()) if positive.size else float("nan")
        if not min_pos > 0:
            problems.append(f"phi(t) <= 0 at t = {ts[ts > 0][np.argmin(positive)]:.3g} (must be > 0 for t > 0)")
        liminf = float(phi[ts >= horizon / 10].min())
        before = float(phi[(ts >= horizon / 100) & (ts < horizon / 10)].min())
        if not liminf > 1e-12 or liminf < 0.5 * before:
            problems.append(f"liminf phi ~ {liminf:.3g} is not positive (min {before:.3g} on [h/100, h/10], "
                            f"{liminf:.3g} on [h/10, h]): the funnel would widen without bound")
        return FunnelCheck(not problems, k, "sampled", tuple(bounds), min_pos, liminf, tuple(problems))

    def __repr__(self) -> str:
        if self.params.get("family") == "exponential":
            p = self.params
            return f"Funnel.exponential(p={p['p']:g}, q={p['q']:g}, r={p['r']:g}, name={self.name!r})"
        return f"Funnel({self.expr}, name={self.name!r})"


def as_funnel(spec, name: str = "phi") -> Funnel:
    """A :class:`Funnel` from a Funnel, a ``(p, q, r)`` triple, a dict ``{"p", "q", "r"}`` or a callable of SX ``t``."""
    if isinstance(spec, Funnel):
        return spec
    if isinstance(spec, dict):
        return Funnel.exponential(spec["p"], spec["q"], spec["r"], name)
    if isinstance(spec, (tuple, list)) and len(spec) == 3:
        return Funnel.exponential(spec[0], spec[1], spec[2], name=name)
    if callable(spec):
        return Funnel.from_callable(spec, name)
    raise ParameterError(f"cannot make a funnel function from {spec!r}: give (p, q, r), a dict or a callable of t")
