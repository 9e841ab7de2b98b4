"""Reference signals as CasADi expressions of time, with exact derivatives by AD."""
from __future__ import annotations

from typing import Sequence

import casadi as ca
import numpy as np

from ..errors import ReferenceSignalError


def poly9_timing_law(t: ca.SX, t0: float, tf: float) -> ca.SX:
    """The timing law of 003 Sect. 6: ``r = 70 s^9 - 315 s^8 + 540 s^7 - 420 s^6 + 126 s^5``,
    ``s = (t - t0)/(tf - t0)`` clipped to [0, 1].

    ``r`` rises from 0 to 1 with derivatives 1..4 vanishing at both ends, so the
    glued signal is C^4 (and in W^{5,inf}).  :func:`invctl.reference.rest_to_rest`
    gives the same law for any smoothness and vector end points.
    """
    if not tf > t0:
        raise ReferenceSignalError(f"timing law needs tf > t0, got t0={t0}, tf={tf}")
    s = (t - t0) / (tf - t0)
    r = 70 * s**9 - 315 * s**8 + 540 * s**7 - 420 * s**6 + 126 * s**5
    return ca.if_else(s <= 0, 0, ca.if_else(s >= 1, 1, r))


class Reference:
    """A reference ``y_ref(t)`` given as a CasADi SX expression of a scalar ``t``.

    Parameters
    ----------
    t : casadi.SX
        The scalar time symbol.
    expr : casadi.SX
        Column expression of ``t`` (m components).
    t0, tf : float
        Start and end of the transition (constant outside).
    smoothness : int
        Number of continuous derivatives (``y_ref`` in C^smoothness); users
        of the reference ask for what they need with ``require``.
    name : str
        Used in messages.
    diagnostics : dict, optional
        How the reference was made (fit residuals, continuity checks, parts of a stack).

    Notes
    -----
    What each use needs: the servo-constraint inversion 3 continuous derivatives
    (jerk-level index reduction of 003 (35)); the funnel controller ``r_hat - 1``
    (plus ``k_i`` for the rows acting on eta2, 003 (42), (48)).
    """

    def __init__(self, t: ca.SX, expr: ca.SX, t0: float, tf: float, smoothness: int, name: str = "y_ref",
                 *, diagnostics: dict | None = None):
        self.t = t
        self.expr = ca.SX(expr)
        self.t0, self.tf = float(t0), float(tf)
        self.smoothness = int(smoothness)
        self.name = name
        self.diagnostics = dict(diagnostics or {})
        self._functions: dict[int, ca.Function] = {}

    def __getstate__(self) -> dict:  # compiled Functions are rebuilt on demand, not pickled
        return {**self.__dict__, "_functions": {}}

    @property
    def m(self) -> int:
        return self.expr.shape[0]

    def __repr__(self) -> str:
        return (f"Reference({self.name!r}, m={self.m}, [t0, tf] = [{self.t0:g}, {self.tf:g}], "
                f"C^{self.smoothness})")

    def require(self, order: int, where: str = "") -> None:
        """Raise unless the reference has ``order`` continuous derivatives."""
        if order > self.smoothness:
            parts = [p for p in self.diagnostics.get("parts", []) if p["smoothness"] < order]
            which = ("; too rough: " + ", ".join(f"{p['name']} (C^{p['smoothness']})" for p in parts)) if parts else ""
            raise ReferenceSignalError(
                f"{where or 'this use'} needs {self.name} with {order} continuous derivatives "
                f"(y_ref in W^{{{order},inf}}), but it is only C^{self.smoothness}{which}; "
                f"build it with smoothness >= {order} (rest_to_rest, waypoints, from_samples; "
                "poly9_timing_law is C^4)"
            )

    def function(self, order: int = 0) -> ca.Function:
        """``t -> (y, y', ..., y^(order))`` as one CasADi Function (outputs ``d0``..``d<order>``)."""
        order = int(order)
        fn = self._functions.get(order)
        if fn is None:
            outs = [self.expr]
            for _ in range(order):
                outs.append(ca.jacobian(outs[-1], self.t))
            # dense outputs: a constant component has structurally zero derivatives, and callers
            # substitute these values for dense symbols
            fn = ca.Function(f"{self.name}_d{order}", [self.t], [ca.densify(o) for o in outs], ["t"],
                             [f"d{k}" for k in range(order + 1)])
            self._functions[order] = fn
        return fn

    def __call__(self, t, order: int = 0) -> np.ndarray:
        """Evaluate the ``order``-th derivative at times ``t``: shape ``(m, len(t))``."""
        t = np.atleast_1d(np.asarray(t, float))
        fn = self.function(order).map(t.size)
        outs = fn(t[None, :])
        out = outs[-1] if isinstance(outs, (list, tuple)) else outs
        return np.array(out).reshape(self.m, t.size)

    @staticmethod
    def stack(refs: Sequence["Reference"], name: str = "y_ref") -> "Reference":
        """One reference from per-output references (each may be vector-valued).

        The result has all components in order, is constant outside
        ``[min t0, max tf]`` and is C^k with ``k`` the least smoothness of the parts.
        """
        refs = list(refs)
        if not refs:
            raise ReferenceSignalError("Reference.stack needs at least one reference")
        for i, r in enumerate(refs):
            if not isinstance(r, Reference):
                raise ReferenceSignalError(f"Reference.stack: item {i} is a {type(r).__name__}, not a Reference")
            stray = sorted({s.name() for s in ca.symvar(r.expr)} - {r.t.name()})
            if stray or r.expr.shape[1] != 1:
                raise ReferenceSignalError(f"Reference.stack: item {i} ({r.name}) must be a column expression "
                                           f"of its time symbol only; shape {r.expr.shape}, other symbols {stray}")
        t = ca.SX.sym("t")
        expr = ca.vertcat(*[ca.substitute(r.expr, r.t, t) for r in refs])
        parts = [{"name": r.name, "m": r.m, "smoothness": r.smoothness, "t0": r.t0, "tf": r.tf,
                  "diagnostics": r.diagnostics} for r in refs]
        return Reference(t, expr, min(r.t0 for r in refs), max(r.tf for r in refs),
                         min(r.smoothness for r in refs), name, diagnostics={"parts": parts})
