"""Free transition time: the shortest (or a time-energy optimal) duration of a reference whose
shape is fixed, under bounds, with exact tracking (:mod:`invctl.inversion.ocp`, ``free_time``).

The reference ``y_ref`` on ``[t0, tf]`` defines the shape ``y_ref(t0 + s (tf - t0))``,
``s in [0, 1]``; a duration ``tau`` gives ``y(t) = shape((t - t0) / tau)`` on ``[t0, t0 + tau]``.
The pre- and post-actuation of the automatic setup (they depend on the internal dynamics at the
end equilibria, not on ``tau``) keep their lengths; the mesh intervals of ``[t0, tf]`` scale with
``tau``.  The problem::

    minimize   tau + w_E int_{T0}^{Tf} |u|^2 dt          (w_E = 0: minimum time)
    subject to the collocation equations of 003 (35) for y_ref of duration tau,
               the boundary conditions 003 (36) and the bounds,  duration[0] <= tau <= duration[1]

With exact tracking the states are a function of ``tau`` alone (the square system), so the
optimum is where a bound becomes active (minimum time) or where the energy saved by a longer
move balances the time (``w_E > 0``).

The bounds hold on the returned interpolant, between the mesh points too: the problem bounds every
interval's polynomial at interior points (``interior="points"`` of :mod:`invctl.inversion.ocp`),
first spread over the interval (Legendre/Radau: none at first), then, solved again, at the interior
extrema of the solution, until the check of :func:`~invctl.inversion.bounded.between_nodes` passes
(``diagnostics["bound_rounds"]`` re-solves, at most :data:`~invctl.inversion.bounded.EXTREMA_ROUNDS`).
"""
from __future__ import annotations

import time
from dataclasses import replace

import casadi as ca
import numpy as np

from ..errors import InfeasibleBoundsError, InversionFailed, OptionError, WallTimeLimitError
from .backends import _TIME_LIMIT
from .bounded import (EXTREMA_ROUNDS, _beyond_tolerance, _inverse, _limits, _violation, active_bounds, between_nodes,
                      check_between_nodes, constraint_points, solve_scaled)
from .cache import ocp_transcription, servo_model
from .options import Bounds, from_keywords
from .problem import prepare, resolve_plan


def retime(reference, duration: float):
    """``reference`` with its transition ``[t0, tf]`` stretched to ``[t0, t0 + duration]`` (same shape)."""
    from ..reference import Reference

    tau_ref = reference.tf - reference.t0
    t = reference.t
    expr = ca.substitute(reference.expr, t, reference.t0 + (t - reference.t0) * (tau_ref / float(duration)))
    return Reference(t, expr, reference.t0, reference.t0 + float(duration), reference.smoothness, reference.name,
                     diagnostics={**reference.diagnostics, "retimed_from": [reference.t0, reference.tf]})


def minimum_time(model, reference, *, bounds=None, energy: float = 0.0, duration=None, objective=None,
                 discretization=None, solver=None, horizon=None, warm_start=None, **keywords):
    """The minimum-time (``energy = 0``) or time-energy optimal duration of ``reference``'s
    transition under ``bounds`` (module doc).

    Parameters
    ----------
    model, reference : Model, Reference
        As for :func:`~invctl.inversion.invert`; ``reference`` gives the shape and the initial
        duration.
    bounds : Bounds
        Bounds on ``u``, ``u'``, ``q``, ``v`` (pre-/post-actuation bounds are not used here).
    energy : float
        Weight ``w_E`` of the input energy (``int |u|^2 dt`` over the horizon) against the duration.
    duration : (float, float), optional
        Range of ``tau``; default ``(0.02, 50) * (tf - t0)``.
    objective : Objective, optional
        Relax the servo constraint and add this least-squares objective (output error, slack,
        energy, rate weights) to ``tau``: the fastest transition that tracks the shape as well as
        the weights ask.  With ``Objective(output=0, slack=0)`` and a selection fixing ``q``,
        ``v`` (and ``u``) at both ends it is the classical free-input minimum-time problem
        between the reference's end equilibria.
    discretization, solver, horizon, **keywords
        As for :func:`~invctl.inversion.invert` (the horizon's ``T0``/``Tf`` fix the pre- and
        post-actuation lengths for the reference's duration).

    Returns
    -------
    Inverse
        The exact inverse of the retimed reference (``inv.y_ref`` is the retimed reference);
        ``diagnostics["free_time"]`` holds the optimal ``duration``, the ``energy``, the
        objective and the active bounds.

    Raises
    ------
    InfeasibleBoundsError
        No duration in the range satisfies the bounds (e.g. the equilibria violate them).
    InversionFailed
        IPOPT did not converge (the last iterate in ``exc.partial``).
    """
    return _minimum_time(None, model, reference, bounds=bounds, energy=energy, duration=duration, objective=objective,
                         discretization=discretization, solver=solver, horizon=horizon, warm_start=warm_start,
                         **keywords)


