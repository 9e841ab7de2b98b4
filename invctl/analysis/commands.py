"""``invctl analyze <scene>``: relative degree, Gamma conditioning, internal dynamics, linearization.

A scene may define ``analysis_setup(model[, samples]) -> dict`` with any of

``internal``      an :class:`InternalDynamics` (default: Sect. 3 coordinates at the design point),
``linearization`` a :class:`LinearizedInternal` (default: at the design point, y-derivatives 0),
``reference``     a :class:`Reference` (for (A2) and eta2_ref^0),
``A1``            ``{"K": [...], "k_i": [...], "rho": ...}`` to check (A1), or a dict name -> such
                  dicts to check several choices (the first is reported as ``checks["A1"]``),
``point``         the design configuration ``q0``.
"""
from __future__ import annotations

import inspect
import time

import numpy as np

from ..errors import InvctlError, SceneError
from ..model import Model
from ..scenes import CommandResult
from .internal import internal_dynamics
from .linearize import linearize_internal
from .relative_degree import relative_degree

_OPTIONS = {"samples"}


def _fmt(M) -> str:
    M = np.atleast_2d(M)
    return "[" + "; ".join(" ".join(f"{v:10.5g}" for v in row) for row in M) + "]"


def _cross_check(a, b, points, per_point: int = 3, rng=0):
    """Largest relative difference of two internal-dynamics routes at the linearization points
    perturbed (y-derivatives above y by 0.2, eta by 0.05) so that the right-hand side is not ~0."""
    gen = np.random.default_rng(rng)
    worst = None
    for ys, eta in points:
        for _ in range(per_point):
            ys_p = [np.asarray(y, float) + (0.2 * gen.uniform(-1, 1, np.size(y)) if k else 0.0)
                    for k, y in enumerate(ys)]
            eta_p = np.asarray(eta, float) + 0.05 * gen.uniform(-1, 1, np.size(eta))
            try:
                fa, fb = a(ys_p, eta_p), b(ys_p, eta_p)
            except InvctlError:
                continue
            d = float(np.max(np.abs(fa - fb)) / max(1.0, np.max(np.abs(fa)))) if fa.size else 0.0
            worst = d if worst is None else max(worst, d)
    return worst


def analyze(model, setup: dict | None = None, samples: int = 200) -> dict:
    """The analysis behind ``invctl analyze`` as a dict of results (no printing)."""
    setup = dict(setup or {})
    timings = {}
    t = time.perf_counter()
    rd = relative_degree(model, samples=samples)
    timings["relative_degree_s"] = time.perf_counter() - t
    t = time.perf_counter()
    internal = setup.get("internal") or internal_dynamics(model, "sect3", point=setup.get("point"), samples=samples)
    timings["internal_s"] = time.perf_counter() - t
    t = time.perf_counter()
    lin = setup.get("linearization")
    if lin is None:
        q0 = internal.point
        y0 = model.evaluate("h", q0).ravel()
        eta0 = np.array(internal.eta(q0, np.zeros(model.n), model.theta_values)).ravel()
        pt = ([y0] + [np.zeros(model.ny)] * (internal.r_hat - 1), eta0)
        lin = linearize_internal(model, internal, [pt])
    timings["linearize_s"] = time.perf_counter() - t
    # cross-check: the other method gives the same right-hand side at the linearization points
    t = time.perf_counter()
    other = "sect2" if internal.method == "sect3" else "sect3"
    cross = None
    try:
        alt = internal_dynamics(model, other, internal.phi_expr, point=internal.point, samples=samples)
        cross = _cross_check(internal, alt, lin.points)
    except InvctlError:
        cross = None
    timings["cross_check_s"] = time.perf_counter() - t
    checks = {
        "relative_degree_exists": True,
        "gamma_min_singular_value": rd.min_singular_value,
        "L_K_phi_max": internal.checks["LK_max"],
        "Phi_prime_sigma_min": internal.checks["Phi_sigma_min"],
        "sect2_vs_sect3_max_diff": cross,
        "linearization_points_in_region": lin.diagnostics.get("points_in_region"),
    }
    ref = setup.get("reference")
    a2 = lin.check_A2(ref)
    checks["A2"] = a2.to_dict()
    if "A1" in setup:
        variants = {"scene": setup["A1"]} if "K" in setup["A1"] else dict(setup["A1"])
        reports = {name: lin.check_A1(a1["K"], rho=a1.get("rho"), k_i=a1.get("k_i"), samples=samples).to_dict()
                   for name, a1 in variants.items()}
        checks["A1"] = next(iter(reports.values()))
        checks["A1_all"] = reports
    eta_ref0 = None
    if ref is not None and lin.k and a2.l2 == 0:
        eta_ref0 = lin.eta2_ref0(ref)
    return {"rd": rd, "internal": internal, "lin": lin, "checks": checks, "eta2_ref0": eta_ref0,
            "timings": timings}


