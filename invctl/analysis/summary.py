"""The analysis of a tracking model in one call: relative degree, Gamma, internal dynamics, linearization.

:func:`analyze` takes a ``setup`` dict with any of

``internal``      an :class:`InternalDynamics` (default: Sect. 3 coordinates at the design point),
``linearization`` a :class:`LinearizedInternal` (default: at the design point, y-derivatives 0),
``reference``     a :class:`Reference` (for (A2) and eta2_ref^0),
``A1``            ``{"K": [...], "k_i": [...], "rho": ...}`` to check (A1), or a dict name -> such
                  dicts to check several choices (the first is reported as ``checks["A1"]``),
``point``         the design configuration ``q0``,
``points``        configurations (e.g. the equilibria along the reference) around which the checks
                  sample when the model declares no operating region.
"""
from __future__ import annotations

import time

import numpy as np

from ..errors import InvctlError
from .internal import internal_dynamics
from .linearize import linearize_internal
from .relative_degree import relative_degree

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
    points = setup.get("points") if model.region is None else None
    rd = relative_degree(model, samples=samples, points=points)
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
        "Phi_prime_singular_count": internal.checks.get("Phi_singular_count"),
        "Phi_prime_singular_sample": internal.checks.get("Phi_singular_sample"),
        "sect2_vs_sect3_max_diff": cross,
        "linearization_points_in_region": lin.diagnostics.get("points_in_region"),
    }
    ref = setup.get("reference")
    a2 = lin.check_A2(ref)
    checks["A2"] = a2.to_dict()
    if "A1" in setup:
        variants = {"scene": setup["A1"]} if "K" in setup["A1"] else dict(setup["A1"])
        reports = {name: lin.check_A1(a1["K"], rho=a1.get("rho"), k_i=a1.get("k_i"), samples=samples,
                                      points=points).to_dict()
                   for name, a1 in variants.items()}
        checks["A1"] = next(iter(reports.values()))
        checks["A1_all"] = reports
    zeros = None
    try:
        from .zeros import classify_zeros

        zeros = classify_zeros(model, internal.point, internal=internal)
    except InvctlError as exc:
        checks["zeros_error"] = f"{type(exc).__name__}: {exc}"
    eta_ref0 = None
    if ref is not None and lin.k and a2.l2 == 0:
        eta_ref0 = lin.eta2_ref0(ref)
    return {"rd": rd, "internal": internal, "lin": lin, "checks": checks, "eta2_ref0": eta_ref0,
            "zeros": zeros, "timings": timings}