def _minimum_time(hold, model, reference, *, bounds=None, energy: float = 0.0, duration=None, objective=None,
                  discretization=None, solver=None, horizon=None, warm_start=None, **keywords):
    """:func:`minimum_time`; ``hold`` (a dict, :class:`MinimumTimeSolver`): the plan, setup and last
    solution of an earlier call on the same model, reference and options, reused and updated."""
    t_all = time.perf_counter()
    opts = from_keywords("minimum_time", discretization=discretization, solver=solver, horizon=horizon,
                         bounds=bounds, objective=objective, **keywords)
    objective = opts.objective
    if opts.bounds is None and not energy > 0:
        raise OptionError("minimum_time: give bounds (minimum time under bounds) and/or energy > 0 (time-energy "
                          "trade); without either the shortest duration is zero")
    if not (np.isfinite(energy) and energy >= 0):
        raise OptionError(f"minimum_time: energy must be a nonnegative weight, got {energy!r}")
    bnd = opts.bounds or Bounds()
    if bnd.max_pre_actuation is not None or bnd.max_post_actuation is not None:
        raise OptionError("minimum_time: pre-/post-actuation bounds are not supported with a free duration; fix "
                          "T0/Tf through horizon=Horizon(T0=..., Tf=...) instead")
    disc, slv = opts.discretization, opts.solver
    if disc.tol is not None:
        if hold is not None:
            raise OptionError("MinimumTimeSolver: tol refines the mesh by raising N, a new problem each time; give N "
                              "(or call minimum_time with tol=...)")
        return _refined(model, reference, opts, dict(bounds=opts.bounds, energy=energy, duration=duration,
                                                     objective=opts.objective, horizon=opts.horizon), warm_start)
    tau_ref = reference.tf - reference.t0
    lo, hi = (0.02 * tau_ref, 50.0 * tau_ref) if duration is None else (float(duration[0]), float(duration[1]))
    if not 0 < lo < hi:
        raise OptionError(f"minimum_time: duration must be (lower, upper) with 0 < lower < upper, got {duration!r}")
    servo = servo_model(model, disc.formulation, disc.omega)
    rb = bnd.resolve(servo)
    relaxed = objective is not None
    last = hold.get("last") if hold else None
    if last is not None:  # a held solver's re-solve: plan and setup as before
        plan_result, setup = last["plan_result"], last["setup"]
    else:
        plan_result = resolve_plan(model, reference, disc, opts.horizon)
        setup = prepare(model, reference, disc, opts.horizon, plan_result=plan_result, any_count=relaxed)
    from .solver import InversionSolver
    from .square import make_inverse, solve_square

    t_mesh = setup.t_mesh
    inside = (t_mesh[:-1] >= reference.t0 - 1e-12) & (t_mesh[1:] <= reference.tf + 1e-12)
    covered = np.sum(np.diff(t_mesh)[inside])
    if abs(covered - tau_ref) > 1e-9 * max(1.0, tau_ref):
        raise OptionError("minimum_time: the mesh must have t0 and tf as mesh points (the default meshes do)")
    mask = inside.astype(float)
    theta = model.theta_values
    # the exact inverse at the reference's duration: the initial guess
    hz = replace(opts.horizon, T0=setup.T0, Tf=setup.Tf, start=plan_result[2], end=plan_result[3],
                 plan=plan_result[4], plan_options=None)
    square = len(setup.selection.start) + len(setup.selection.end) == servo.layout.nx
    if last is not None:
        guess = None  # the last solution is the start
    elif warm_start is None and square:
        guess = solve_square(model, reference, replace(opts, horizon=hz, bounds=None, objective=None), setup=setup)
    else:
        guess = None
    sch, N = setup.scheme, t_mesh.size - 1
    tr = ocp_transcription(servo, setup.selection, sch, N, relaxed=relaxed, free_time=True, bounded=rb.bounded,
                           rated=rb.rated, interior=sch.tracking_interior, compiled=disc.compiled)
    tc = tr.collocation_times(t_mesh)
    tau0 = float(np.clip(tau_ref if warm_start is None else warm_start.tf - warm_start.t0, lo, hi))
    no_inverse = None  # a shorter duration at which the exact inverse of the shape was not found
    if guess is not None and warm_start is None and not relaxed:
        # start where the exact inverse nearly meets the input and rate bounds (they scale like
        # tau^-2 and tau^-3 for a fixed shape): from a duration the bounds cut deeply into, IPOPT's
        # first steps can leave towards very short moves, where the non-minimum-phase inverse explodes.
        # Bounds far from what the reference needs (either way) put the optimum far from tau_ref: the
        # estimate is refined on exact inverses of the retimed shape (a fixed-point iteration, as the
        # parts of the inputs that do not scale, e.g. gravity, make the power laws approximate)
        cur, tau_cur, mesh_cur = guess, tau_ref, t_mesh
        # one held solver for the retimed exact inverses: the mesh keeps N, so its transcription is reused
        held = InversionSolver(model, reference, discretization=disc, solver=opts.solver,
                               horizon=replace(hz, plan=None))
        for _round in range(8):
            target = float(np.clip(_feasible_duration(cur, servo, retime(reference, tau_cur), theta, rb, tau_cur),
                                   lo, hi))
            if abs(target / tau_cur - 1.0) < (0.02 if _round else 1e-9):
                break
            tau_s = float(np.clip(target, tau_cur / 2, tau_cur * 2))  # continuation: at most a factor 2 a step
            for _halving in range(3):
                mesh_s = tr.retimed_mesh(t_mesh, mask, tau_ref, tau_s)
                try:
                    cur = held.solve(reference=retime(reference, tau_s), mesh=mesh_s,
                                     warm_start=_Retimed(cur, mesh_cur, mesh_s))
                    break
                except InversionFailed:
                    if tau_s < tau_cur:
                        no_inverse = tau_s  # the tightest failure so far (the halvings approach tau_cur)
                    tau_s = float(np.sqrt(tau_s * tau_cur))
            else:
                break  # keep the last duration whose exact inverse exists
            tau_cur, mesh_cur = tau_s, mesh_s
        if cur is not guess:
            warm_start, tau0 = cur, tau_cur
    if last is not None:  # the held solution (same layout), its duration moved into the range
        x0 = last["x"].copy()
        x0[tr.i_tau] = float(np.clip(x0[tr.i_tau], lo, hi))
        tau0 = float(x0[tr.i_tau])
    elif warm_start is not None:  # a solution for another duration: sample it at the same shape positions
        ws_mesh = tr.retimed_mesh(t_mesh, mask, tau_ref, tau0)
        x0 = tr.pack(warm_start.X(ws_mesh), warm_start.X(tr.collocation_times(ws_mesh)) if tc.size else None,
                     tau=tau0)
    elif guess is not None:
        x0 = tr.pack(guess.X(t_mesh), guess.X(tc) if tc.size else None, tau=tau0)
    else:
        x0 = tr.pack(setup.initial_guess(t_mesh), setup.initial_guess(tc) if tc.size else None, tau=tau0)
    Y = servo.reference_samples(reference, tr.sample_times(t_mesh))
    lbx, ubx, lbg, ubg = _limits(tr, rb, (lo, hi))

    from .ocp import slack_scale

    c = slack_scale(servo, tau_ref)
    ow = objective.output_weights(model) if relaxed else 0.0
    rho, e_w, r_w = (objective.slack, objective.energy + energy, objective.rate) if relaxed else (0.0, energy, 0.0)

    # interior points spread over the intervals, then at the extrema of the polynomials (held: the last ones)
    kept = last if last is not None and last["tr"] is tr else None  # the held solution on this transcription
    points = None if kept is None else kept["points"]
    # a held re-solve of another problem moves its points to the extrema of its own first solution, as a fresh
    # solve does (the check alone would accept points that leave the bounds violated up to ACTIVE_TOL)
    problem = (rb.lo.tobytes(), rb.hi.tobytes(), rb.rate_lo.tobytes(), rb.rate_hi.tobytes(), float(energy), lo, hi)
    moved = kept is not None and kept["problem"] != problem

    def params(scale):
        return tr.parameters(t_mesh, Y, theta, setup.E0, setup.Ef, W=ow, rho=rho, energy=e_w, rate=r_w,
                             time_weight=1.0, c=c, mask=mask, tau_ref=tau_ref, scale=scale, points=points)

    t_solve = time.perf_counter()
    hessian = "exact" if slv.hessian == "auto" else slv.hessian
    start, rounds, iterations = x0, 0, 0
    warm = None if kept is None else (kept["lam_x"], kept["lam_g"])
    while True:  # until the bounds hold between the nodes too (interior points at the extrema)
        # from the second round on, the last round's primal-dual point: the problem only moved its interior points
        sol, st, scale = solve_scaled(tr, slv, start, params, (lbx, ubx, lbg, ubg), hessian=hessian, scale=1.0,
                                      warm=warm)
        iterations += st["iterations"]
        x, g = np.array(sol["x"]).ravel(), np.array(sol["g"]).ravel()
        viol = _violation(g, lbg, ubg, x, lbx, ubx)
        status = st.get("return_status", "?")
        ok = bool(st.get("success", False)) or (status == "Solved_To_Acceptable_Level" and viol < 1e-8)
        tau = float(x[tr.i_tau])
        ref_opt = retime(reference, tau)
        mesh_opt = tr.retimed_mesh(t_mesh, mask, tau_ref, tau)
        Yopt = servo.reference_samples(ref_opt, tr.sample_times(mesh_opt))
        inv = _inverse(tr, servo, ref_opt, sch, mesh_opt, x, Yopt, theta, c, make_inverse)
        chk = between_nodes(inv, rb)
        if not ok or rounds >= EXTREMA_ROUNDS or not (_beyond_tolerance(rb, chk) or (moved and not rounds)):
            break
        warm = (sol["lam_x"], sol["lam_g"])
        if tr.interior is None:  # Legendre/Radau: add the interior points only where a bound needs them
            tr = ocp_transcription(servo, setup.selection, sch, N, relaxed=relaxed, free_time=True,
                                   bounded=rb.bounded, rated=rb.rated, interior="points", compiled=disc.compiled)
            lbx, ubx, lbg, ubg = _limits(tr, rb, (lo, hi))
            warm = None  # another layout of the constraints
        points, start, rounds = tr.extremum_points(inv), x, rounds + 1
    st["iterations"] = iterations
    solve_s = time.perf_counter() - t_solve
    # energy by the scheme's quadrature (the objective's own), and the active bounds at the optimum
    w_unit = tr.parameters(mesh_opt, Yopt, theta, setup.E0, setup.Ef, W=0.0, energy=1.0, time_weight=0.0,
                           mask=np.zeros(N), tau_ref=tau)
    E = float(np.sum(np.array(tr.residual(x, w_unit)) ** 2))
    active = active_bounds(tr, rb, mesh_opt, x, np.array(sol["lam_x"]).ravel() / scale,
                           np.array(sol["lam_g"]).ravel() / scale, g)
    at_limit = [name for name, val, b in (("duration lower", tau, lo), ("duration upper", tau, hi))
                if abs(val - b) <= 1e-6 * b]
    from .square import residuals

    res = residuals(inv, servo, ref_opt, theta)
    inv.diagnostics.update({
        "status": status, "iterations": int(st["iterations"]), "success": ok, "max_constraint_violation": viol,
        "backend": "ipopt", "hessian": hessian, "scheme": sch.name, "N": int(N), "relaxed": relaxed,
        "formulation": disc.formulation, "omega": disc.omega, "build_s": setup.timings["build_s"] + tr.build_s,
        "solve_s": solve_s, "guess_s": setup.timings["guess_s"], "unknowns": tr.nX, "equations": tr.ng,
        "selection": setup.selection.describe(), "T0": inv.T0, "Tf": inv.Tf, "residuals": res,
        "plan": None if setup.plan is None else setup.plan.to_dict(), "mesh": setup.mesh_kind,
        "bound_rounds": rounds, "held": last is not None,
        "free_time": {"duration": tau, "reference_duration": tau_ref, "t0": reference.t0, "tf": reference.t0 + tau,
                      "energy": E, "energy_weight": float(energy), "objective": tau + energy * E,
                      "duration_range": [lo, hi], "at_duration_limit": at_limit, "active": active,
                      "bound_violation": chk["max_violation_between_nodes"]},
        "wall_s": time.perf_counter() - t_all,
    })
    ft = inv.diagnostics["free_time"]
    ft["limited_by"] = ("bounds" if active else "duration range" if at_limit else "energy weight" if energy > 0
                        else "model")
    model_limit = ""
    if no_inverse is not None and no_inverse < tau0:
        inv.diagnostics["free_time"]["no_exact_inverse_at"] = no_inverse
        model_limit = (f"; the exact inverse of this shape was not found at a duration of {no_inverse:.4g} s "
                       f"(it exists at {tau0:.4g} s, where the bounds are not yet active): the shortest move may "
                       "be limited by the model (the inverse ceasing to exist), not by the bounds; search above it "
                       f"(duration=({tau0:.4g}, ...), --duration {tau0:.4g}:HI)")
    if hold is not None and ok:
        hold["last"] = {"plan_result": plan_result, "setup": setup, "tr": tr, "x": x, "points": points, "problem": problem,
                        "lam_x": sol["lam_x"], "lam_g": sol["lam_g"]}
    key = "holonomic_mesh" if relaxed else "position_mesh"
    if ok and res[key] > slv.residual_tol:
        raise InversionFailed(
            f"minimum_time: the solution violates the position-level constraints by {res[key]:.3g} > residual_tol "
            f"= {slv.residual_tol:.3g} at the mesh ({sch.name} N={N}); refine the mesh{model_limit}", partial=inv,
            diagnostics=inv.diagnostics)
    if not ok and status in _TIME_LIMIT:
        raise WallTimeLimitError(
            f"minimum_time stopped at the wall-time limit of {slv.max_wall_time:g} s after "
            f"{inv.diagnostics['iterations']} iterations ({sch.name} N={N}); raise max_wall_time or use fewer "
            f"intervals (N); the last iterate is in exc.partial{model_limit}", partial=inv,
            diagnostics=inv.diagnostics)
    if not ok:
        if status in ("Infeasible_Problem_Detected", "Restoration_Failed", "Local_Infeasibility"):
            raise InfeasibleBoundsError(
                f"minimum_time: no duration in [{lo:.4g}, {hi:.4g}] s lets the exact inverse satisfy the bounds "
                f"(IPOPT: {status}, constraint violation {viol:.3g}); widen the duration range or relax the bounds "
                "(invert with bounds= gives the least-squares compromise and the closest feasible relaxation)",
                partial=inv, diagnostics=inv.diagnostics)
        raise InversionFailed(
            f"minimum_time failed (IPOPT: {status} after {inv.diagnostics['iterations']} iterations, constraint "
            f"violation {viol:.3g}); try more iterations (max_iter), another initial duration (a reference of a "
            f"feasible duration) or hessian='exact'; the last iterate is in exc.partial{model_limit}", partial=inv,
            diagnostics=inv.diagnostics)
    check_between_nodes(inv, rb, None, f"minimum_time ({sch.name} N={N})", chk)
    return inv


