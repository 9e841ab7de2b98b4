"""Vector relative degree and high-gain matrix of the auxiliary ODE 003 (10).

The relative degree of each auxiliary output ``O_i`` is found from Lie
derivatives (CasADi AD): the smallest ``r_i`` with ``L_K L_F^(r_i-1) O_i``
not identically zero on the sample points of the operating region.  The
high-gain matrix Gamma (Sect. 1.3) stacks these rows; it must be invertible at
every sample point, and its conditioning is reported.

Special cases: position output with ``r_hat = 2`` (003 Sect. 2.2), where
``Gamma = [J; G; h'] M^-1 [J^T G^T B]`` and ``S`` is the Schur complement of
``A = [J; G] M^-1 [J; G]^T`` in Gamma, and the colocated case ``h' = B^T``
(Sect. 2.3), where Gamma and ``S`` are symmetric positive definite.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from ..errors import RelativeDegreeError
from .auxiliary import (
    as_points, auxiliary_system, cache_of, cached, eval_batch, region_samples, sampling_domain, uses_neighbourhood,
)

_ZERO_TOL = 1e-10
_SINGULAR_TOL = 1e-10


@dataclass(frozen=True)
class LieChain:
    """Symbolic Lie derivatives of the auxiliary outputs (cached per model).

    ``chains[i]`` is ``[O_i, L_F O_i, ..., L_F^(r_i - 1) O_i]`` and
    ``gamma_rows[i] = L_K L_F^(r_i - 1) O_i``.
    """

    r_aux: tuple
    chains: tuple
    gamma: ca.SX


@dataclass(frozen=True)
class RelativeDegree:
    """Vector relative degree of the auxiliary ODE (10) on a model's operating region.

    Attributes
    ----------
    r_aux : tuple of int
        Relative degree of every auxiliary output ``(O1, O2, O3)`` (p + l + m entries).
    r_hat : int or None
        Common relative degree of the outputs ``O3 = h`` (None if they differ).
    r_output : tuple of int
        Relative degrees of the m outputs.
    r_bar : int
        ``sum(r_aux)``; the internal dynamics have dimension ``2n - r_bar``.
    gamma : casadi.Function
        ``(q, v, theta) -> Gamma`` (high-gain matrix, (p+l+m) square).
    worst_condition : float
        Largest 2-norm condition number of Gamma over the sample points.
    worst_point : (ndarray, ndarray)
        ``(q, v)`` where it occurs.
    min_singular_value : float
        Smallest singular value of Gamma over the samples.
    det_range : (float, float)
        Smallest and largest ``det Gamma`` over the samples.
    samples : int
        Number of points checked.
    """

    r_aux: tuple
    r_hat: int | None
    r_output: tuple
    r_bar: int
    blocks: tuple
    gamma: ca.Function
    worst_condition: float
    worst_point: tuple
    min_singular_value: float
    min_singular_point: tuple
    det_range: tuple
    samples: int
    region: str = ""
    diagnostics: dict = field(default_factory=dict)

    def summary(self) -> str:
        p, l, m = self.blocks
        return (
            f"vector relative degree of (10): {list(self.r_aux)} (p={p}, l={l}, m={m}); "
            f"r_hat = {self.r_hat}, r_bar = {self.r_bar}\n"
            f"Gamma on {self.samples} points of {self.region or 'the sample box'}: "
            f"worst cond = {self.worst_condition:.4g}, min singular value = {self.min_singular_value:.4g}, "
            f"det in [{self.det_range[0]:.4g}, {self.det_range[1]:.4g}]"
        )

    def plot(self, ax=None):
        """Condition number of Gamma and det Gamma over the sample points (one figure)."""
        import matplotlib.pyplot as plt

        cond, dets = self.diagnostics.get("conditions"), self.diagnostics.get("dets")
        if ax is None:
            _, ax = plt.subplots(1, 2, figsize=(9, 3.2))
        ax[0].semilogy(np.sort(cond)[::-1], ".")
        ax[0].set(xlabel="sample (sorted)", ylabel="cond(Gamma)", title=f"r = {list(self.r_aux)}")
        ax[1].hist(dets, bins=30)
        ax[1].set(xlabel="det Gamma", ylabel="count", title=self.region or "samples")
        ax[0].figure.tight_layout()
        return ax

    def to_npz(self, path) -> None:
        """Save the numbers (not the CasADi Function) to ``path`` (.npz)."""
        np.savez(path, r_aux=np.array(self.r_aux), r_bar=self.r_bar, r_hat=-1 if self.r_hat is None else self.r_hat,
                 worst_condition=self.worst_condition, worst_q=self.worst_point[0], worst_v=self.worst_point[1],
                 min_singular_value=self.min_singular_value, det_range=np.array(self.det_range),
                 conditions=self.diagnostics.get("conditions", np.zeros(0)),
                 dets=self.diagnostics.get("dets", np.zeros(0)), sample_q=self.diagnostics.get("q", np.zeros(0)))

    def to_dict(self) -> dict:
        return {
            "r_aux": list(self.r_aux), "r_hat": self.r_hat, "r_output": list(self.r_output),
            "r_bar": self.r_bar, "worst_condition": self.worst_condition,
            "worst_point": {"q": self.worst_point[0], "v": self.worst_point[1]},
            "min_singular_value": self.min_singular_value, "det_range": list(self.det_range),
            "samples": self.samples,
        }


def _is_zero_on(model, expr_row: ca.SX, qs, vs, name: str) -> bool:
    """Is a (row) expression of (q, v, theta) zero at all sample points?"""
    if expr_row.nnz() == 0 or (expr_row.is_constant() and not np.any(np.array(ca.DM(expr_row)))):
        return True
    fn = ca.Function(name, [model.q, model.v, model.theta], [expr_row])
    vals = eval_batch(fn, qs, vs, theta=model.theta_values)[0]
    scale = max(1.0, float(np.max(np.abs(vals))) if vals.size else 1.0)
    return bool(np.max(np.abs(vals)) <= _ZERO_TOL * scale) if vals.size else True


def lie_chain(model, samples: int = 50, rng=0) -> LieChain:
    """Symbolic Lie derivatives up to the relative degree of every auxiliary output."""

    def build():
        aux = auxiliary_system(model)
        qs, vs = region_samples(model, samples, rng)
        max_order = 2 * model.n
        r_aux, chains, rows = [], [], []
        for i in range(aux.n_aux):
            expr = aux.O[i]
            chain = []
            for k in range(max_order + 1):
                chain.append(expr)
                row = aux.lie_K(expr)
                # exact structural zero first (position outputs), numeric zero at samples otherwise
                if not (ca.jacobian(expr, model.v).nnz() == 0 or _is_zero_on(model, row, qs, vs, f"LK_{i}_{k}")):
                    break
                expr = aux.lie_F(expr)
            else:
                raise RelativeDegreeError(
                    f"{model.name}: auxiliary output {i} ({_aux_name(model, i)}) is not influenced by the input "
                    f"up to derivative {max_order}: L_K L_F^k O_i = 0 for all k <= {max_order}; "
                    "the relative degree does not exist (check B and h)"
                )
            r_aux.append(k + 1)
            chains.append(tuple(chain))
            rows.append(row)
        return LieChain(tuple(r_aux), tuple(chains), ca.vertcat(*rows))

    return cached(model, ("lie_chain",), build)


def _aux_name(model, i: int) -> str:
    p, l = model.p, model.ell
    if i < p:
        return f"non-holonomic constraint {i + 1}"
    if i < p + l:
        return f"holonomic constraint g{i - p + 1}"
    return f"output {model.y_names[i - p - l]}"


def relative_degree(model, samples: int = 200, rng=0, *, points=None, radius=None,
                    v_radius=None) -> RelativeDegree:
    """Vector relative degree and high-gain matrix of (10), checked on the operating region.

    Parameters
    ----------
    model : Model
    samples : int
        Number of random points ``(q, v)`` at which Gamma is checked: drawn from ``model.region``,
        or, when the model declares no region and ``points`` are given, from the neighbourhood of
        the points (see ``radius``).
    rng : int or Generator
        Seed of the sampling.
    points : sequence, optional
        Points (``q`` or ``(q, v)``, e.g. :func:`~invctl.analysis.equilibrium.operating_points`
        along a reference) at which Gamma is checked too.  Without a declared region they define
        the analysed domain: the tube of half-width ``radius`` around the polyline through them.
    radius, v_radius : float or array, optional
        Half-widths of that tube in ``q`` and ``v`` (defaults 0.1 and 1.0, see
        :data:`~invctl.analysis.auxiliary.NEIGHBOURHOOD_RADIUS`).  Given with a declared region,
        the tube is intersected with the region.

    Raises
    ------
    RelativeDegreeError
        If Gamma is singular at a sample point (names the point and Gamma's smallest
        singular value), ``det Gamma`` changes sign on the (connected) sampled domain, or an
        output is never influenced by the input.
    """
    pts = as_points(model, points)
    key = ("relative_degree", tuple(model.theta_values), samples, repr(rng),
           None if points is None else repr([(q.tolist(), v.tolist()) for q, v in pts]),
           None if radius is None else repr(np.asarray(radius, float).tolist()),
           None if v_radius is None else repr(np.asarray(v_radius, float).tolist()))
    cache = cache_of(model)
    if key in cache:
        return cache[key]
    chain = lie_chain(model)
    p, l, m = model.p, model.ell, model.ny
    r_out = chain.r_aux[p + l:]
    r_hat = r_out[0] if r_out and all(r == r_out[0] for r in r_out) else None
    gamma = ca.Function("Gamma", [model.q, model.v, model.theta], [chain.gamma],
                        ["q", "v", "theta"], ["Gamma"])
    qs, vs = region_samples(model, samples, rng, pts, radius=radius, v_radius=v_radius)
    G = eval_batch(gamma, qs, vs, theta=model.theta_values)[0]
    sv = np.linalg.svd(G, compute_uv=False)
    smin, smax = sv[:, -1], sv[:, 0]
    with np.errstate(divide="ignore"):
        cond = np.where(smin > 0, smax / np.where(smin > 0, smin, 1), np.inf)
    dets = np.linalg.det(G)
    kmin = int(np.argmin(smin / np.maximum(smax, 1e-300)))
    kc = int(np.argmax(cond))
    local = uses_neighbourhood(model, pts, radius) and samples > 0
    region = sampling_domain(model, pts, radius, v_radius) if samples else "the given points"
    if local:
        restrict = "Analyse a smaller neighbourhood (radius) of the operating points or choose another output"
    elif model.region is not None:
        restrict = "Restrict the operating region (model.region) away from these points or choose another output"
    else:
        restrict = ("No region is declared, so a default box was sampled: declare model.region, or pass the "
                    "operating points (points=operating_points(model, reference)) to analyse their neighbourhood")
    result = RelativeDegree(
        r_aux=chain.r_aux, r_hat=r_hat, r_output=tuple(r_out), r_bar=int(sum(chain.r_aux)),
        blocks=(p, l, m), gamma=gamma, worst_condition=float(cond[kc]),
        worst_point=(qs[kc], vs[kc]), min_singular_value=float(smin.min()),
        min_singular_point=(qs[kmin], vs[kmin]), det_range=(float(dets.min()), float(dets.max())),
        samples=qs.shape[0], region=region,
        diagnostics={"conditions": cond, "dets": dets, "sigma_min": smin, "q": qs, "v": vs},
    )
    bad = ~np.isfinite(smin) | (smin <= _SINGULAR_TOL * np.maximum(smax, 1.0))
    if not np.any(bad) and dets.min() < 0 < dets.max():
        # det Gamma changes sign on the (connected) sampled domain: Gamma is singular in between
        i, j = int(np.argmin(dets)), int(np.argmax(dets))
        raise RelativeDegreeError(
            f"{model.name}: det Gamma changes sign on {region} (det = {dets[i]:.3g} at "
            f"q = {np.round(qs[i], 5).tolist()}, det = {dets[j]:.3g} at q = {np.round(qs[j], 5).tolist()}), so "
            f"Gamma is singular somewhere between them (the sampled domain is connected); the smallest singular value "
            f"found is {smin[kmin]:.3g} at q = {np.round(qs[kmin], 5).tolist()}. "
            + f"{restrict}.",
            partial=result,
            diagnostics={"q": qs[kmin], "v": vs[kmin], "sigma_min": float(smin[kmin]),
                         "det_negative_at": qs[i], "det_positive_at": qs[j]},
        )
    if np.any(bad):
        k = int(np.flatnonzero(bad)[0])
        raise RelativeDegreeError(
            f"{model.name}: the vector relative degree {list(chain.r_aux)} does not exist at "
            f"q = {np.round(qs[k], 6).tolist()}, v = {np.round(vs[k], 6).tolist()}: Gamma's smallest "
            f"singular value is {smin[k]:.3g} (largest {smax[k]:.3g}); {int(bad.sum())} of {qs.shape[0]} "
            f"sample points are singular. {restrict}.",
            partial=result,
            diagnostics={"q": qs[k], "v": vs[k], "sigma_min": float(smin[k]), "sigma_max": float(smax[k]),
                         "singular_points": int(bad.sum())},
        )
    cache[key] = result
    return result


# ------------------------------------------------------------ special cases
def is_position_output(model) -> bool:
    """True if ``h`` depends on ``q`` only (003 Sect. 2.2)."""
    return ca.jacobian(model.h, model.v).nnz() == 0


def position_output_gamma(model) -> ca.Function:
    """Closed form of Gamma for a position output with ``r_hat = 2`` (003 Sect. 2.2):
    ``[J; G; h'] M^-1 [J^T G^T B]`` as ``(q, theta) -> Gamma``."""
    aux = auxiliary_system(model)
    H = ca.jacobian(model.h, model.q)
    C = ca.vertcat(model.J, model.G, H)
    return ca.Function("Gamma_22", [model.q, model.theta], [ca.mtimes(C, aux.MinvBt)], ["q", "theta"], ["Gamma"])


def schur_complement(model) -> ca.Function:
    """``S`` of 003 (15): the Schur complement of ``A = Gamma_11`` in Gamma.

    ``S = Gamma_3b - Gamma_3a A^-1 Gamma_12`` where Gamma is partitioned into the
    constraint rows/multiplier columns and output rows/input columns; this is the
    input matrix of ``y^(r_hat) = b5 + S u`` (16).  Returns ``(q, v, theta) -> S``.
    """

    def build():
        chain = lie_chain(model)
        Gm = chain.gamma
        c = model.p + model.ell
        if c == 0:
            S = Gm
        else:
            A = Gm[:c, :c]
            S = Gm[c:, c:] - ca.mtimes(Gm[c:, :c], ca.solve(A, Gm[:c, c:]))
        return ca.Function("S", [model.q, model.v, model.theta], [S], ["q", "v", "theta"], ["S"])

    return cached(model, ("schur",), build)


@dataclass(frozen=True)
class ColocationReport:
    """Result of :func:`colocated_check` (003 Sect. 2.3)."""

    colocated: bool
    max_mismatch: float
    gamma_min_eig: float
    gamma_max_asym: float
    schur_min_eig: float
    samples: int


def colocated_check(model, samples: int = 100, rng=0) -> ColocationReport:
    """Check ``h' = B^T`` (17) and that Gamma and S are symmetric positive definite at samples."""
    H = ca.jacobian(model.h, model.q)
    mism = ca.Function("HB", [model.q, model.theta], [H - ca.SX(model.B).T])
    qs, vs = region_samples(model, samples, rng)
    th = model.theta_values
    mm = float(np.max(np.abs(eval_batch(mism, qs, theta=th)[0]))) if is_position_output(model) else np.inf
    rd = relative_degree(model, samples=0, points=[(q, v) for q, v in zip(qs, vs)])
    G = eval_batch(rd.gamma, qs, vs, theta=th)[0]
    S = eval_batch(schur_complement(model), qs, vs, theta=th)[0]
    asym = float(np.max(np.abs(G - G.transpose(0, 2, 1))))
    gmin = float(np.min(np.linalg.eigvalsh(0.5 * (G + G.transpose(0, 2, 1)))))
    smin = float(np.min(np.linalg.eigvalsh(0.5 * (S + S.transpose(0, 2, 1)))))
    return ColocationReport(bool(mm < 1e-12 * max(1.0, np.max(np.abs(th)))), mm, gmin, asym, smin, qs.shape[0])
