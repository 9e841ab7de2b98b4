"""Automatic feedback design for the funnel controller (48) of 003 Sect. 5.

:func:`design_funnel_feedback` chooses every parameter of :class:`NMPFunnelController` from the model,
the linearized internal dynamics (39) and the reference (constants: :class:`DesignRules`):

* **the new output (41)**: ``K``, ``k_i``, ``rho`` and the output/input pairing by
  :func:`~invctl.control.new_output.design_new_output` (identity construction where the colocated remark
  after (A2) applies, else the high-gain construction refined over the design points);
* **time scale** ``T = tf - t0`` of the reference (:func:`reference_time_scale`);
* **gains** ``kappa_i,j = 5/T`` (time constants T/5) and ``kappa_bar = max(20/(T lambda_0), ||u_s|| / s)``:
  the last level closes at ``~20/T`` (``lambda_0 = lambda_min(sym(rho D S~(w0) E))``), and is stiff enough to
  carry the holding input ``u_s`` (the static load at the start and end of the reference, e.g. gravity) at
  the expected error with nominal gains (``s = ||(prod_j kappa_i,j |G0_i| eps)_i||``);
* **funnels** ``phi = (p e^(-q t) + r)^-1``, ``q = 3/T``.  Final widths: level 0 is 3 times the quasi-static
  image of the expected error ``eps``, ``|e_i,0| ~ |G0_i| eps`` with ``G0_i = -K_i Q~^-1 P~`` (eta2 rows: the
  equilibrium ``eta2 = -Q~^-1 P~ y`` of (40)) or ``K_i``; level ``j + 1`` is ``2 kappa_i,j`` times level j
  (an error varying at the rate kappa: ``|e' + k e| ~ 2 kappa |e|``); ``phi_bar`` takes the 2-norm over
  the rows.  Initial widths ``p + r`` are 10 times the final ones (room for the transient; ``e^-3`` of it
  is left at ``t = T``) and at least twice the error levels ``e_i,j(0)`` of the plant's start state,
  evaluated with the controller's own error functions and iterated (the gains ``k_i,j`` depend on the
  funnels) until every ratio ``phi_i,j(0) |e_i,j(0)|`` is at most 1/2.  Every funnel is exponential,
  hence in every class ``Phi_k`` of (9).
* **levels** ``"per-output"`` (invctl's extension, the default): each output gets its own funnels as above;
  ``"shared"`` (the rule of 003 Sect. 6: ``phi_i,j = phi_j``, ``kappa_i,j = kappa_j``): one funnel and one gain
  per level j for all outputs that have it, the widest of the per-output widths at level 0 (final and
  initial), level ``j + 1`` ``level_factor kappa_j`` times level j, and ``phi = phi_(max r - 1)`` for ``e_bar``
  (003: ``phi = phi_2``); the initial widths are the largest over the outputs.

Any entry passed in ``overrides`` is used as is.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np

from ..analysis import relative_degree
from ..analysis.internal import design_point
from ..errors import FeedbackDesignError, ParameterError
from .funnel import Funnel
from .funnel_nmp import NMPFunnelController, _nested, _number_leaf
from .new_output import NewOutput, _S_batch, design_new_output

OVERRIDABLE = ("K", "k_i", "rho", "pairing", "funnels", "kappa", "kappa_bar", "phi_bar")
#: how the funnels and gains of the levels are chosen: "per-output" (invctl's extension) or "shared" (003 Sect. 6)
LEVEL_RULES = ("per-output", "shared")
#: max of the derivative of the C^4 timing law of 003 Sect. 6 over [0, 1] (630/256)
POLY9_PEAK_RATE = 630.0 / 256.0


@dataclass(frozen=True)
class DesignRules:
    """The constants of the design rules (see the module docstring); all dimensionless."""

    expected_fraction: float = 0.02   # default expected error: this fraction of the largest output excursion
    final_factor: float = 3.0         # final width of level 0 / quasi-static image of the expected error
    level_factor: float = 2.0         # width of level j+1 = level_factor * kappa_i,j * width of level j
    transient_factor: float = 10.0    # initial width / final width (at least)
    start_ratio: float = 0.5          # phi(0) |e(0)| at most this
    decay: float = 3.0                # q = decay / T
    kappa_rate: float = 5.0           # kappa_i,j = kappa_rate / T
    kappa_bar_rate: float = 20.0      # kappa_bar = kappa_bar_rate / (T lambda_0)
    refine: bool = True               # Nelder-Mead refinement of the high-gain construction

    def __post_init__(self):
        for name in ("expected_fraction", "final_factor", "level_factor", "transient_factor", "decay",
                     "kappa_rate", "kappa_bar_rate"):
            if not getattr(self, name) > 0:
                raise ParameterError(f"DesignRules.{name} must be > 0, got {getattr(self, name)}")
        if not 0 < self.start_ratio < 1:
            raise ParameterError(f"DesignRules.start_ratio must lie in (0, 1), got {self.start_ratio}")


# ----------------------------------------------------------------------------- time scale, points
def reference_time_scale(reference, t_end: float = 2.0, samples: int = 401, *, need: bool = True) -> tuple:
    """``(T, excursion, peak_rate)`` of a reference.

    ``T = tf - t0`` (the transition); without a finite transition, from the derivative magnitudes on
    ``[0, t_end]``: ``T = (630/256) min_l excursion_l / max|y_l'|`` (for the C^4 timing law of 003
    Sect. 6 this is exactly ``tf - t0``); ``excursion_l = max_t |y_l(t) - y_l(t0)|``."""
    t0, tf = float(reference.t0), float(reference.tf)
    finite = np.isfinite(tf) and tf > t0
    ts = np.linspace(t0, tf, samples) if finite else np.linspace(0.0, float(t_end), samples)
    y, dy = reference(ts), reference(ts, 1)
    exc = np.max(np.abs(y - y[:, :1]), axis=1)
    rate = np.max(np.abs(dy), axis=1)
    moving = (exc > 0) & (rate > 0)
    Td = float(np.min(POLY9_PEAK_RATE * exc[moving] / rate[moving])) if moving.any() else np.inf
    T = tf - t0 if finite else Td
    if need and (not np.isfinite(T) or T <= 0):
        raise ParameterError(f"{reference.name}: no time scale (the reference does not move on "
                             f"[{ts[0]:g}, {ts[-1]:g}]); give time_scale= (seconds)")
    return T, exc, rate


def _quasi_static_points(lin, reference, count=21):
    """Configurations ``(q, v)`` on the reference: ``Phi^-1(0, y_ref(t), y_ref'(t), .., eta)`` with eta the
    mean of the linearization points' internal states (Newton failures are skipped)."""
    internal = getattr(lin, "internal", None)
    if internal is None or not lin.points:
        return []
    eta = np.mean([np.asarray(pt[1], float).ravel() for pt in lin.points], axis=0)
    t0, tf = reference.t0, reference.tf
    ts = np.linspace(t0, tf, count) if np.isfinite(tf) and tf > t0 else np.array([t0])
    ys = [reference(ts, j) for j in range(internal.r_hat)]
    th = lin.model.theta_values
    N = ts.size
    try:
        q, v = internal.state.map(N)(*ys, np.tile(eta[:, None], (1, N)), np.tile(th[:, None], (1, N)))
        return list(zip(np.array(q).T, np.array(v).T))
    except RuntimeError:        # Newton failed somewhere on the path: keep the points where it converges
        out = []
        for i in range(N):
            try:
                q, v = internal.state(*[y[:, i] for y in ys], eta, th)
            except RuntimeError:
                continue
            out.append((np.array(q).ravel(), np.array(v).ravel()))
        return out


def _holding_input(model, reference, q_guess):
    """Largest ``||u||`` that holds the plant at rest with ``y = y_ref(t0)`` or ``y_ref(tf)``: Newton on
    ``f(q, 0) + G^T lam + B u = 0, g(q) = 0, h(q) = y`` (the static load pure feedback must carry).
    ``None`` if the model has non-holonomic constraints or Newton fails."""
    if model.p or not np.isfinite(reference.tf):
        return None
    th = ca.DM(model.theta_values)
    lam, u, y = ca.SX.sym("lam", model.ell), ca.SX.sym("u", model.m), ca.SX.sym("y", model.m)
    sub = lambda e: ca.substitute(ca.substitute(e, model.v, ca.SX.zeros(model.n)), model.theta, th)  # noqa: E731
    res = ca.vertcat(sub(model.f) + ca.mtimes(sub(model.G).T, lam) + ca.mtimes(sub(model.B), u), sub(model.g),
                     sub(model.h) - y)
    x = ca.vertcat(model.q, lam, u)
    try:
        rf = ca.rootfinder("holding", "newton", ca.Function("r", [x, y], [res]),
                           {"abstol": 1e-10, "max_iter": 50, "error_on_fail": True})
        x0 = np.concatenate([np.asarray(q_guess, float).ravel(), np.zeros(model.ell + model.m)])
        us = [np.array(rf(x0, reference(t).ravel()))[-model.m:].ravel() for t in (reference.t0, reference.tf)]
    except RuntimeError:
        return None
    return float(max(np.linalg.norm(v) for v in us))


def _as_points(points, n):
    if points is None:
        return []
    if isinstance(points, tuple) and len(points) == 2 and np.ndim(points[0]) == 2:
        q, v = (np.asarray(a, float) for a in points)
        if q.shape[0] != n or v.shape != q.shape:
            raise ParameterError(f"design_points=(q, v) needs two arrays of shape (n = {n}, N), got "
                                 f"{q.shape} and {v.shape}")
        return list(zip(q.T, v.T))
    out = []
    for pt in points:
        q, v = (pt if isinstance(pt, tuple) and len(pt) == 2 else (pt, np.zeros(n)))
        q, v = np.asarray(q, float).ravel(), np.asarray(v, float).ravel()
        if q.size != n or v.size != n:
            raise ParameterError(f"design point needs q and v of length n = {n}, got {q.size} and {v.size}")
        out.append((q, v))
    return out


# ----------------------------------------------------------------------------- the whole design
@dataclass(frozen=True)
class FunnelDesign:
    """Parameters of (48) with the reasons: ``NMPFunnelController(model, lin, reference,
    **design.controller_options())``.

    Attributes
    ----------
    K, k_i, rho, pairing, funnels, kappa, kappa_bar, phi_bar
        The controller's parameters (``funnels[i][j]``, ``kappa[i][j]`` per output i and level j, or the
        override as given).
    relative_degrees : tuple
        ``r_i`` of ``y_new`` (``r_hat + k_i`` for the eta2 rows, ``r_hat`` otherwise).
    new_output : NewOutput
        The (A1) construction with its margins (``a1_design_point``, ``a1_points``).
    sources : dict
        ``"designed"`` or ``"override"`` per parameter.
    time_scale, expected_error
        ``T`` [s] and ``eps`` (output units) the rules used.
    initial_errors, initial_ratios, ratio_names
        ``e_i,j(0)`` per output (last entry: ``e_bar_i``) and ``phi(0) |e(0)|`` per level at ``start``.
    design_point, start : (q, v)
        Where ``S~`` for the construction was taken, and the plant's start state.
    notes, warnings : tuple of str
        How each piece was chosen; (A1) failures at design points.
    """

    K: tuple
    k_i: tuple
    rho: int
    pairing: tuple
    funnels: Any
    kappa: Any
    kappa_bar: float
    phi_bar: Any
    relative_degrees: tuple
    new_output: NewOutput
    sources: dict
    time_scale: float
    expected_error: np.ndarray
    initial_errors: tuple
    initial_ratios: np.ndarray
    ratio_names: tuple
    design_point: tuple
    start: tuple
    notes: tuple = ()
    warnings: tuple = ()
    given: dict = field(default_factory=dict, repr=False)
    levels: str = "per-output"

    @property
    def construction(self) -> str:
        return self.new_output.construction

    @property
    def decoupling_matrix(self) -> np.ndarray:
        return self.new_output.D

    @property
    def pairing_matrix(self) -> np.ndarray:
        return self.new_output.E

    @property
    def a1_design_point(self) -> float:
        """(A1) margin ``lambda_min(sym(rho D S~ E))`` at the design point."""
        return float(self.new_output.margins[0])

    @property
    def a1_points(self) -> np.ndarray:
        """(A1) margins at the design points (design point first, the start state last)."""
        return self.new_output.margins

    def controller_options(self) -> dict:
        """Keyword arguments of :class:`NMPFunnelController` (overrides exactly as given)."""
        out = {"K": [np.array(Ki) for Ki in self.K], "k_i": list(self.k_i), "rho": self.rho,
               "funnels": self.funnels, "kappa": self.kappa, "kappa_bar": self.kappa_bar, "phi_bar": self.phi_bar}
        if self.pairing != tuple(range(len(self.pairing))) or "pairing" in self.given:
            out["pairing"] = self.pairing
        out.update(self.given)
        return out

    def describe(self) -> str:
        lines = [f"funnel feedback design ({self.construction} construction)"]
        lines += [f"  - {n}" for n in self.notes]
        lines += [f"  ! {w}" for w in self.warnings]
        lines.append("  start ratios phi(0)|e(0)|: " + ", ".join(
            f"{n} {r:.3g}" for n, r in zip(self.ratio_names, self.initial_ratios)))
        return "\n".join(lines)

    def to_dict(self) -> dict:
        fun = lambda f: f.params if isinstance(f, Funnel) else f  # noqa: E731
        return {"K": [Ki.tolist() for Ki in self.K], "k_i": list(self.k_i), "rho": self.rho,
                "pairing": list(self.pairing), "construction": self.construction,
                "funnels": [[fun(f) for f in row] for row in self.funnels] if self.sources["funnels"] == "designed"
                else repr(self.funnels), "kappa": self.kappa, "kappa_bar": self.kappa_bar,
                "phi_bar": fun(self.phi_bar), "a1_design_point": self.a1_design_point,
                "a1_min_points": float(self.a1_points.min()), "relative_margin": self.new_output.relative_margin,
                "time_scale": self.time_scale, "expected_error": self.expected_error.tolist(),
                "initial_ratios": self.initial_ratios.tolist(), "sources": dict(self.sources), "levels": self.levels,
                "notes": list(self.notes), "warnings": list(self.warnings)}


def design_funnel_feedback(model, lin, reference, *, q0=None, v0=None, expected_error=None, design_points=None,
                           time_scale=None, rules: DesignRules | None = None, controller_options=None,
                           levels: str = "per-output", **overrides) -> FunnelDesign:
    """Choose ``K, k_i, rho, pairing, funnels, kappa, kappa_bar, phi_bar`` of (48) (rules: module docstring).

    Parameters
    ----------
    model, lin, reference
        As for :class:`NMPFunnelController` (``lin=None`` or ``lin.k = 0``: minimum phase).
    q0, v0 : array_like, optional
        The plant's start state (default: the linearization's design configuration at rest); the
        initial funnels contain its error levels.
    expected_error : float or array_like, optional
        Expected steady tracking error ``|y_l - y_ref,l|`` in output units (default: 2 % of the
        largest output excursion of the reference, the same for every output).
    design_points : (q, v) arrays (n, N) or list of (q, v), optional
        Where (A1) is checked and the high-gain rows refined, e.g. the inverse's states (default:
        21 quasi-static configurations along the reference).  The start state is always added.
    time_scale : float, optional
        ``T`` in seconds (default: :func:`reference_time_scale`).
    rules : DesignRules, optional
    controller_options : dict, optional
        Further options of the controller used to evaluate the start errors (``eta2_source``,
        ``t_end``, ``eta2_ref_samples``, ...); pass the same to the controller you build.
    levels : {"per-output", "shared"}
        Funnels and gains per output (invctl's extension) or one per level shared by all outputs
        (003 Sect. 6); see the module docstring.
    **overrides
        Entries of :data:`OVERRIDABLE`, used as is.

    Raises
    ------
    FeedbackDesignError
        (A1) fails at the design point, eta2 is not recoverable from ``y_new`` (rank), or a given
        funnel does not contain the start (``partial`` carries what was designed).
    """
    bad = sorted(set(overrides) - set(OVERRIDABLE))
    copts = dict(controller_options or {})
    bad += sorted(set(copts) & set(OVERRIDABLE))
    if bad:
        raise ParameterError(f"design_funnel_feedback: unknown or misplaced option(s) {bad}; overrides are "
                             f"{list(OVERRIDABLE)}, controller_options the other controller keywords")
    if levels not in LEVEL_RULES:
        raise ParameterError(f"design_funnel_feedback: levels must be one of {list(LEVEL_RULES)}, got {levels!r}")
    rules = rules or DesignRules()
    m, n = model.m, model.n
    k = lin.k if lin is not None else 0
    w0 = (np.asarray(lin.internal.point, float).ravel() if lin is not None else design_point(model, q0), np.zeros(n))
    q0 = w0[0] if q0 is None else np.asarray(q0, float).ravel()
    v0 = np.zeros(n) if v0 is None else np.asarray(v0, float).ravel()
    pts = _as_points(design_points, n) if design_points is not None else _quasi_static_points(lin, reference)
    S_all = _S_batch(model, [w0] + pts + [(q0, v0)])
    Qt, Pt = (lin.Q_tilde, lin.P_tilde) if k else (np.zeros((0, 0)), np.zeros((0, m)))
    new = design_new_output(Qt, Pt, S_all[0], S_points=S_all[1:], k_i=overrides.get("k_i"), K=overrides.get("K"),
                            rho=overrides.get("rho"), pairing=overrides.get("pairing"), refine=rules.refine)
    if not new.margins[0] > 0:
        raise FeedbackDesignError(f"(A1) fails at the design point: lambda_min(sym(rho D S~ E)) = "
                                  f"{new.margins[0]:.3g} <= 0 for K = {[Ki.tolist() for Ki in new.K]}", partial=new)
    if new.flatness_rank < k:
        raise FeedbackDesignError(f"the rows K_i Q~^j (j < k_i) have rank {new.flatness_rank} < k = {k}: eta2 is not "
                                  "a function of y_new and its derivatives, (41) does not remove the unstable part",
                                  partial=new)
    warnings = []
    if new.margins.min() <= 0:
        warnings.append(f"(A1) fails at {int(np.sum(new.margins <= 0))} of {new.margins.size} design points "
                        f"(min {new.margins.min():.3g}): it holds only near the design point")
    # -- scales: time, expected error
    T, exc, _ = reference_time_scale(reference, copts.get("t_end", 2.0), need=time_scale is None)
    if time_scale is not None:
        T = float(time_scale)
        if not T > 0:
            raise ParameterError(f"time_scale must be > 0 (seconds), got {time_scale!r}")
    if expected_error is None:
        if not exc.max() > 0:
            raise ParameterError("the reference does not move: give expected_error (output units)")
        eps = np.full(m, rules.expected_fraction * float(exc.max()))
    else:
        eps = np.broadcast_to(np.asarray(expected_error, float).ravel(), (m,)).copy()
        if not np.all(eps > 0):
            raise ParameterError(f"expected_error must be > 0 (output units), got {expected_error!r}")
    # -- relative degrees, gains, final widths
    q = len(new.k_i)
    r_hat = lin.r_hat if lin is not None else relative_degree(model, samples=0, points=[w0]).r_hat
    if r_hat is None:
        raise FeedbackDesignError(f"{model.name}: the outputs have different relative degrees at the design point; "
                                  "the funnel design needs one r_hat for all outputs (003 Sect. 5)")
    r = [r_hat + new.k_i[i] if i < q else r_hat for i in range(m)]
    sources = {name: ("override" if name in overrides else "designed") for name in OVERRIDABLE}
    kappa = overrides.get("kappa", [[rules.kappa_rate / T] * (ri - 1) for ri in r])
    kap = _nested(kappa, r, "kappa", lambda s, nm: float(s), _number_leaf)
    shared = levels == "shared"
    if shared:      # one gain per level: kappa_j of the first output that has level j
        top = [next(i for i in range(m) if r[i] - 1 > j) for j in range(max(r) - 1)]
        if any(kap[i][j] != kap[top[j]][j] for i in range(m) for j in range(r[i] - 1)):
            raise ParameterError(f"levels='shared' needs one gain per level (003 Sect. 6: kappa_i,j = kappa_j), "
                                 f"got kappa = {kappa!r}; give a list over the levels or levels='per-output'")
    lam0 = float(new.margins[0])
    Qinv = np.linalg.inv(Qt) if k and np.linalg.cond(Qt) < 1e8 else None
    G0 = [(-new.K[i] @ Qinv @ Pt if Qinv is not None else T * new.K[i] @ Pt) if i < q else new.K[i] for i in range(m)]
    load = _holding_input(model, reference, w0[0]) if "kappa_bar" not in overrides else None
    stiff = float(np.linalg.norm([np.prod(kap[i]) * (np.abs(G0[i]) @ eps) for i in range(m)]))
    kappa_bar_load = load / stiff if load and stiff > 0 else 0.0
    kappa_bar = float(overrides.get("kappa_bar", max(rules.kappa_bar_rate / (T * lam0), kappa_bar_load)))
    fin = []
    for i in range(m):
        row = [rules.final_factor * float(np.abs(G0[i]) @ eps)]
        for j in range(r[i] - 1):
            row.append(rules.level_factor * kap[i][j] * row[-1])
        fin.append(row)
    fin_bar = float(np.linalg.norm([row[-1] for row in fin]))
    if shared:      # phi_i,j = phi_j: the widest level 0, then level_factor kappa_j per level; phi = phi_(max r - 1)
        w = [max(fin[i][0] for i in range(m))]
        for j in range(max(r) - 1):
            w.append(rules.level_factor * kap[top[j]][j] * w[-1])
        fin = [w[:r[i]] for i in range(m)]
        fin_bar = w[-1]
    # -- initial widths from the start errors (the controller's own error functions)
    funnels, phi_bar, errs, ratios, names = _fit_start(
        lambda f, b, extra: NMPFunnelController(model, lin, reference, K=list(new.K), k_i=list(new.k_i), rho=new.rho,
                                                pairing=new.pairing, funnels=f, kappa=kappa, kappa_bar=kappa_bar,
                                                phi_bar=b, **copts, **extra),
        overrides.get("funnels"), overrides.get("phi_bar"), fin, fin_bar, r, rules, T, q0, v0, shared,
        reuse=bool(k) and copts.get("reference_mode", "backward") == "backward" and "eta2_ref_samples" not in copts)
    notes = _notes(new, lin, T, eps, expected_error, rules, kappa, kappa_bar, lam0, fin, fin_bar, sources, q0, v0, w0,
                   load, kappa_bar_load)
    if shared:
        notes.append("levels shared (003 Sect. 6): one funnel and one gain per level for all outputs, phi = phi_"
                     f"{max(r) - 1} on e_bar")
    design = FunnelDesign(tuple(new.K), tuple(new.k_i), new.rho, tuple(new.pairing), funnels, kappa, kappa_bar,
                          phi_bar, tuple(r), new, sources, T, eps, tuple(tuple(float(x) for x in e) for e in errs),
                          ratios, names, w0, (q0, v0), tuple(notes), tuple(warnings), dict(overrides), levels)
    if ratios.max() >= 1:
        raise FeedbackDesignError(f"the start state is outside a given funnel: {names[int(np.argmax(ratios))]} = "
                                  f"{ratios.max():.3g} >= 1 at t = 0; widen it (larger p)", partial=design)
    return design


def _fit_start(build, given_f, given_b, fin, fin_bar, r, rules, T, q0, v0, shared, reuse):
    """Initial widths ``max(transient_factor x final, |e(0)| / start_ratio)``, iterated with the controller's own
    error functions (the gains ``k_i,j`` of the upper levels depend on the funnels of the lower ones);
    ``shared``: the largest over the outputs per level."""

    def share(W):
        if shared:
            for j in range(max(r) - 1):
                wj = max(W[i][j] for i in range(len(r)) if r[i] - 1 > j)
                for i in range(len(r)):
                    if r[i] - 1 > j:
                        W[i][j] = wj
        return W

    def start_values(ctrl):
        out = ctrl.core(0.0, q0, v0, ctrl.z0(q0, v0), ctrl.eta2_ref(0.0))
        e, rows, it = np.array(out[3]).ravel(), [], 0
        for ri in ctrl.levels.r:
            rows.append(e[it:it + ri])
            it += ri
        return rows, np.array(out[1]).ravel(), tuple(ctrl.ratio_names)

    wide = Funnel.constant(1e6, "wide")
    ctrl = build(given_f if given_f is not None else [[wide] * (ri - 1) for ri in r],
                 given_b if given_b is not None else wide, {})
    if given_f is not None and given_b is not None:
        return (given_f, given_b) + start_values(ctrl)
    extra = {"eta2_ref_samples": ctrl.eta2_ref_grid} if reuse else {}     # the bounded solution of (42), once
    errs = start_values(ctrl)[0]
    m, beta = len(r), rules.start_ratio
    W = share([[max(abs(errs[i][j]) / beta, rules.transient_factor * fin[i][j]) for j in range(r[i] - 1)]
               for i in range(m)])
    Wb = max(float(np.linalg.norm([e[-1] for e in errs])) / beta, rules.transient_factor * fin_bar)
    for _ in range(6):
        funnels = given_f if given_f is not None else [
            [Funnel.exponential(W[i][j] - fin[i][j], rules.decay / T, fin[i][j],
                                f"phi_{j}" if shared else f"phi_{i + 1},{j}")
             for j in range(r[i] - 1)] for i in range(m)]
        phi_bar = given_b if given_b is not None else Funnel.exponential(Wb - fin_bar, rules.decay / T, fin_bar,
                                                                          "phi_bar")
        errs, ratios, names = start_values(build(funnels, phi_bar, extra))
        grow = False
        for i in range(m if given_f is None else 0):
            for j in range(r[i] - 1):
                if abs(errs[i][j]) > beta * (1 + 1e-9) * W[i][j]:
                    W[i][j], grow = abs(errs[i][j]) / beta, True
        share(W)
        nb = float(np.linalg.norm([e[-1] for e in errs]))
        if given_b is None and nb > beta * (1 + 1e-9) * Wb:
            Wb, grow = nb / beta, True
        if not grow:
            break
    return funnels, phi_bar, errs, ratios, names


def _notes(new, lin, T, eps, expected_error, rules, kappa, kappa_bar, lam0, fin, fin_bar, sources, q0, v0, w0, load,
           kappa_bar_load):
    src = lambda name: "given" if sources[name] == "override" else "designed"  # noqa: E731
    K = "; ".join(np.array2string(Ki, precision=4) for Ki in new.K)
    default_eps = f"default: {rules.expected_fraction:g} x largest excursion"
    how = "given" if new.construction == "given" else f"designed, {new.construction} construction"
    notes = [f"K ({how}): rows {K}, k_i = {list(new.k_i)} (controllability indices "
             f"{list(new.indices)}), pairing {list(new.pairing)} (e_bar_i drives u[pairing[i]]), rho = {new.rho}; "
             f"{new.note}",
             f"(A1): lambda_min(sym(rho D S~ E)) = {new.margins[0]:.4g} at the design point, "
             f"min {new.margins.min():.4g} over {new.margins.size} points, relative margin "
             f"{new.relative_margin:.3g}; zero conditions {new.zero_residual:.2g}, rank of K_i Q~^j = "
             f"{new.flatness_rank} (k = {lin.k if lin is not None else 0})",
             f"time scale T = {T:.4g} s; expected error {np.array2string(eps, precision=4)} "
             f"({'given' if expected_error is not None else default_eps})",
             f"kappa ({src('kappa')}): " + (f"{rules.kappa_rate:g}/T = {rules.kappa_rate / T:.4g}" if
                                          sources["kappa"] == "designed" else repr(kappa)),
             f"kappa_bar ({src('kappa_bar')}): " + (
                 f"max({rules.kappa_bar_rate:g}/(T lambda_0), load) = max({rules.kappa_bar_rate / (T * lam0):.4g}, "
                 f"{kappa_bar_load:.4g}) (lambda_0 = {lam0:.4g}; holding input ||u_s|| = "
                 f"{'n/a' if load is None else f'{load:.3g}'} carried at the expected error with nominal gains)"
                 if sources["kappa_bar"] == "designed" else f"{kappa_bar:g}"),
             f"funnels ({src('funnels')}), phi_bar ({src('phi_bar')})" + (
                 "" if "designed" not in (sources["funnels"], sources["phi_bar"]) else
                 f": q = {rules.decay:g}/T; final widths {[[float(f'{x:.3g}') for x in row[:-1]] for row in fin]}, "
                 f"phi_bar {fin_bar:.3g} ({rules.final_factor:g} x the quasi-static image of the expected error on "
                 f"level 0, x {rules.level_factor:g} kappa per level); initial widths >= "
                 f"{rules.transient_factor:g} x final and >= |e(0)|/{rules.start_ratio:g}")]
    if not (np.allclose(q0, w0[0]) and np.allclose(v0, w0[1])):
        notes.append(f"start state q0 = {np.round(q0, 4).tolist()} differs from the design point "
                     f"{np.round(w0[0], 4).tolist()}")
    return notes
