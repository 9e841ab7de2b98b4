"""Reference signals as CasADi expressions of time, with exact derivatives by AD."""
from __future__ import annotations

from functools import lru_cache

import casadi as ca
import numpy as np

from ..errors import ReferenceSignalError


def poly9_timing_law(t: ca.SX, t0: float, tf: float) -> ca.SX:
    """The timing law of 003 Sect. 6: ``r = 70 s^9 - 315 s^8 + 540 s^7 - 420 s^6 + 126 s^5``,
    ``s = (t - t0)/(tf - t0)`` clipped to [0, 1].

    ``r`` rises from 0 to 1 with derivatives 1..4 vanishing at both ends, so the
    glued signal is C^4 (and in W^{5,inf}).
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
    """

    def __init__(self, t: ca.SX, expr: ca.SX, t0: float, tf: float, smoothness: int, name: str = "y_ref"):
        self.t = t
        self.expr = ca.SX(expr)
        self.t0, self.tf = float(t0), float(tf)
        self.smoothness = int(smoothness)
        self.name = name

    @property
    def m(self) -> int:
        return self.expr.shape[0]

    def require(self, order: int, where: str = "") -> None:
        """Raise unless the reference has ``order`` continuous derivatives."""
        if order > self.smoothness:
            raise ReferenceSignalError(
                f"{where or 'this use'} needs {self.name} with {order} continuous derivatives "
                f"(y_ref in W^{{{order},inf}}), but it is only C^{self.smoothness}; "
                "use a smoother timing law (e.g. poly9_timing_law, C^4)"
            )

    @lru_cache(maxsize=None)
    def function(self, order: int = 0) -> ca.Function:
        """``t -> (y, y', ..., y^(order))`` as one CasADi Function (outputs ``d0``..``d<order>``)."""
        outs = [self.expr]
        for _ in range(order):
            outs.append(ca.jacobian(outs[-1], self.t))
        return ca.Function(f"{self.name}_d{order}", [self.t], outs, ["t"], [f"d{k}" for k in range(order + 1)])

    def __call__(self, t, order: int = 0) -> np.ndarray:
        """Evaluate the ``order``-th derivative at times ``t``: shape ``(m, len(t))``."""
        t = np.atleast_1d(np.asarray(t, float))
        fn = self.function(order).map(t.size)
        outs = fn(t[None, :])
        out = outs[-1] if isinstance(outs, (list, tuple)) else outs
        return np.array(out).reshape(self.m, t.size)