class MinimumTimeSolver:
    """:func:`minimum_time` held for re-solves: the plan, the setup, the transcription and the last
    solution (its interior bound points and multipliers) are kept, and :meth:`solve` starts IPOPT
    from that primal-dual point (no exact inverse, no duration estimate).  The model, reference and
    options are fixed at construction; ``bounds`` (values), ``energy`` and ``duration`` may change
    from one solve to the next.

    >>> held = MinimumTimeSolver(model, reference, bounds=Bounds(u=1.0), N=100)
    >>> inv = held.solve(); inv = held.solve(bounds=Bounds(u=1.2))
    """

    def __init__(self, model, reference, *, bounds=None, energy: float = 0.0, duration=None, **options):
        self.model, self.reference, self.options = model, reference, options
        self.problem = {"bounds": bounds, "energy": energy, "duration": duration}
        self._held: dict = {}

    def solve(self, **problem):
        """The optimum for these ``bounds``, ``energy``, ``duration`` (default: the last ones), as
        :func:`minimum_time` returns it (``diagnostics["held"]``: started from the last solution)."""
        unknown = set(problem) - set(self.problem)
        if unknown:
            raise OptionError(f"MinimumTimeSolver.solve: {', '.join(sorted(unknown))} cannot change between solves "
                              f"(only {', '.join(self.problem)}); build another MinimumTimeSolver")
        self.problem.update(problem)
        return _minimum_time(self._held, self.model, self.reference, **self.problem, **self.options)


