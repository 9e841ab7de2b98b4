"""Error-driven mesh refinement: solve, forward-check, refine where the collocation polynomial
violates the ODE most, warm-start, until the forward-check output error is below ``tol``."""
from __future__ import annotations

import math
import sys
from dataclasses import replace

import numpy as np

from ..errors import INTERRUPT_LIKE, InversionFailed, RunInterrupted, is_interrupt
from .schemes import get_scheme
from .guess import _split


def interval_errors(inv, servo, reference, theta) -> np.ndarray:
    """Local error estimate per interval: ``h_k * max |X'(t) - F(X(t), t)|`` of the
    collocation polynomial at points that are not collocation points (scaled per
    component by ``1 + max |X|``)."""
    tm = inv.t_mesh
    h = np.diff(tm)
    s = np.array([0.17, 0.33, 0.67, 0.83])
    tt = (tm[:-1, None] + h[:, None] * s[None, :]).ravel()
    eps = 1e-6 * h.min()
    dXn = (inv.X(tt + eps) - inv.X(tt - eps)) / (2 * eps)
    Y = servo.reference_samples(reference, tt)
    F = np.array(servo.maps.mapped(servo.rhs, tt.size)(inv.X(tt), Y, theta))
    scale = 1.0 + np.max(np.abs(inv.X_mesh), axis=1, keepdims=True)
    err = np.max(np.abs(dXn - F) / scale, axis=0).reshape(h.size, s.size).max(axis=1)
    return err * h


def refine(model, reference, options, warm_start, solve_once, servo):
    """Refine until ``options.discretization.tol`` is met.

    ``solve_once(options, warm_start) -> Inverse`` solves on ``options.discretization``'s mesh
    (``N`` or ``mesh``); the refined meshes are passed as ``mesh``.  On Ctrl-C,
    :class:`RunInterrupted` with the last accepted mesh's inverse (solved and forward-checked,
    ``tol`` not met yet) in ``partial``.
    """
    state = {"meshes": [], "accepted": None}
    tol = options.discretization.tol
    try:
        return _refine_meshes(model, reference, options, warm_start, solve_once, servo, state)
    except INTERRUPT_LIKE as exc:
        if not is_interrupt(exc):
            raise
        last, meshes = state["accepted"], state["meshes"]
        note = f"mesh refinement interrupted after {len(meshes)} complete mesh(es)"
        if last is not None:
            last.diagnostics.update({"meshes": meshes, "max_output_error": meshes[-1]["error"], "tol": tol,
                                     "partial": note})
        raise RunInterrupted(
            note + ("; the last accepted mesh (N = {}, forward-check error {:.3g}, tol {:.2g} not met) is in "
                    "exc.partial".format(last.N, meshes[-1]["error"], tol) if last is not None
                    else "; no mesh was complete") + (f" ({exc})" if str(exc) else ""),
            partial=last, diagnostics={"meshes": meshes}) from None


def _refine_meshes(model, reference, options, warm_start, solve_once, servo, state):
    from .verify import forward_check

    disc = options.discretization
    tol = disc.tol
    sch = get_scheme(disc.scheme)
    meshes = state["meshes"]
    inv = warm_start
    total_build = total_solve = 0.0
    current = replace(disc, tol=None)
    progress = options.solver.progress
    for it in range(disc.max_refinements + 1):
        inv = solve_once(replace(options, discretization=current), inv)
        fc = forward_check(model, inv, reference, **dict(disc.forward_options or {}))
        total_build += inv.diagnostics["build_s"]
        total_solve += inv.diagnostics["solve_s"]
        meshes.append({"N": inv.N, "error": fc["error"], "iterations": inv.diagnostics["iterations"],
                       "solve_s": inv.diagnostics["solve_s"], "build_s": inv.diagnostics["build_s"]})
        state["accepted"] = inv
        if progress:
            print(f"  refinement {it}: N = {inv.N}, forward-check error {fc['error']:.3e} (tol {tol:.1e})",
                  file=sys.stderr)
        if fc["error"] <= tol:
            inv.diagnostics.update({"meshes": meshes, "max_output_error": fc["error"], "forward_check": {
                k: fc[k] for k in ("error", "t_worst", "window", "windows", "rate")}, "tol": tol,
                "total_build_s": total_build, "total_solve_s": total_solve})
            return inv
        if it == disc.max_refinements or inv.N >= disc.max_N:
            break
        err = np.maximum(interval_errors(inv, servo, reference, model.theta_values), 1e-300)
        h = np.diff(inv.t_mesh)
        order = sch.order
        factor = min(4.0, max(1.5, (fc["error"] / tol) ** (1.0 / order) * 1.2))
        N = min(disc.max_N, int(math.ceil(inv.N * factor)))
        dens = (err / h ** (order + 1)) ** (1.0 / (order + 1))
        dens = np.maximum(dens, 0.05 * dens.max())
        cum = np.concatenate([[0.0], np.cumsum(dens * h)])
        knots = [inv.T0, reference.t0, reference.tf, inv.Tf]
        ck = np.interp(knots, inv.t_mesh, cum)
        counts = _split(N, np.diff(knots), np.diff(ck))
        parts = [np.interp(np.linspace(ck[i], ck[i + 1], counts[i] + 1)[:-1], cum, inv.t_mesh)
                 for i in range(3) if counts[i] > 0]
        t_mesh = np.concatenate(parts + [[inv.Tf]])
        t_mesh[0], t_mesh[-1] = inv.T0, inv.Tf
        current = replace(current, mesh=t_mesh)
    tried = ", ".join(f"N={m['N']}: {m['error']:.2g}" for m in meshes)
    raise InversionFailed(
        f"mesh refinement did not reach the output error {tol:.2g}; meshes tried (forward-check error): {tried}; "
        "raise max_refinements/max_N or use a higher-order scheme (legendre3)", partial=inv,
        diagnostics={"meshes": meshes})
