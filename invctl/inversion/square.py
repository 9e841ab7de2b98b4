"""The square servo-constraint BVP of 003 (35)-(36) on one mesh: transcription, IPOPT or Newton
(with a time-stretch continuation when the first solve fails), the residual checks, and the
:class:`Inverse` of a solution.  :func:`invctl.inversion.invert` calls it; the bounded and
minimum-time problems use its pieces.
"""
from __future__ import annotations

import time
from typing import Any

import casadi as ca
import numpy as np

from ..errors import InversionFailed, RunInterrupted, WallTimeLimitError, check_interrupt, watch_sigint
from .backends import _TIME_LIMIT, IPOPT_DEFAULTS, IPOPT_SQUARE_DEFAULTS, _newton, _progress_of
from .cache import transcription
from .collocation import start_deferred_compiles
from .options import Options
from .problem import Setup, prepare
from .result import Inverse


def solve_square(model, reference, opts: Options, warm_start: Any = None, setup: Setup | None = None,
                 tr=None, x0=None) -> Inverse:
    """The square (or input-energy underdetermined) servo-constraint BVP on one mesh.

    ``tr``: the transcription to use (a held solver's; default: the cached one); ``x0``: the
    initial decision vector (default: ``warm_start`` or the quasi-static guess on the mesh).
    Pieces missing from the compile cache start compiling in the background when it returns."""
    try:
        return _solve_square(model, reference, opts, warm_start, setup, tr, x0)
    finally:
        start_deferred_compiles()


def _solve_square(model, reference, opts, warm_start, setup, tr, x0) -> Inverse:
    t_all = time.perf_counter()
    disc, slv = opts.discretization, opts.solver
    if setup is None:
        setup = prepare(model, reference, disc, opts.horizon)
    servo, sch, sel, t_mesh = setup.servo, setup.scheme, setup.selection, setup.t_mesh
    N = t_mesh.size - 1
    under = setup.underdetermined
    if opts.objective is not None:
        weight = opts.objective.energy
    else:
        weight = 1.0 if under else 0.0
    t_build = time.perf_counter()
    if tr is None:
        tr = transcription(servo, sel, sch, N, weight, compiled=disc.compiled if not under else False)
    build_s = setup.timings["build_s"] + time.perf_counter() - t_build
    tc = tr.collocation_times(t_mesh)
    if x0 is not None:
        pass
    elif warm_start is not None:
        x0 = tr.pack(warm_start.X(t_mesh), warm_start.X(tc) if tc.size else None)
    else:
        x0 = tr.pack(setup.initial_guess(t_mesh), setup.initial_guess(tc) if tc.size else None)
    theta = model.theta_values
    Y = servo.reference_samples(reference, tr.sample_times(t_mesh))
    p = tr.parameters(t_mesh, Y, theta, setup.E0, setup.Ef)
    label = f"{sch.name} N={N}"
    kw = dict(backend=slv.backend, ipopt_options=slv.ipopt_options, max_iter=slv.max_iter,
              max_wall_time=slv.max_wall_time, newton_tol=slv.newton_tol, progress=slv.progress, label=label,
              square=not under)
    x, info, solve_s, build_solver_s = _solve(tr, x0, p, **kw)
    build_s += build_solver_s
    cont_info = None
    if (not info["success"] and slv.continuation and warm_start is None and setup.guess is not None
            and info["status"] not in _TIME_LIMIT):
        x, info, cont_info = _continuation(reference, tr, servo, t_mesh, x0, setup.E0, setup.Ef, theta, **kw)
        solve_s += cont_info.pop("solve_s")
    Xmesh, Xcol = tr.unpack(x)
    inv = make_inverse(model, reference, servo, sch, t_mesh, Xmesh, Xcol, theta, tr=tr)
    res = residuals(inv, servo, reference, theta, tr=tr)
    inv.diagnostics.update(info)
    inv.diagnostics.update({
        "backend": slv.backend, "scheme": sch.name, "N": int(N), "formulation": disc.formulation,
        "omega": disc.omega, "build_s": build_s, "solve_s": solve_s, "guess_s": setup.timings["guess_s"],
        "unknowns": tr.nX, "equations": tr.ng, "selection": sel.describe(), "T0": setup.T0, "Tf": setup.Tf,
        "residuals": res, "continuation": cont_info, "compiled": tr.compiled,
        "compiled_pieces": list(tr.compiled_pieces), "dichotomy": setup.dichotomy,
        "plan": None if setup.plan is None else setup.plan.to_dict(), "mesh": setup.mesh_kind,
        "wall_s": time.perf_counter() - t_all,
    })
    if not info["success"] and info["status"] in _TIME_LIMIT:
        raise WallTimeLimitError(
            f"stable inversion stopped at the wall-time limit of {slv.max_wall_time:g} s after {info['iterations']} "
            f"iterations ({slv.backend}, {label}, max constraint violation "
            f"{info.get('max_constraint_violation', float('nan')):.3g}); raise max_wall_time (invert(..., "
            "max_wall_time=...) or the scene's Tracking(inversion={'max_wall_time': ...})) or use fewer intervals "
            "(N); the last iterate is in exc.partial", partial=inv, diagnostics=inv.diagnostics)
    if not info["success"]:
        raise InversionFailed(
            f"stable inversion failed ({slv.backend}: {info['status']} after {info['iterations']} iterations, "
            f"max constraint violation {info.get('max_constraint_violation', float('nan')):.3g}) on {label}. "
            "Try a finer mesh (N), a longer horizon, warm_start from a coarser solution, more iterations "
            "(max_iter) or another boundary selection; the last iterate is in exc.partial",
            partial=inv, diagnostics=inv.diagnostics)
    if res["position_mesh"] > slv.residual_tol:
        raise InversionFailed(
            f"the solution violates the position-level constraints g = 0, h = y_ref by "
            f"{res['position_mesh']:.3g} > residual_tol = {slv.residual_tol:.3g} at the mesh ({label}); refine the "
            "mesh or check the boundary selection (drift modes must be fixed)", partial=inv,
            diagnostics=inv.diagnostics)
    return inv