def _refined(model, reference, opts, problem, warm_start):
    """:func:`minimum_time` on meshes of growing N (each warm-started from the last) until the forward
    check of the retimed reference is below ``tol``; ``diagnostics["meshes"]`` lists them."""
    import math
    import sys

    from ..errors import check_interrupt
    from .schemes import get_scheme
    from .verify import forward_check

    disc = opts.discretization
    if disc.mesh is not None:
        raise OptionError("minimum_time: tol refines the default mesh by raising N; it cannot refine a given mesh")
    if problem["objective"] is not None:
        raise OptionError("minimum_time: tol measures exact tracking; with an objective (relaxed servo constraint) "
                          "the output error is part of the optimum: give N instead")
    tol, order = disc.tol, get_scheme(disc.scheme).order
    meshes, inv, N = [], warm_start, int(disc.N)
    for it in range(disc.max_refinements + 1):
        check_interrupt()
        inv = minimum_time(model, reference, discretization=replace(disc, tol=None, N=N), solver=opts.solver,
                           warm_start=inv, **problem)
        ft = inv.diagnostics["free_time"]
        fc = forward_check(model, inv, retime(reference, ft["duration"]), **dict(disc.forward_options or {}))
        meshes.append({"N": N, "error": fc["error"], "duration": ft["duration"],
                       "iterations": inv.diagnostics["iterations"], "solve_s": inv.diagnostics["solve_s"]})
        if opts.solver.progress:
            print(f"  refinement {it}: N = {N}, duration {ft['duration']:.6g} s, forward-check error "
                  f"{fc['error']:.3e} (tol {tol:.1e})", file=sys.stderr)
        if fc["error"] <= tol:
            inv.diagnostics.update({"meshes": meshes, "max_output_error": fc["error"], "tol": tol})
            return inv
        if N >= disc.max_N:
            break
        N = min(disc.max_N, int(math.ceil(N * min(4.0, max(1.5, 1.2 * (fc["error"] / tol) ** (1.0 / order))))))
    tried = ", ".join(f"N={m['N']}: {m['error']:.2g} (duration {m['duration']:.6g} s)" for m in meshes)
    raise InversionFailed(
        f"minimum_time: mesh refinement did not reach the output error {tol:.2g}; meshes tried (forward-check "
        f"error): {tried}; raise max_refinements/max_N or use a higher-order scheme", partial=inv,
        diagnostics={"meshes": meshes})


