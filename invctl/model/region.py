"""Operating regions: where a model's analysis is claimed to hold."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from ..errors import ModelError


@dataclass(frozen=True)
class OperatingRegion:
    """A box in ``q`` (optionally in ``v``) with extra strict inequalities ``c(q) > 0``.

    Parameters
    ----------
    q_lower, q_upper : sequence of float
        Bounds on ``q`` (open box); use ``-inf``/``inf`` for free coordinates.
    constraints : sequence of callables ``c(q) -> float``
        Extra conditions ``c(q) > 0`` (e.g. ``cos(gamma) - 2/3``).
    sample_bounds : (lower, upper), optional
        Finite box used for sampling where ``q_lower``/``q_upper`` are infinite.
    v_scale : float
        Velocities are sampled uniformly in ``[-v_scale, v_scale]``.
    description : str
        Human-readable statement of the region (shown in reports).
    """

    q_lower: Sequence[float]
    q_upper: Sequence[float]
    constraints: Sequence[Callable[[np.ndarray], float]] = field(default_factory=tuple)
    sample_bounds: tuple[Sequence[float], Sequence[float]] | None = None
    v_scale: float = 1.0
    description: str = ""

    def contains(self, q: np.ndarray) -> bool:
        q = np.asarray(q, float).ravel()
        lo, hi = np.asarray(self.q_lower, float), np.asarray(self.q_upper, float)
        if q.shape != lo.shape:
            raise ModelError(f"region expects q of length {lo.size}, got {q.size}")
        if np.any(q <= lo) or np.any(q >= hi):
            return False
        return all(c(q) > 0 for c in self.constraints)

    def inside(self, Q: np.ndarray) -> np.ndarray:
        """:meth:`contains` for the rows of ``Q``: the box test on all rows at once, the constraints (scalar
        callables) only on the rows inside the box."""
        lo, hi = np.asarray(self.q_lower, float), np.asarray(self.q_upper, float)
        ok = np.all((Q > lo) & (Q < hi), axis=1)
        if self.constraints:
            for k in np.flatnonzero(ok):
                ok[k] = all(c(Q[k]) > 0 for c in self.constraints)
        return ok

    def sample(self, count: int, rng: np.random.Generator | int | None = 0, *, max_tries: int = 100):
        """Sample ``count`` points ``(q, v)`` of the region by rejection."""
        rng = np.random.default_rng(rng)
        lo = np.asarray(self.q_lower, float)
        hi = np.asarray(self.q_upper, float)
        if self.sample_bounds is not None:
            slo, shi = (np.asarray(b, float) for b in self.sample_bounds)
            lo, hi = np.maximum(lo, slo), np.minimum(hi, shi)
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise ModelError("region has infinite bounds: give sample_bounds to sample it")
        qs: list[np.ndarray] = []
        got = 0
        for _ in range(max_tries):
            cand = rng.uniform(lo, hi, size=(4 * count, lo.size))
            acc = cand[self.inside(cand)]
            qs.append(acc)
            got += acc.shape[0]
            if got >= count:
                break
        if got < count:
            raise ModelError(f"could not sample {count} points of region {self.description!r}")
        q = np.concatenate(qs)[:count]
        v = rng.uniform(-self.v_scale, self.v_scale, size=q.shape)
        return q, v