def analyze_command(scene_module, params: dict, samples: int = 200, **options) -> CommandResult:
    """Handler of ``invctl analyze <scene>`` (see module docstring)."""
    unknown = sorted(set(options) - _OPTIONS)
    if unknown:
        raise SceneError(f"invctl analyze does not take option(s) {unknown}")
    if samples < 1:
        raise SceneError(f"--samples must be positive, got {samples}")
    t0 = time.perf_counter()
    model = scene_module.build(**params)
    if not isinstance(model, Model):
        raise SceneError(f"scene {getattr(scene_module, '__name__', '?')!r}: build() returned "
                         f"{type(model).__name__}, but invctl analyze needs an invctl.model.Model")
    t_setup = time.perf_counter()
    setup = {}
    if hasattr(scene_module, "analysis_setup"):
        hook = scene_module.analysis_setup
        takes_samples = "samples" in inspect.signature(hook).parameters
        setup = hook(model, samples=samples) if takes_samples else hook(model)
    t_setup = time.perf_counter() - t_setup
    res = analyze(model, setup, samples)
    res["timings"]["scene_setup_s"] = t_setup
    rd, internal, lin, checks = res["rd"], res["internal"], res["lin"], res["checks"]
    wall = time.perf_counter() - t0
    p, l, m = rd.blocks
    eig = lin.eigenvalues
    lines = [
        f"invctl analyze {model.name}: n = {model.n}, l = {l}, p = {p}, m = {m}",
        f"parameters: " + ", ".join(f"{k}={v:.6g}" for k, v in model.values.items()),
        f"vector relative degree of the auxiliary ODE (10): {list(rd.r_aux)}  ->  r_hat = {rd.r_hat}, "
        f"r_bar = {rd.r_bar}",
        f"high-gain matrix Gamma on {rd.samples} points of {rd.region or 'the sample box'}:",
        f"  worst condition number {rd.worst_condition:.4g} at q = {np.round(rd.worst_point[0], 4).tolist()}",
        f"  smallest singular value {rd.min_singular_value:.4g}; det Gamma in [{rd.det_range[0]:.4g}, "
        f"{rd.det_range[1]:.4g}]",
        f"internal dynamics: dimension 2n - r_bar = {internal.dim} ({internal.method}, {internal.coordinates})",
        f"  checks: max |L_K phi| = {checks['L_K_phi_max']:.2g}, min sigma(Phi') = "
        f"{checks['Phi_prime_sigma_min']:.3g}"
        + (f", Sect. 2 vs Sect. 3 rhs differ by {checks['sect2_vs_sect3_max_diff']:.2g} (relative, near the "
           "linearization points)"
           if checks["sect2_vs_sect3_max_diff"] is not None else ""),
        f"linearization (37) at {len(lin.points)} point(s)"
        + (f" (configurations in the region: {lin.diagnostics['points_in_region']})"
           if "points_in_region" in lin.diagnostics else "")
        + ", derivative removal (38): eta' = Q eta + P y",
        f"  Q = {_fmt(lin.Q)}",
        f"  P = {_fmt(lin.P)}",
        f"  eigenvalues of Q: {np.round(eig, 6).tolist()}  "
        f"({lin.k} in the closed right half plane: {'minimum phase' if lin.minimum_phase else 'non-minimum phase'})",
    ]
    if lin.k:
        lines.append(f"  split (39, T by {lin.split}): Q~ = {_fmt(lin.Q_tilde)}, P~ = {_fmt(lin.P_tilde)}")
    lines.append(f"  (A2): {'holds' if checks['A2']['passed'] else 'NOT shown'} - {checks['A2']['message']}")
    for name, a1 in checks.get("A1_all", {}).items():
        lines.append(
            f"  (A1), {name} (rho = {a1['rho']}): {'holds' if a1['passed'] else 'does NOT hold'} on all "
            f"region samples ({100 * a1['fraction_satisfied']:.0f}% of {a1['samples']} points; min eig of sym. part "
            f"{a1['min_eig_sym']:.3g}, at the design point {a1['min_eig_at_design_point']:.3g})"
        )
    if res["eta2_ref0"] is not None:
        lines.append(f"  eta2_ref^0 by (43): {np.round(res['eta2_ref0'], 6).tolist()}")
    lines.append(f"analysis time {wall:.3f} s")
    data = {
        "scene": model.name,
        "params": dict(model.values),
        "relative_degree": list(rd.r_aux),
        "r_hat": rd.r_hat,
        "r_bar": rd.r_bar,
        "gamma": rd.to_dict(),
        "internal_dim": internal.dim,
        "internal_method": internal.method,
        "internal_eigs": eig.real.tolist() if np.all(eig.imag == 0) else [[e.real, e.imag] for e in eig],
        "Q": lin.Q, "P": lin.P, "P_list": lin.P_list, "T": lin.T, "k": lin.k,
        "Q_tilde": lin.Q_tilde, "P_tilde": lin.P_tilde,
        "eta2_ref0": res["eta2_ref0"],
        "checks": checks,
        "timings": {**res["timings"], "total_s": wall},
    }
    return CommandResult("\n".join(lines), data)