class _Retimed:
    """An inverse of one duration read at the same shape positions of another (the mesh ``src`` of
    the first corresponds node by node to ``dst``; within intervals the map is affine)."""

    def __init__(self, inverse, src, dst):
        self.inverse, self.src, self.dst = inverse, np.asarray(src, float), np.asarray(dst, float)

    def X(self, t):
        return self.inverse.X(np.interp(np.atleast_1d(np.asarray(t, float)), self.dst, self.src))


def _feasible_duration(inv, servo, reference, theta, rb, tau_ref) -> float:
    """A duration at which the exact inverse of the shape about meets the input (``tau^-2``) and rate
    (``tau^-3``) bounds, estimated from the inverse ``inv`` of duration ``tau_ref``, 5 % longer
    (``tau_ref`` itself when no input or rate is bounded)."""
    _ts, X, _tr, U = constraint_points(inv, servo, reference, theta)
    ub = servo.layout.blocks["u"]
    factor = None
    for i in rb.bounded:
        if ub.start <= i < ub.stop:
            need = max(np.max(X[i]) / rb.hi[i] if rb.hi[i] > 0 else 0.0,
                       np.min(X[i]) / rb.lo[i] if rb.lo[i] < 0 else 0.0)
            factor = max(factor or 0.0, need ** 0.5)
    for j in rb.rated:
        need = max(np.max(U[j]) / rb.rate_hi[j] if rb.rate_hi[j] > 0 else 0.0,
                   np.min(U[j]) / rb.rate_lo[j] if rb.rate_lo[j] < 0 else 0.0)
        factor = max(factor or 0.0, need ** (1 / 3))
    if not factor or not np.isfinite(factor):
        return tau_ref
    return tau_ref * factor * 1.05
