"""Model parameters from printed linearization data (least squares with identifiability report).

Papers often print what a model linearizes to (eigenvalues of the internal dynamics ``Q``, the split
``T^-1 Q T`` and ``T^-1 P`` of 003 (39), transmission zeros) but not the parameters behind it (003
Table 1 is missing).  :func:`identify` fits chosen parameters of a :class:`~invctl.model.Model` to such
numbers and says how far the numbers determine them:

* **residual** of every target entry in units of its *resolution* (half a unit of the last printed
  digit for printed numbers): ``max |r| <= 1`` means the fitted model reproduces the printed digits;
* **confidence**: the Jacobian of the residuals with respect to ``log(theta)`` (central differences),
  its singular values, rank and condition number, and per parameter the largest relative change the
  printed rounding allows (linearized: ``sum_i |(J^+)_ji|``, the box ``|r_i| <= 1``) and the standard
  deviation under uniform rounding errors;
* **non-uniqueness**: directions of ``log(theta)`` the targets cannot see (singular values below
  ``rank_tol``), parameters whose column vanishes (the targets do not depend on them), and distinct
  minima found from several starts.

``T`` is the matrix of eigenvectors of ``Q`` (columns, eigenvalues ascending) so that ``T^-1 Q T`` is
diagonal (003 Sect. 6 writes ``T^-1 Q T``; :mod:`invctl.analysis.linearize` stores its inverse).  Its
columns are only defined up to scale, so ``T^-1 P`` needs a stated normalization
(:func:`invctl.analysis.linearize.eigenvector_columns`); 003's printed ``T^-1 P`` is reproduced with
unit-length columns whose last entry is negative (``"unit-last-negative"``), not with the printed
``T = [mu2/c mu1/c; 1 1]`` (``"last-one"``): see docs/reproduction.md.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Mapping, Sequence

import numpy as np

from ..errors import InvctlError, ParameterError
from .linearize import EIG_NORMALIZATIONS, eigenvector_columns

#: the features :func:`linearization_features` computes
FEATURES = ("eigenvalues", "TinvQT", "TinvP", "Q", "P", "zeros")
_PENALTY_FACTOR = 10.0  # residual where the model cannot be evaluated: this times the largest one seen


# ----------------------------------------------------------------------------- features
def eigen_split(Q, P, normalization: str = "unit-last-negative"):
    """``(eigenvalues, T^-1 Q T, T^-1 P, T)`` with ``T`` the real eigenvector columns of ``Q``
    (eigenvalues ascending), normalized by ``normalization``.

    Raises
    ------
    ParameterError
        Complex eigenvalues (no real diagonalizing ``T``) or a defective ``Q``.
    """
    Q, P = np.atleast_2d(np.asarray(Q, float)), np.atleast_2d(np.asarray(P, float))
    w, V = np.linalg.eig(Q)
    if np.any(np.abs(w.imag) > 1e-12 * max(1.0, np.abs(w).max())):
        raise ParameterError(f"eigen_split: Q has complex eigenvalues {w}; T^-1 Q T is not real diagonal")
    order = np.argsort(w.real)
    V = eigenvector_columns(np.real(V[:, order]), normalization)
    if np.linalg.cond(V) > 1e12:
        raise ParameterError("eigen_split: Q is (nearly) defective; its eigenvectors do not form a basis")
    Vi = np.linalg.inv(V)
    return w.real[order], Vi @ Q @ V, Vi @ P, V


def linearization_features(lin, normalization: str = "unit-last-negative") -> dict:
    """``eigenvalues``, ``TinvQT``, ``TinvP`` (:func:`eigen_split`), ``Q`` and ``P`` of a
    :class:`~invctl.analysis.linearize.LinearizedInternal` (003 (38), (39))."""
    ev, TQT, TP, _ = eigen_split(lin.Q, lin.P, normalization)
    return {"eigenvalues": ev, "TinvQT": TQT, "TinvP": TP, "Q": np.asarray(lin.Q), "P": np.asarray(lin.P)}


def linearization_evaluator(linearize: Callable, normalization: str = "unit-last-negative",
                            zeros: Callable | None = None) -> Callable:
    """``model -> features``: :func:`linearization_features` of ``linearize(model)`` and, with
    ``zeros(model) -> array``, the ``zeros`` (e.g. ``classify_zeros(model, q0).transmission``), sorted
    by real part."""
    if normalization not in EIG_NORMALIZATIONS:
        raise ParameterError(f"normalization must be one of {EIG_NORMALIZATIONS}, got {normalization!r}")

    def evaluate(model):
        out = linearization_features(linearize(model), normalization)
        if zeros is not None:
            z = np.asarray(zeros(model))
            out["zeros"] = np.sort_complex(z).real if np.all(np.abs(np.imag(z)) == 0) else np.sort_complex(z)
        return out

    return evaluate


# ----------------------------------------------------------------------------- targets
@dataclass(frozen=True)
class Target:
    """One target array: ``value`` of feature ``name`` known to ``resolution`` (same shape or scalar).

    ``resolution`` is the error the number may carry: half a unit of its last printed digit for a
    printed number (:func:`printed`), or a tolerance for computed data.  ``NaN`` entries of ``value``
    are not fitted (unknown entries)."""

    name: str
    value: np.ndarray
    resolution: np.ndarray

    def __post_init__(self):
        v = np.asarray(self.value, float)
        r = np.broadcast_to(np.asarray(self.resolution, float), v.shape).copy()
        if not np.all(r > 0):
            raise ParameterError(f"target {self.name!r}: resolution must be > 0, got {self.resolution!r}")
        object.__setattr__(self, "value", v)
        object.__setattr__(self, "resolution", r)

    @property
    def mask(self) -> np.ndarray:
        return np.isfinite(self.value)


def printed(name: str, value, decimals: int) -> Target:
    """A printed number with ``decimals`` decimals: resolution ``0.5 * 10**-decimals``."""
    if int(decimals) != decimals or decimals < 0:
        raise ParameterError(f"printed({name!r}): decimals must be a non-negative integer, got {decimals!r}")
    return Target(name, value, np.asarray(0.5 * 10.0 ** (-int(decimals))))


# ----------------------------------------------------------------------------- result
@dataclass
class Identification:
    """Result of :func:`identify` (see the module docstring for the meaning of each entry).

    Attributes
    ----------
    values : dict
        Fitted parameters (name -> value).
    start : dict
        The start of the best fit.
    residuals : dict
        Per target ``(value(theta) - target) / resolution`` (arrays; NaN where not fitted).
    max_residual : float
        Largest ``|residual|``; ``<= 1`` means within the targets' resolution (the printed digits).
    features : dict
        The fitted model's features (all that the evaluator returned).
    jacobian : ndarray
        ``d residuals / d log(theta)`` at the fit (rows: fitted target entries).
    singular_values : ndarray
        Of ``jacobian``; ``rank`` counts those above ``rank_tol`` times the largest.
    bound : dict
        Largest relative change of each parameter that keeps every residual change within one
        resolution (linearized; ``inf`` for unidentifiable parameters).
    std : dict
        Relative standard deviation under independent errors uniform within the resolution.
    null_directions : list of dict
        Unit directions in ``log(theta)`` (name -> coefficient) with singular value below
        ``rank_tol`` times the largest: parameter combinations the targets do not determine.
    insensitive : tuple
        Parameters with a vanishing Jacobian column.
    alternatives : list of dict
        Other minima from the multistart with residual within ``accept`` (values, max_residual).
    """

    names: tuple
    values: dict
    start: dict
    residuals: dict
    max_residual: float
    features: dict
    jacobian: np.ndarray
    singular_values: np.ndarray
    rank: int
    condition: float
    bound: dict
    std: dict
    null_directions: list
    insensitive: tuple
    alternatives: list
    success: bool
    message: str
    nfev: int
    diagnostics: dict = field(default_factory=dict)

    @property
    def within_resolution(self) -> bool:
        """Every fitted target entry is reproduced within its resolution (``max_residual <= 1``)."""
        return bool(self.max_residual <= 1.0)

    @property
    def unique(self) -> bool:
        """Full rank and no distinct alternative minimum."""
        return self.rank == len(self.names) and not self.alternatives

    def describe(self) -> str:
        lines = [f"identification of {', '.join(self.names)} ({'converged' if self.success else 'NOT converged'}: "
                 f"{self.message}; {self.nfev} evaluations)"]
        for k in self.names:
            b = self.bound[k]
            lines.append(f"  {k} = {self.values[k]:.10g}  (relative change allowed by the resolution "
                         f"{b:.2g}, std {self.std[k]:.2g})" if math.isfinite(b) else
                         f"  {k} = {self.values[k]:.10g}  (not determined by the targets)")
        lines.append(f"  max |residual| = {self.max_residual:.3g} resolutions "
                     f"({'within' if self.within_resolution else 'OUTSIDE'} the targets' resolution)")
        lines.append(f"  Jacobian d r / d log(theta): singular values "
                     f"{', '.join(f'{s:.3g}' for s in self.singular_values)}; rank {self.rank} of "
                     f"{len(self.names)}, condition {self.condition:.3g}")
        if self.insensitive:
            lines.append(f"  the targets do not depend on: {', '.join(self.insensitive)}")
        for d in self.null_directions:
            lines.append("  undetermined combination: " + " + ".join(f"{c:+.3g} log {k}" for k, c in d.items()))
        for a in self.alternatives:
            lines.append("  another minimum: " + ", ".join(f"{k} = {v:.6g}" for k, v in a["values"].items())
                         + f" (max |residual| {a['max_residual']:.3g})")
        if self.unique:
            lines.append("  unique: full rank, no other minimum from the starts tried")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {"names": list(self.names), "values": self.values, "start": self.start,
                "residuals": {k: v.tolist() for k, v in self.residuals.items()}, "max_residual": self.max_residual,
                "within_resolution": self.within_resolution, "singular_values": self.singular_values.tolist(),
                "rank": self.rank, "condition": self.condition, "bound": self.bound, "std": self.std,
                "null_directions": self.null_directions, "insensitive": list(self.insensitive),
                "alternatives": self.alternatives, "unique": self.unique, "success": self.success,
                "message": self.message, "nfev": self.nfev}


# ----------------------------------------------------------------------------- the fit
def _residual_fn(model, names, targets, evaluate, log):
    sizes = [int(t.mask.sum()) for t in targets]
    n_res = sum(sizes)

    def values_of(x):
        return {k: (math.exp(xi) if lg else xi) for k, xi, lg in zip(names, x, log)}

    def features(x):
        try:
            return evaluate(model.with_params(**values_of(x)))
        except (InvctlError, np.linalg.LinAlgError, RuntimeError, ValueError, OverflowError):
            return None

    worst = [1.0]

    def residual(x, feats=None):
        f = features(x) if feats is None else feats
        if f is None:  # above every residual seen, so a step into this region is rejected
            return np.full(n_res, _PENALTY_FACTOR * worst[0])
        out = []
        for t in targets:
            if t.name not in f:
                raise ParameterError(f"identify: the evaluator returned no feature {t.name!r} "
                                     f"(it returned {sorted(f)})")
            v = np.asarray(f[t.name])
            v = v.real if np.iscomplexobj(v) and np.all(v.imag == 0) else v
            if np.shape(v) != t.value.shape:
                raise ParameterError(f"identify: feature {t.name!r} has shape {np.shape(v)}, the target "
                                     f"{t.value.shape}")
            out.append(((np.asarray(v, float) - t.value) / t.resolution)[t.mask])
        r = np.concatenate(out) if out else np.zeros(0)
        if r.size and np.all(np.isfinite(r)):
            worst[0] = max(worst[0], float(np.max(np.abs(r))))
        return r

    return residual, features, values_of


def identify(model, free: Sequence[str], targets: Sequence[Target], evaluate: Callable, *,
             start: Mapping[str, float] | None = None, bounds: Mapping[str, tuple] | None = None,
             n_starts: int = 6, rng=0, log: bool | Mapping[str, bool] = True, rank_tol: float = 1e-8,
             accept: float = 1.0, xtol: float = 1e-15, max_nfev: int = 2000) -> Identification:
    """Fit the parameters ``free`` of ``model`` so that ``evaluate(model)`` matches ``targets``.

    Parameters
    ----------
    model : Model
        Every parameter not in ``free`` keeps its value (e.g. lengths fixed by a printed geometry).
    free : sequence of str
        Parameter names to fit.
    targets : sequence of Target
        What ``evaluate`` must reproduce (:func:`printed` for printed numbers).
    evaluate : callable
        ``evaluate(model) -> {feature name: array}`` (e.g. :func:`linearization_evaluator`).
    start : dict, optional
        First start (default: the model's values); ``n_starts`` more are drawn log-uniformly in
        ``bounds`` (default: a factor 10 around the first start) to detect other minima.
    bounds : dict, optional
        ``name -> (low, high)`` for the random starts and the fit.
    log : bool or dict
        Fit ``log(theta)`` (default; keeps positive parameters positive and makes the confidence
        relative); a dict sets it per parameter.  Parameters that are not positive are fitted linearly.
    rank_tol : float
        Singular values below ``rank_tol`` times the largest count as zero (null directions).
    accept : float
        Minima with ``max |residual| <= max(accept, 2 * best)`` count as alternatives when their
        parameters differ from the best by more than 1e-3 (relative).

    Returns
    -------
    Identification

    Raises
    ------
    ParameterError
        Unknown or repeated parameter names, no targets, a start or bound outside the domain, or an
        evaluator that fails at the first start or returns features of the wrong shape.  (Fewer target
        entries than parameters is allowed: the result reports the undetermined directions.)
    """
    from scipy.optimize import least_squares

    names = tuple(free)
    if not names or len(set(names)) != len(names):
        raise ParameterError(f"identify: give distinct parameter names to fit, got {list(free)}")
    unknown = sorted(set(names) - set(model.values))
    if unknown:
        raise ParameterError(f"identify: unknown parameter(s) {unknown}; the model has {sorted(model.values)}")
    targets = tuple(targets)
    if not targets or not all(isinstance(t, Target) for t in targets):
        raise ParameterError("identify: give at least one Target (invctl.analysis.identify.Target/printed)")
    m = sum(int(t.mask.sum()) for t in targets)
    if m == 0:
        raise ParameterError("identify: every target entry is NaN (unknown); nothing to fit")
    start = {k: float((start or {}).get(k, model.values[k])) for k in names}
    logs = [bool(log.get(k, True) if isinstance(log, Mapping) else log) and start[k] > 0 for k in names]
    bounds = dict(bounds or {})
    for k, (lo, hi) in bounds.items():
        if k not in names or not lo < hi or (logs[names.index(k)] and lo <= 0):
            raise ParameterError(f"identify: bound {k}: ({lo}, {hi}) must name a fitted parameter with low < high "
                                 "(and low > 0 for a parameter fitted in log)")
    tr = [(math.log if lg else (lambda v: v)) for lg in logs]
    lo = np.array([tr[i](bounds[k][0]) if k in bounds else -np.inf for i, k in enumerate(names)])
    hi = np.array([tr[i](bounds[k][1]) if k in bounds else np.inf for i, k in enumerate(names)])
    residual, features, values_of = _residual_fn(model, names, targets, evaluate, logs)
    x0 = np.array([tr[i](start[k]) for i, k in enumerate(names)])
    if np.any(x0 < lo) or np.any(x0 > hi):
        raise ParameterError(f"identify: the start {start} lies outside the bounds {bounds}")
    f0 = features(x0)
    if f0 is None:
        try:
            evaluate(model.with_params(**start))
        except InvctlError as exc:
            raise ParameterError(f"identify: the model cannot be evaluated at the start {start}: {exc}") from exc
    residual(x0, f0)  # shape and name checks with a clear message
    gen = np.random.default_rng(rng)
    starts = [x0]
    for _ in range(int(n_starts)):
        a = np.where(np.isfinite(lo), lo, x0 - np.where(logs, math.log(10.0), np.maximum(np.abs(x0), 1.0)))
        b = np.where(np.isfinite(hi), hi, x0 + np.where(logs, math.log(10.0), np.maximum(np.abs(x0), 1.0)))
        starts.append(a + (b - a) * gen.random(len(names)))
    method = "trf" if (np.isfinite(lo).any() or np.isfinite(hi).any() or m < len(names)) else "lm"
    fits = []
    for xs in starts:
        try:
            sol = least_squares(residual, xs, method=method, bounds=(lo, hi) if method == "trf" else (-np.inf, np.inf),
                                x_scale=1.0, xtol=xtol, ftol=xtol, gtol=xtol, max_nfev=max_nfev)
        except (ValueError, np.linalg.LinAlgError):
            continue
        fits.append((float(np.max(np.abs(sol.fun))) if sol.fun.size else 0.0, sol, xs))
    if not fits:
        raise ParameterError("identify: no start led to a fit (every evaluation failed)")
    fits.sort(key=lambda f: f[0])
    best_r, sol, xs = fits[0]
    x = sol.x
    # confidence: central differences of the residuals in the fitted coordinates
    h = 1e-5
    J = np.empty((m, len(names)))
    for j in range(len(names)):
        e = np.zeros(len(names))
        e[j] = h * (1.0 if logs[j] else max(1.0, abs(x[j])))
        J[:, j] = (residual(x + e) - residual(x - e)) / (2 * e[j])
    sv = np.linalg.svd(J, compute_uv=False)
    smax = float(sv[0]) if sv.size and sv[0] > 0 else 0.0
    rank = int(np.sum(sv > rank_tol * smax)) if smax else 0
    cond = float(sv[0] / sv[-1]) if sv.size and sv[-1] > 0 else math.inf
    colnorm = np.linalg.norm(J, axis=0)
    insensitive = tuple(k for k, c in zip(names, colnorm) if c <= rank_tol * max(smax, 1e-300))
    _, _, Vt = np.linalg.svd(J)
    null = [{k: float(c) for k, c in zip(names, Vt[i]) if abs(c) > 1e-6} for i in range(rank, len(names))]
    bound, std = {}, {}
    if rank == len(names):
        Jp = np.linalg.pinv(J)
        for j, k in enumerate(names):
            scale = 1.0 if logs[j] else 1.0 / max(abs(values_of(x)[k]), 1e-300)
            bound[k] = float(np.sum(np.abs(Jp[j])) * scale)
            std[k] = float(np.sqrt(np.sum(Jp[j] ** 2) / 3.0) * scale)
    else:
        bound = {k: math.inf for k in names}
        std = {k: math.inf for k in names}
    best_vals = values_of(x)
    alternatives: list = []
    for r, s2, _ in fits[1:]:
        if r > max(accept, 2.0 * best_r):
            continue
        vals = values_of(s2.x)
        if all(abs(vals[k] - best_vals[k]) <= 1e-3 * max(abs(best_vals[k]), 1e-12) for k in names):
            continue
        if any(all(abs(vals[k] - a["values"][k]) <= 1e-3 * max(abs(a["values"][k]), 1e-12) for k in names)
               for a in alternatives):
            continue
        alternatives.append({"values": vals, "max_residual": r})
    feats = features(x) or {}
    res = {}
    for t in targets:
        full = np.full(t.value.shape, np.nan)
        if t.name in feats:
            full[t.mask] = ((np.asarray(np.real(feats[t.name]), float) - t.value) / t.resolution)[t.mask]
        res[t.name] = full
    return Identification(
        names=names, values=best_vals, start=values_of(xs), residuals=res, max_residual=best_r, features=feats,
        jacobian=J, singular_values=sv, rank=rank, condition=cond, bound=bound, std=std, null_directions=null,
        insensitive=insensitive, alternatives=alternatives, success=bool(sol.success), message=str(sol.message),
        nfev=int(sum(f[1].nfev for f in fits)),
        diagnostics={"starts": len(starts), "fits": [{"max_residual": r, "values": values_of(s.x)} for r, s, _ in fits],
                     "method": method, "log": dict(zip(names, logs))},
    )