def _solve(tr, x0, p, *, backend, ipopt_options, max_iter, max_wall_time, newton_tol, progress, label, square,
           lam_g0=None, assembled_jacobian=True):
    t0 = time.perf_counter()
    if backend == "newton":
        if not square:
            raise ValueError("backend='newton' needs a square system (2n+l+p+m boundary conditions)")
        tr.evaluators()
        build = time.perf_counter() - t0
        t1 = time.perf_counter()
        x, info = _newton(tr, x0, p, max_iter=max_iter, max_wall_time=max_wall_time, tol=newton_tol,
                          progress=progress, label=label)
        return x, info, time.perf_counter() - t1, build
    if backend != "ipopt":
        raise ValueError(f"backend must be 'ipopt' or 'newton', got {backend!r}")
    opts: dict[str, Any] = dict(IPOPT_DEFAULTS)
    opts["ipopt.max_iter"] = int(max_iter)
    opts["ipopt.max_wall_time"] = float(max_wall_time)
    if square:
        # square system: the primal step solves J dx = -g whatever the Hessian (exact zero Hessian,
        # Transcription.ipopt); without bounds the barrier parameter plays no role
        opts.update(IPOPT_SQUARE_DEFAULTS)
    opts.update(ipopt_options or {})
    if progress:
        opts["iteration_callback"] = _progress_of(tr, label)
    zero_hessian = (square and assembled_jacobian
                    and opts.get("ipopt.hessian_approximation", "exact") == "exact")
    solver = tr.ipopt(opts, assembled_jacobian=assembled_jacobian, zero_hessian=zero_hessian)
    build = time.perf_counter() - t0
    t1 = time.perf_counter()
    args = {"x0": x0, "p": p, "lbg": 0, "ubg": 0}
    if lam_g0 is not None:
        args["lam_g0"] = lam_g0
    check_interrupt()
    with watch_sigint() as sigint:  # Ctrl-C inside IPOPT ends as User_Requested_Stop: an interruption
        try:
            sol = solver(**args)
        except RuntimeError as exc:  # a Ctrl-C caught in a Python callback (progress) aborts the call
            if not sigint.seen:
                raise
            raise RunInterrupted(f"interrupted during the IPOPT solve on {label}",
                                 diagnostics={"solver": str(exc).splitlines()[-1][:200]}) from None
    solve_s = time.perf_counter() - t1
    st = solver.stats()
    if sigint.seen and not st.get("success", False):
        raise RunInterrupted(f"interrupted during the IPOPT solve on {label} after {st.get('iter_count', '?')} "
                             "iterations", diagnostics={"status": st.get("return_status", "?"),
                                                        "iterations": int(st.get("iter_count", -1))})
    g = np.array(sol["g"]).ravel()
    viol = float(np.max(np.abs(g))) if g.size else 0.0
    ok = bool(st.get("success", False)) or (st.get("return_status") == "Solved_To_Acceptable_Level" and viol < 1e-8)
    info = {"status": st.get("return_status", "?"), "iterations": int(st.get("iter_count", -1)),
            "success": ok, "max_constraint_violation": viol}
    return np.array(sol["x"]).ravel(), info, solve_s, build


def _continuation(reference, tr, servo, t_mesh, x0, E0, Ef, theta, **kw):
    """Homotopy from the quasi-static problem: reference samples scaled in time
    (slower transition, s -> 1), each step warm-started from the last."""
    from ..reference import Reference

    steps = []
    x = x0
    total = 0.0
    info = {"success": False, "status": "not run", "iterations": 0}
    for stretch in (4.0, 2.0, 1.4, 1.0):
        t = reference.t
        tc = reference.t0
        slow = ca.substitute(reference.expr, t, tc + (t - tc) / stretch)
        ref_s = Reference(t, slow, reference.t0, reference.t0 + stretch * (reference.tf - reference.t0),
                          reference.smoothness, reference.name)
        Y = servo.reference_samples(ref_s, tr.sample_times(t_mesh))
        p = tr.parameters(t_mesh, Y, theta, E0, Ef)
        x, info, s, _ = _solve(tr, x, p, **kw)
        total += s
        steps.append({"stretch": stretch, "status": info["status"], "iterations": info["iterations"]})
        if not info["success"]:
            break
    return x, info, {"steps": steps, "solve_s": total}


def make_inverse(model, reference, servo, sch, t_mesh, Xmesh, Xcol, theta, dX=None, tr=None) -> Inverse:
    """The :class:`Inverse` of a solution on ``t_mesh`` (slopes ``dX`` at the mesh for
    Hermite-Simpson: ``F`` of the servo model unless given, through the transcription ``tr``'s
    compiled right-hand side when given)."""
    if dX is None:
        rhs = servo.maps.mapped(servo.rhs, t_mesh.size) if tr is None else tr.mapped_call("rhs", t_mesh.size)
        dX = sch.mesh_slopes(Xmesh, lambda: rhs(Xmesh, servo.reference_samples(reference, t_mesh), theta)[0])
    L = servo.layout
    return Inverse(sch.name, t_mesh, Xmesh, dX, Xcol, {"n": L.n, "l": L.l, "p": L.p, "m": L.m},
                   reference.t0, reference.tf, {k: list(v) for k, v in servo.names.items()}, {}, y_ref_fn=reference)


def residuals(inv: Inverse, servo, reference, theta, samples_per_interval: int = 4, tr=None) -> dict:
    """Constraint residuals of (35) at the mesh and between mesh points: ``position``
    (``g`` and ``h - y_ref`` together), ``holonomic`` (``g``), ``servo`` (``h - y_ref``),
    ``velocity`` and ``acceleration`` levels.  One mapped evaluation at all points (the
    transcription ``tr``'s compiled one when given)."""
    tm = inv.t_mesh
    s = np.linspace(0, 1, samples_per_interval + 1)[1:-1]
    tt = (tm[:-1, None] + np.diff(tm)[:, None] * s[None, :]).ravel()
    t = np.concatenate([tm, tt])
    fn = servo.maps.mapped(servo.residuals, t.size) if tr is None else tr.mapped_call("residuals", t.size)
    pos, vel, acc = (np.array(r) for r in fn(inv.X(t), servo.reference_samples(reference, t), theta))
    nl, k = servo.layout.l, tm.size
    out = {}
    for name, part in (("mesh", slice(0, k)), ("between", slice(k, None))):
        p, v, a = pos[:, part], vel[:, part], acc[:, part]
        out[f"position_{name}"] = float(np.max(np.abs(p))) if p.size else 0.0
        out[f"holonomic_{name}"] = float(np.max(np.abs(p[:nl]))) if nl and p.size else 0.0
        out[f"servo_{name}"] = float(np.max(np.abs(p[nl:]))) if p[nl:].size else 0.0
        out[f"velocity_{name}"] = float(np.max(np.abs(v))) if v.size else 0.0
        out[f"acceleration_{name}"] = float(np.max(np.abs(a))) if a.size else 0.0
    out["position"] = max(out["position_mesh"], out["position_between"])
    return out
