"""Bounded inversion: exact tracking when the exact inverse respects the bounds, least-squares
tracking with the servo constraint relaxed when it does not (:mod:`invctl.inversion.ocp`).

1. The exact (square) inverse is computed on the horizon of the automatic setup and checked
   against the bounds on its interpolant (:func:`between_nodes`).  If it satisfies
   them, it *is* the answer (``diagnostics["tracking"]["exact"]``; the margins are reported).
2. Otherwise the relaxed problem is solved from it (IPOPT): the inputs are free, the output
   error is minimized in the least-squares sense with the user's :class:`Objective` weights.
   A pre-/post-actuation bound shorter than the setup needs makes the inverse start/end at
   rest at the shortened ``T0``/``Tf`` (every entry of ``X`` fixed to the equilibrium).
3. The report (``diagnostics["bounds"]``) lists every active bound, the time intervals where it
   is active, the exact inverse's excursion beyond it, and the sensitivity of the optimal
   objective to relaxing it (the sum of its multipliers); ``diagnostics["tracking"]`` holds
   the output error all bounds together cost (largest, RMS, per output).
4. If IPOPT finds the bounds infeasible, the elastic problem (every bound relaxed by a
   nonnegative amount, the scaled sum minimized) gives the closest feasible relaxation, and
   :class:`~invctl.errors.InfeasibleBoundsError` reports it.
5. The bounds hold on the whole returned trajectory, not only at the nodes: the problem bounds
   the Bezier control points of every interval's cubic (Hermite-Simpson; Legendre/Radau: solved
   again with the Bernstein coefficients bounded when their polynomials leave a bound between the
   collocation points; :mod:`invctl.inversion.ocp`), and
   the result is checked at :data:`CHECK_SAMPLES` points per interval
   (``diagnostics["bounds"]["max_violation_between_nodes"]``); a violation beyond
   :data:`ACTIVE_TOL` (relative) raises :class:`~invctl.errors.InversionFailed`.
"""
from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np

from ..errors import (InfeasibleBoundsError, InversionFailed, OptionError, RunInterrupted, WallTimeLimitError,
                      watch_sigint)
from .backends import _TIME_LIMIT, IPOPT_DEFAULTS
from .cache import ocp_transcription, servo_model
from .ocp import slack_scale
from .options import Objective, Options
from .problem import prepare, resolve_plan
from .solver import structure_change

#: IPOPT options of the bounded problems: the adaptive barrier update (measured on the manipulator, |u2| <= 6 ... 9 N,
#: HS N = 20, 40, 100, Gauss-Newton: 17-31 iterations, monotone 18-29; minimum time, exact Hessian, five
#: test problems: 9-25 iterations, monotone 14-32) ...
IPOPT_BOUNDED_DEFAULTS = {"ipopt.mu_strategy": "adaptive"}
#: ... except with the exact Hessian on a fixed duration (hessian="exact" in invert): the monotone one. With the
#: adaptive update the exact Hessian's first steps (after the barrier parameter rose to ~4) go far beyond the
#: region where the defects are near linear and IPOPT stalls in tiny steps: |u2| <= 8 N, HS N = 20, bounded and
#: elastic problems at max_iter; monotone: 20 iterations (N = 40, 100: 18, 22 against 24, 24; |u2| <= 6, 7, 9 N,
#: N = 20, 40: 15-21 against 14-31)
IPOPT_EXACT_HESSIAN_DEFAULTS = {"ipopt.mu_strategy": "monotone"}
#: distance (relative to max(1, |bound|)) within which a bound counts as active
ACTIVE_TOL = 1e-6
#: weight of the least-squares tracking in the elastic problem (relaxations weigh 1/|bound|): small,
#: so that the smallest relaxation wins, large enough to keep the Gauss-Newton steps regular
ELASTIC_EPS = 1e-3
#: most re-solves of minimum time with the interior bound points moved to the extrema of the polynomials
EXTREMA_ROUNDS = 8
#: points per mesh interval where :func:`between_nodes` checks the bounds on the returned trajectory
CHECK_SAMPLES = 20
#: statuses meaning "IPOPT believes the constraints cannot be satisfied"
INFEASIBLE = ("Infeasible_Problem_Detected", "Restoration_Failed", "Local_Infeasibility",
              "Not_Enough_Degrees_Of_Freedom")


def constraint_points(inv, servo, reference, theta):
    """``(t_states, X, t_rates, U')`` where the bounded problem imposes its bounds (:meth:`Scheme.bound_points`)."""
    return inv._scheme.bound_points(inv, servo.rhs, lambda t: servo.reference_samples(reference, t), theta,
                                    servo.layout.blocks["u"])


def between_nodes(inv, rb, reference=None, samples: int = CHECK_SAMPLES) -> dict:
    """The bounds checked on the trajectory the user gets (:meth:`Inverse.X`, :meth:`Inverse.dX`
    sampled at ``samples`` points per mesh interval and at the interior extrema of every interval's
    polynomial, so that the largest values are exact, and the pre-/post-actuation of ``reference``):
    ``margins`` (smallest distance to each bound, negative: violated), the largest violation (0
    when every bound holds), the bound and time where it occurs."""
    tm = inv.t_mesh
    s = np.arange(samples) / samples
    grid = np.concatenate([(tm[:-1, None] + np.diff(tm)[:, None] * s[None, :]).ravel(), [tm[-1]]])
    ub = inv._slice("u").start
    margins, when = {}, {}
    for labels, lo, hi, idx, rate in ((rb.labels, rb.lo, rb.hi, rb.bounded, False),
                                      (rb.rate_labels, rb.rate_lo, rb.rate_hi, rb.rated, True)):
        for i in idx:
            row = ub + i if rate else i
            t = np.concatenate([grid, inv.extrema(row, derivative=rate)])
            v = (inv.dX(t) if rate else inv.X(t))[row]
            m = np.minimum(hi[i] - v, v - lo[i])
            k = int(np.argmin(m))
            margins[labels[i]], when[labels[i]] = float(m[k]), float(t[k])
    if reference is not None:
        for name, need in (("max_pre_actuation", reference.t0 - inv.T0), ("max_post_actuation", inv.Tf - reference.tf)):
            if getattr(rb, name) is not None:
                margins[name] = float(getattr(rb, name) - need)
                when[name] = inv.T0 if name == "max_pre_actuation" else inv.Tf
    worst = min(margins, key=margins.__getitem__, default=None)
    bad = worst is not None and margins[worst] < 0
    return {"max_violation_between_nodes": float(-margins[worst]) if bad else 0.0,
            "max_violation_bound": worst if bad else None, "t_max_violation": when[worst] if bad else None,
            "samples_per_interval": int(samples), "margins": margins}


def check_between_nodes(inv, rb, reference, where: str, chk=None) -> dict:
    """:func:`between_nodes` of a solution (``chk``: already computed, without ``reference``), stored in
    ``diagnostics["bounds"]``; raises :class:`InversionFailed` (``exc.partial`` the solution) when a
    bound is violated beyond :data:`ACTIVE_TOL` (relative to the bound)."""
    chk = dict(between_nodes(inv, rb, reference) if chk is None else chk)
    chk.pop("margins")
    inv.diagnostics.setdefault("bounds", {}).update(chk)
    if _beyond_tolerance(rb, chk):
        label = chk["max_violation_bound"]
        hint = ("rate bounds hold between the collocation points with scheme='hermite-simpson' only; use it"
                if label in rb.rate_labels and not inv._scheme.rates_between_nodes else "try a finer mesh (N) or more iterations "
                "(max_iter)")
        inv.diagnostics["success"] = False
        raise InversionFailed(
            f"{where}: the solution violates the bound on {label} by {chk['max_violation_between_nodes']:.3g} at "
            f"t = {chk['t_max_violation']:.6g} s on the returned trajectory (checked at {chk['samples_per_interval']} "
            f"points per mesh interval); {hint}; the solution is in exc.partial", partial=inv,
            diagnostics=inv.diagnostics)
    return chk


def _beyond_tolerance(rb, chk) -> bool:
    label = chk["max_violation_bound"]
    return label is not None and chk["max_violation_between_nodes"] > ACTIVE_TOL * max(1.0, _bound_size(rb, label))


def _intervals(times, spacing):
    """Merge sorted times into intervals (gaps larger than 1.5 local spacings split)."""
    times = np.sort(np.asarray(times, float))
    if times.size == 0:
        return []
    out, a, b = [], times[0], times[0]
    for t in times[1:]:
        if t - b <= 1.5 * spacing(b):
            b = t
        else:
            out.append([float(a), float(b)])
            a = b = t
    out.append([float(a), float(b)])
    return out


def _bound_rows(tr, rb, t_mesh):
    """Every bounded quantity of the transcription: ``(label, lo, hi, time, source, index)`` with
    ``source`` "x" (a decision variable) or "g" (a constraint row)."""
    rows = []
    nx, N = tr.nx, tr.N
    tc = tr.collocation_times(t_mesh)
    if not tr.elastic:
        for i in rb.bounded:
            for k in range(N + 1):
                rows.append((rb.labels[i], rb.lo[i], rb.hi[i], t_mesh[k], "x", k * nx + i))
            for k in range(tr.n_col):
                rows.append((rb.labels[i], rb.lo[i], rb.hi[i], tc[k], "x", nx * (N + 1) + k * nx + i))
    times = tr.row_times(t_mesh)
    base = tr.n_defect + tr.n_bc
    for q, (r, t) in enumerate(zip(tr.path_rows, times)):
        if r.kind == "X":
            rows.append((rb.labels[r.entry], rb.lo[r.entry], rb.hi[r.entry], t, "g", base + q))
        else:
            rows.append((rb.rate_labels[r.entry], rb.rate_lo[r.entry], rb.rate_hi[r.entry], t, "g", base + q))
    return rows


def _limits(tr, rb, tau_range=None):
    """``lbx, ubx, lbg, ubg`` of a (non-elastic or elastic) bounded transcription."""
    lbx, ubx = np.full(tr.nX, -np.inf), np.full(tr.nX, np.inf)
    lbg, ubg = np.zeros(tr.ng), np.zeros(tr.ng)
    nx, N = tr.nx, tr.N
    if not tr.elastic:
        for i in rb.bounded:
            for start, count in ((i, N + 1), (nx * (N + 1) + i, tr.n_col)):
                sl = slice(start, start + nx * count, nx)
                lbx[sl], ubx[sl] = rb.lo[i], rb.hi[i]
    if tr.free_time:
        lbx[tr.i_tau], ubx[tr.i_tau] = tau_range
    if tr.nr:
        lbx[tr.i_r:], ubx[tr.i_r:] = 0.0, np.inf
    base = tr.n_defect + tr.n_bc
    lo = np.array([rb.lo[r.entry] if r.kind == "X" else rb.rate_lo[r.entry] for r in tr.path_rows])
    hi = np.array([rb.hi[r.entry] if r.kind == "X" else rb.rate_hi[r.entry] for r in tr.path_rows])
    n = len(tr.path_rows)
    if tr.elastic:  # first copy: value - r_up <= hi; second: value + r_lo >= lo
        lbg[base:base + n], ubg[base:base + n] = -np.inf, hi
        lbg[base + n:base + 2 * n], ubg[base + n:base + 2 * n] = lo, np.inf
    else:
        lbg[base:base + n], ubg[base:base + n] = lo, hi
    return lbx, ubx, lbg, ubg


def active_bounds(tr, rb, t_mesh, x, lam_x, lam_g, g, *, exact_margins=None) -> list[dict]:
    """The active bounds of a solution (module doc, item 3), largest sensitivity first."""
    spacing_t = np.asarray(t_mesh, float)
    h = np.diff(spacing_t)

    def spacing(t):
        k = int(np.clip(np.searchsorted(spacing_t, t) - 1, 0, h.size - 1))
        return h[k]

    groups: dict = {}
    for label, lo, hi, t, src, idx in _bound_rows(tr, rb, t_mesh):
        val = x[idx] if src == "x" else g[idx]
        lam = lam_x[idx] if src == "x" else lam_g[idx]
        for side, b in (("lower", lo), ("upper", hi)):
            if not math.isfinite(b) or abs(val - b) > ACTIVE_TOL * max(1.0, abs(b)):
                continue
            e = groups.setdefault((label, side), {"bound": label, "side": side, "value": float(b), "times": [],
                                                  "sensitivity": 0.0, "peak_multiplier": 0.0})
            e["times"].append(float(t))
            e["sensitivity"] += abs(float(lam))
            e["peak_multiplier"] = max(e["peak_multiplier"], abs(float(lam)))
    out = []
    for e in groups.values():
        e["intervals"] = _intervals(e.pop("times"), spacing)
        e["points"] = sum(1 for _ in e["intervals"])
        if exact_margins is not None and e["bound"] in exact_margins:
            e["exact_inverse_excess"] = max(0.0, -exact_margins[e["bound"]])
        out.append(e)
    return sorted(out, key=lambda e: -e["sensitivity"])


def output_error(inv, servo, reference, theta, samples_per_interval: int = 8) -> dict:
    """``e = h(q) - y_ref`` of an inverse on ``[T0, Tf]``: largest per output and overall,
    RMS over the horizon, and where the largest occurs."""
    tm = inv.t_mesh
    s = np.linspace(0.0, 1.0, samples_per_interval, endpoint=False)
    t = np.concatenate([(tm[:-1, None] + np.diff(tm)[:, None] * s[None, :]).ravel(), [tm[-1]]])
    X = inv.X(t)
    Ys = servo.reference_samples(reference, t)
    e = np.array(servo.maps.mapped(servo.output, t.size)(X, Ys, theta)) - Ys[:reference.m]
    ea = np.abs(e)
    k = int(np.argmax(np.max(ea, axis=0)))
    rms = np.sqrt(np.trapezoid(e * e, t, axis=1) / (t[-1] - t[0]))
    names = list(servo.model.y_names)
    return {"max": float(ea.max()), "t_max": float(t[k]), "rms": float(np.sqrt(np.mean(rms ** 2))),
            "by_output": {nm: {"max": float(ea[i].max()), "rms": float(rms[i])} for i, nm in enumerate(names)}}


#: IPOPT options of a solve started from a nearby solution's primal and dual point (barrier parameter small,
#: the start not pushed into the interior): a minimum-time re-solve with the interior points moved to the
#: extrema takes 4 iterations instead of 14 from the primal point alone (cart-pole, |F| <= 1 N, HS N = 100)
IPOPT_WARM = {"ipopt.warm_start_init_point": "yes", "ipopt.warm_start_bound_push": 1e-9,
              "ipopt.warm_start_mult_bound_push": 1e-9, "ipopt.mu_init": 1e-9}


#: regularization of the predictor's KKT system (Hessian block, constraint block): degenerate active sets (a plateau
#: at a bound makes mesh, control-point and rate rows dependent) have a step only with it
REG_W, REG_C = 1e-8, 1e-8
#: most active-set corrections of the predicted start
PREDICTOR_ROUNDS = 10


def _csc(tr, name, M):
    """A sparse CasADi DM as a scipy CSC matrix, its pattern (``name``: which output) kept on ``tr``."""
    import scipy.sparse as sps

    patterns = tr.__dict__.setdefault("_csc_patterns", {})
    if name not in patterns:
        sp = M.sparsity()
        patterns[name] = (np.array(sp.row(), np.int32), np.array(sp.colind(), np.int32))
    return sps.csc_matrix((np.array(M.nonzeros()), *patterns[name]), shape=M.shape)


def predicted_start(tr, p, x, lam_x, lam_g, old, new):
    """The start of a held re-solve after a bound or parameter change: the Newton step (Gauss-Newton Hessian) on
    the optimality conditions of the last optimum ``(x, lam_x, lam_g)`` at the parameters ``p``, its active bounds
    moved to their values in ``new`` (``old``, ``new``: ``(lbx, ubx, lbg, ubg)``); bounds the linearized step
    violates join the active set and bounds whose multiplier changes sign leave it, until neither happens.  Started
    at the last optimum itself, IPOPT spends its first iterations in steps cut short at the moved bounds.
    Returns ``(x0, lam_x0, lam_g0)``, or ``None`` when the step is not defined."""
    import scipy.sparse as sps
    from scipy.sparse.linalg import splu

    x, lam_x, lam_g = (np.asarray(v, float).ravel() for v in (x, lam_x, lam_g))
    n, ng = x.size, lam_g.size
    g = np.array(tr.g_function()(x, p)).ravel()
    C = sps.vstack([_csc(tr, "jac_g", tr._jac_g(x, p, g)[0]), sps.identity(n)], format="csr")  # rows: g, then x
    v, lam = np.concatenate([g, x]), np.concatenate([lam_g, lam_x])
    lo0, hi0 = np.concatenate([old[2], old[0]]), np.concatenate([old[3], old[1]])
    lo, hi = np.concatenate([new[2], new[0]]), np.concatenate([new[3], new[1]])
    Hu = _csc(tr, "hess_gn", tr._hess_gn(x, p, 1.0, lam_g))
    H = Hu + Hu.T - sps.diags(Hu.diagonal()) + REG_W * sps.identity(n)
    stationarity = -(np.array(tr._grad_f(x, p)[1]).ravel() + C.T @ lam)
    tol = ACTIVE_TOL * np.maximum(1.0, np.minimum(np.abs(lo0), np.abs(hi0)))
    eq = lo == hi
    # held at hi (equalities: lo = hi) or lo: active at the last optimum, or beyond a moved bound there
    upper = eq | (((np.abs(v - hi0) <= tol) & (lam >= 0)) | (v > hi + tol)) & np.isfinite(hi)
    lower = ~upper & (((np.abs(v - lo0) <= tol) & (lam <= 0)) | (v < lo - tol)) & np.isfinite(lo)
    for _ in range(PREDICTOR_ROUNDS):
        rows = np.flatnonzero(upper | lower)
        A = C[rows]
        K = sps.bmat([[H, A.T], [A, -REG_C * sps.identity(rows.size)]], format="csc")
        rhs = np.concatenate([stationarity, np.where(upper[rows], hi[rows], lo[rows]) - v[rows]])
        try:
            step = splu(K).solve(rhs)
        except RuntimeError:  # singular
            return None
        if not np.all(np.isfinite(step)):
            return None
        new_lam = lam.copy()
        new_lam[rows] += step[n:]
        v_lin = v + C @ step[:n]
        leave = ~eq & ((upper & (new_lam < 0)) | (lower & (new_lam > 0)))
        join_hi = ~(upper | lower) & (v_lin > hi + tol)
        join_lo = ~(upper | lower) & (v_lin < lo - tol)
        if not (leave.any() or join_hi.any() or join_lo.any()):
            break
        upper, lower = (upper & ~leave) | join_hi, (lower & ~leave) | join_lo
    new_lam[~(upper | lower)] = 0.0
    return x + step[:n], new_lam[ng:], new_lam[:ng]


def solve_scaled(tr, slv, x0, params, limits, *, hessian: str, scale: float = 1e3, warm=None):
    """Solve with the objective scaled by ``scale``; when the optimal scaled objective is below
    1e-2 (tiny output errors), solve again warm-started with the objective scaled to 1, so that
    the multipliers are large against IPOPT's final barrier parameter and active bounds are
    met to ~1e-9 instead of ~1e-5 (measured on the manipulator, u2 <= 8).

    ``warm``: the multipliers ``(lam_x, lam_g)`` of a nearby solution (same transcription and
    ``scale``) to start from (:data:`IPOPT_WARM`); if that solve does not succeed, it is solved
    again from ``x0`` alone.

    Returns ``(solution, stats, scale)``; ``stats["iterations"]`` counts every solve."""
    lbx, ubx, lbg, ubg = limits
    opts = _ipopt_options(slv, hessian, tr.free_time)
    if slv.progress:
        opts["iteration_callback"] = _progress(tr)
    spent = 0
    if warm is not None:
        solver = tr.ipopt(dict(opts, **IPOPT_WARM), hessian=hessian)
        with watch_sigint() as sigint:
            sol = solver(x0=x0, lam_x0=warm[0], lam_g0=warm[1], p=params(scale), lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg)
        st = dict(solver.stats())
        _interrupted(sigint, st, tr)
    if warm is None or not st.get("success"):
        spent = int(st.get("iter_count", 0)) if warm is not None else 0
        solver = tr.ipopt(opts, hessian=hessian)
        with watch_sigint() as sigint:  # Ctrl-C inside IPOPT ends as User_Requested_Stop: an interruption
            sol = solver(x0=x0, p=params(scale), lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg)
        st = dict(solver.stats())
        _interrupted(sigint, st, tr)
    st["iterations"] = spent + int(st.get("iter_count", -1))
    f = float(sol["f"]) / scale
    inequalities = bool(tr.bounded or tr.rated)  # without them there is nothing to sharpen
    if (inequalities and st.get("success") and 0 < f * scale < 1e-2
            and "ipopt.obj_scaling_factor" not in (slv.ipopt_options or {})):
        s2 = min(1.0 / f, 1e9)
        solver2 = tr.ipopt(dict(opts, **IPOPT_WARM, **{"ipopt.max_iter": min(int(opts["ipopt.max_iter"]), 50)}),
                           hessian=hessian)
        k = s2 / scale
        with watch_sigint() as sigint:
            sol2 = solver2(x0=sol["x"], lam_x0=sol["lam_x"] * k, lam_g0=sol["lam_g"] * k, p=params(s2), lbx=lbx,
                           ubx=ubx, lbg=lbg, ubg=ubg)
        st2 = dict(solver2.stats())
        _interrupted(sigint, st2, tr)
        if st2.get("success"):
            st2["iterations"] = st["iterations"] + int(st2.get("iter_count", 0))
            return sol2, st2, s2
    return sol, st, scale


def _interrupted(sigint, st, tr):
    if sigint.seen and not st.get("success", False):
        raise RunInterrupted(f"interrupted during the IPOPT solve of the {'free-time' if tr.free_time else 'bounded'} "
                             f"problem ({tr.scheme.name} N={tr.N}) after {st.get('iter_count', '?')} iterations",
                             diagnostics={"status": st.get("return_status", "?"),
                                          "iterations": int(st.get("iter_count", -1))})


def _progress(tr):
    """IPOPT iteration callback: objective and largest equality violation (defects, boundary rows);
    one per transcription (restarted per solve), so it never makes a cached solver new."""
    import sys

    from .backends import _Progress

    label = f"{tr.scheme.name} N={tr.N} {'free time' if tr.free_time else 'bounded'}"
    cb = getattr(tr, "_progress", None)
    if cb is not None:
        cb.restart(label)
        return cb
    n_eq = tr.n_defect + tr.n_bc

    class OCPProgress(_Progress):
        def eval(self, arg):
            import casadi as ca

            names = ca.nlpsol_out()
            g = np.array(arg[names.index("g")]).ravel()[:n_eq]
            f = float(np.array(arg[names.index("f")]).ravel()[0])
            print(f"  [{self.label}] iter {self.k:3d}  objective {f:.6e}  max|defect| = "
                  f"{np.max(np.abs(g)) if g.size else 0.0:.3e}  ({time.perf_counter() - self.t:.2f} s)",
                  file=sys.stderr, flush=True)
            self.k += 1
            return [0]

    tr._progress = OCPProgress(tr.nX, tr.ng, tr.np, label)
    return tr._progress


def _hessian(slv, auto: str) -> str:
    return auto if slv.hessian == "auto" else slv.hessian


def _ipopt_options(slv, hessian: str, free_time: bool = False):
    """IPOPT options of a bounded (``free_time``: minimum-time) solve with this Hessian; the user's
    ``ipopt_options`` win."""
    opts = dict(IPOPT_DEFAULTS)
    exact = hessian in ("exact", "ad") and not free_time
    opts.update(IPOPT_EXACT_HESSIAN_DEFAULTS if exact else IPOPT_BOUNDED_DEFAULTS)
    opts["ipopt.max_iter"] = int(slv.max_iter)
    opts["ipopt.max_wall_time"] = float(slv.max_wall_time)
    opts.update(slv.ipopt_options or {})
    return opts


def _equilibrium_check(setup, rb):
    """Bounds violated by the entries the boundary conditions fix to the equilibria."""
    bad = []
    for side, idx, E, when in (("start", setup.selection.start, setup.E0, "T0"),
                               ("end", setup.selection.end, setup.Ef, "Tf")):
        for i in idx:
            if E[i] > rb.hi[i] + 1e-12 or E[i] < rb.lo[i] - 1e-12:
                bad.append({"bound": rb.labels[i], "side": "upper" if E[i] > rb.hi[i] else "lower",
                            "value": float(rb.hi[i] if E[i] > rb.hi[i] else rb.lo[i]), "needed": float(E[i]),
                            "where": f"{side} equilibrium (fixed at {when})"})
    return bad


def invert_bounded(model, reference, opts: Options, *, warm_start=None, hold=None, exact_solve=None,
                   plan_result=None):
    """The bounded inversion (module doc); called by :func:`invctl.inversion.invert` with ``bounds``.

    A held solver (:class:`~invctl.inversion.InversionSolver`) passes ``plan_result`` (its re-plan),
    ``exact_solve`` (``(options, warm_start) -> Inverse``: its held square solve, refined to ``tol`` if given)
    and ``hold``, a dict where the last relaxed optimum (transcription, primal-dual point, objective
    scale) is kept: the next relaxed solve on the same structure starts from it (:data:`IPOPT_WARM`)
    and ``hold["info"]`` says what was reused or rebuilt."""
    from .square import make_inverse, residuals, solve_square

    t_all = time.perf_counter()
    disc, slv, hz = opts.discretization, opts.solver, opts.horizon
    objective = opts.objective or Objective()
    if not isinstance(objective, Objective):
        raise OptionError("invert: bounded inversions need an Objective, not a number")
    if opts.bounds is None:
        raise OptionError("invert_bounded: no bounds given; pass bounds=Bounds(...) (or call invert without bounds)")
    servo = servo_model(model, disc.formulation, disc.omega)
    rb = opts.bounds.resolve(servo)
    if plan_result is None:
        plan_result = resolve_plan(model, reference, disc, hz)
    T0p, Tfp = plan_result[0], plan_result[1]
    last: dict = {} if hold is None else (hold.get("last") or {})
    info: dict = {"reused": [], "rebuilt": None}
    if hold is not None:
        hold["info"] = info
    T0, Tf = T0p, Tfp
    rest_start = rb.max_pre_actuation is not None and reference.t0 - T0p > rb.max_pre_actuation + 1e-12
    rest_end = rb.max_post_actuation is not None and Tfp - reference.tf > rb.max_post_actuation + 1e-12
    if rest_start:
        T0 = reference.t0 - rb.max_pre_actuation
    if rest_end:
        Tf = reference.tf + rb.max_post_actuation
    theta = model.theta_values
    # 1. the exact inverse (on the setup's horizon) and its margins
    exact, margins, exact_s = None, None, 0.0
    hz_plan = replace(hz, T0=T0p, Tf=Tfp, start=plan_result[2], end=plan_result[3], plan=plan_result[4],
                      plan_options=None)
    from .boundary import _resolve

    square = len(_resolve("start", plan_result[2], servo)) + len(_resolve("end", plan_result[3], servo)) == \
        servo.layout.nx
    if square and (warm_start is None or not (rest_start or rest_end)):
        t0_ = time.perf_counter()
        exact_opts = replace(opts, horizon=hz_plan, bounds=None, objective=None)
        if exact_solve is not None:
            exact = exact_solve(exact_opts, warm_start)
            if disc.tol is not None:
                disc = replace(disc, tol=None, mesh=None, N=exact.N)
        elif disc.tol is not None:
            from .refine import refine

            exact = refine(model, reference, exact_opts, warm_start,
                           lambda o, ws: solve_square(model, reference, o, ws), servo)
            disc = replace(disc, tol=None, mesh=None, N=exact.N)
        else:
            exact = solve_square(model, reference, exact_opts, warm_start)
        exact_s = time.perf_counter() - t0_
        margins = between_nodes(exact, rb)["margins"]
        if not (rest_start or rest_end) and all(v >= -ACTIVE_TOL * max(1.0, _bound_size(rb, k))
                                                for k, v in margins.items()):
            exact.diagnostics["bounds"] = {"active": [], "margins": margins, "rest": [False, False],
                                           "describe": "exact tracking within the bounds (no bound active)"}
            exact.diagnostics["tracking"] = {"exact": True, "max_output_error": 0.0, "rms_output_error": 0.0}
            check_between_nodes(exact, rb, reference, "bounded inversion")
            if hold is not None:
                hold["last"] = None  # the next relaxed solve starts from its exact inverse, as a fresh one
            return exact
    elif disc.tol is not None:
        raise OptionError("invert: tol (mesh refinement) needs an exact inverse first (a square selection and no "
                          "warm start with a shortened pre-/post-actuation); give N instead")
    # 2. the relaxed problem
    setup = prepare(model, reference, disc, hz, T0=T0, Tf=Tf, rest_start=rest_start, rest_end=rest_end,
                    plan_result=plan_result, any_count=True, ends=last.get("ends"))
    bad = _equilibrium_check(setup, rb)
    if bad:
        worst = bad[0]
        raise InfeasibleBoundsError(
            f"the bounds exclude the equilibrium the boundary conditions fix: {worst['bound']} = "
            f"{worst['needed']:.6g} at the {worst['where']} is outside the {worst['side']} bound "
            f"{worst['value']:.6g}; no trajectory can satisfy them. Relax {worst['bound']} to at least "
            f"{worst['needed']:.6g} (or change the reference's end points)",
            diagnostics={"relaxation": {b["bound"] + ":" + b["side"]: {"bound": b["value"], "needed": b["needed"],
                                                                       "where": b["where"]} for b in bad}})
    sch, t_mesh, N = setup.scheme, setup.t_mesh, setup.t_mesh.size - 1
    t_build = time.perf_counter()
    why = _structure_change(last["tr"], servo, setup.selection, N, rb) if last else None
    held = bool(last) and why is None
    if held:  # the last transcription (Legendre/Radau: with the interior rows if the last solve needed them)
        tr = last["tr"]
        info["reused"].append("transcription")
    else:
        tr = ocp_transcription(servo, setup.selection, sch, N, relaxed=True, bounded=rb.bounded, rated=rb.rated,
                               compiled=disc.compiled)
        info["rebuilt"] = why
    build_s = setup.timings["build_s"] + time.perf_counter() - t_build
    guess = warm_start if warm_start is not None else exact
    tc = tr.collocation_times(t_mesh)
    warm, scale0 = None, 1e3
    if held:  # the last optimum, primal and dual (same layout); another mesh: its states there, the same slacks
        if np.array_equal(last["t_mesh"], t_mesh):
            x0 = last["x"]
        else:
            x0 = np.concatenate([tr.pack(last["inverse"].X(t_mesh), last["inverse"].X(tc) if tc.size else None)
                                 [:tr.nXs], last["x"][tr.nXs:]])
        warm, scale0 = (last["lam_x"], last["lam_g"]), last["scale"]
        info["reused"].append("last optimum (primal-dual)")
    elif guess is not None:
        x0 = tr.pack(guess.X(t_mesh), guess.X(tc) if tc.size else None)
    else:
        x0 = tr.pack(setup.initial_guess(t_mesh), setup.initial_guess(tc) if tc.size else None)
    Y = servo.reference_samples(reference, tr.sample_times(t_mesh))
    c = slack_scale(servo, reference.tf - reference.t0)
    lbx, ubx, lbg, ubg = _limits(tr, rb)

    def params(scale):
        return tr.parameters(t_mesh, Y, theta, setup.E0, setup.Ef, W=objective.output_weights(model),
                             rho=objective.slack, energy=objective.energy, rate=objective.rate, c=c, scale=scale)

    t_solve = time.perf_counter()
    if warm is not None:  # the last optimum moved by the change of bounds or parameters
        predicted = predicted_start(tr, params(scale0), x0, warm[0], warm[1], last["limits"], (lbx, ubx, lbg, ubg))
        if predicted is not None:
            x0, warm = predicted[0], predicted[1:]
            info["reused"].append("predicted start")
    hessian = _hessian(slv, "gauss-newton")

    def run(start, warm=None, scale=1e3):
        sol, st, scale = solve_scaled(tr, slv, start, params, (lbx, ubx, lbg, ubg), hessian=hessian, scale=scale,
                                      warm=warm)
        x, g = np.array(sol["x"]).ravel(), np.array(sol["g"]).ravel()
        viol = _violation(g, lbg, ubg, x, lbx, ubx)
        status = st.get("return_status", "?")
        ok = bool(st.get("success", False)) or (status == "Solved_To_Acceptable_Level" and viol < 1e-8)
        inv = _inverse(tr, servo, reference, sch, t_mesh, x, Y, theta, c, make_inverse)
        return sol, st, scale, x, g, viol, status, ok, inv

    sol, st, scale, x, g, viol, status, ok, inv = run(x0, warm, scale0)
    if ok and tr.interior is None and _beyond_tolerance(rb, between_nodes(inv, rb)):
        # Legendre/Radau: the polynomials leave the bounds between the collocation points; solve again
        # from here with their Bernstein coefficients bounded too (not by default: where no bound
        # needs them they only add rows)
        iterations = st["iterations"]
        tr = ocp_transcription(servo, setup.selection, sch, N, relaxed=True, bounded=rb.bounded, rated=rb.rated,
                               interior="hull", compiled=disc.compiled)
        lbx, ubx, lbg, ubg = _limits(tr, rb)
        sol, st, scale, x, g, viol, status, ok, inv = run(x)
        st["iterations"] += iterations
    solve_s = time.perf_counter() - t_solve
    if not ok and status in _TIME_LIMIT:
        raise WallTimeLimitError(
            f"bounded inversion stopped at the wall-time limit of {slv.max_wall_time:g} s after "
            f"{st['iterations']} iterations ({sch.name} N={N}); raise max_wall_time or use fewer intervals (N); "
            "the last iterate is in exc.partial", partial=inv, diagnostics={"status": status, "constraint_violation":
                                                                           viol})
    restarted = None
    if not ok and (status in INFEASIBLE or viol > 1e-6):
        err_or_start = _infeasible(model, reference, servo, setup, rb, sch, t_mesh, Y, theta, c, objective, slv, x0,
                                   status, make_inverse, viol)
        if isinstance(err_or_start, InversionFailed):
            raise err_or_start
        # the elastic problem met every bound without relaxing one: IPOPT's verdict was local; solve the
        # bounded problem again from that feasible point
        first = status
        sol, st, scale, x, g, viol, status, ok, inv = run(err_or_start)
        solve_s = time.perf_counter() - t_solve
        restarted = f"IPOPT first ended with {first}; restarted from the elastic problem's feasible point"
        if not ok and (status in INFEASIBLE or viol > 1e-6):
            raise InfeasibleBoundsError(
                f"IPOPT reports the bounds infeasible ({first}, then {status} from a point that met every bound, "
                f"constraint violation {viol:.3g}) on [{setup.T0:.6g}, {setup.Tf:.6g}], {sch.name} N={N}: the "
                "verdict is local, not a proof; try a finer mesh, more iterations (max_iter) or a warm_start "
                "(exc.partial is the last iterate)", partial=inv,
                diagnostics={"relaxation": {}, "status": status, "first_status": first, "constraint_violation": viol})
    res = residuals(inv, servo, reference, theta)
    err = output_error(inv, servo, reference, theta)
    active = active_bounds(tr, rb, t_mesh, x, np.array(sol["lam_x"]).ravel() / scale,
                           np.array(sol["lam_g"]).ravel() / scale, g, exact_margins=margins)
    if rest_start:
        active.insert(0, {"bound": "max_pre_actuation", "side": "upper", "value": rb.max_pre_actuation,
                          "intervals": [[T0, T0]], "needed": reference.t0 - T0p,
                          "describe": f"the inverse starts at rest at T0 = {T0:.6g} (the exact one needs "
                                      f"{reference.t0 - T0p:.4g} s of pre-actuation)"})
    if rest_end:
        active.insert(0, {"bound": "max_post_actuation", "side": "upper", "value": rb.max_post_actuation,
                          "intervals": [[Tf, Tf]], "needed": Tfp - reference.tf,
                          "describe": f"the inverse ends at rest at Tf = {Tf:.6g} (the exact one needs "
                                      f"{Tfp - reference.tf:.4g} s of post-actuation)"})
    Xm, _Xc, S, _tau, _r = tr.unpack(x)
    inv.diagnostics.update({
        "status": status, "iterations": int(st["iterations"]), "success": ok,
        "max_constraint_violation": viol, "backend": "ipopt", "hessian": hessian, "scheme": sch.name,
        "N": int(N), "formulation": disc.formulation, "omega": disc.omega, "build_s": build_s, "solve_s": solve_s,
        "exact_solve_s": exact_s, "guess_s": setup.timings["guess_s"], "unknowns": tr.nX, "equations": tr.ng,
        "selection": setup.selection.describe(), "T0": T0, "Tf": Tf, "residuals": res, "compiled": False,
        "plan": None if setup.plan is None else setup.plan.to_dict(), "mesh": setup.mesh_kind,
        "objective": float(sol["f"]) / scale, "objective_scale": scale,
        "slack_max": float(np.max(np.abs(S))) if S.size else 0.0,
        "bounds": {"active": active, "margins": margins, "rest": [bool(rest_start), bool(rest_end)],
                   "describe": describe_active(active, err)},
        "tracking": {"exact": False, "max_output_error": err["max"], "t_max_output_error": err["t_max"],
                     "rms_output_error": err["rms"], "by_output": err["by_output"]},
        "wall_s": time.perf_counter() - t_all, "restarted": restarted,
    })
    if not ok:
        raise InversionFailed(
            f"bounded inversion failed (IPOPT: {status} after {inv.diagnostics['iterations']} iterations, max "
            f"constraint violation {viol:.3g}) on {sch.name} N={N}. Try more iterations (max_iter), a finer mesh, "
            "a larger slack weight (Objective(slack=...)) or hessian='exact'; the last iterate is in exc.partial",
            partial=inv, diagnostics=inv.diagnostics)
    if res["holonomic_mesh"] > slv.residual_tol:
        raise InversionFailed(
            f"the bounded solution violates the holonomic constraints g = 0 by {res['holonomic_mesh']:.3g} > "
            f"residual_tol = {slv.residual_tol:.3g} at the mesh ({sch.name} N={N}); refine the mesh",
            partial=inv, diagnostics=inv.diagnostics)
    check_between_nodes(inv, rb, reference, f"bounded inversion ({sch.name} N={N})")
    inv.diagnostics["held"] = held
    if hold is not None:
        hold["last"] = {"tr": tr, "x": x, "lam_x": sol["lam_x"], "lam_g": sol["lam_g"], "scale": scale,
                        "t_mesh": t_mesh, "inverse": inv, "ends": (setup.E0, setup.Ef),
                        "limits": (lbx, ubx, lbg, ubg)}
    return inv


def _structure_change(tr, servo, selection, N, rb) -> str | None:
    """Why a held bounded solve builds another transcription (``info["rebuilt"]``), or ``None``."""
    why = structure_change(tr, servo, selection, N)
    if why is None and (tr.bounded, tr.rated) != (tuple(rb.bounded), tuple(rb.rated)):
        names, rnames = list(rb.labels), list(rb.rate_labels)
        why = (f"bounded entries {[names[i] for i in tr.bounded]} -> {[names[i] for i in rb.bounded]}, rate-bounded "
               f"{[rnames[j] for j in tr.rated]} -> {[rnames[j] for j in rb.rated]}")
    return why or ("functions compiled in the background are ready" if tr.upgradable() else None)


def _bound_size(rb, label) -> float:
    if label in ("max_pre_actuation", "max_post_actuation"):
        return float(getattr(rb, label))
    labels = list(rb.labels)
    if label in labels:
        i = labels.index(label)
        return max(abs(v) for v in (rb.lo[i], rb.hi[i]) if math.isfinite(v))
    j = list(rb.rate_labels).index(label)
    return max(abs(v) for v in (rb.rate_lo[j], rb.rate_hi[j]) if math.isfinite(v))


def _violation(g, lbg, ubg, x, lbx, ubx) -> float:
    v = max(float(np.max(g - ubg, initial=0.0)), float(np.max(lbg - g, initial=0.0)))
    return max(v, float(np.max(x - ubx, initial=0.0)), float(np.max(lbx - x, initial=0.0)))


def _inverse(tr, servo, reference, sch, t_mesh, x, Y, theta, c, make_inverse, tau=None, tau_ref=1.0):
    """The :class:`Inverse` of a bounded solution (Hermite-Simpson slopes from the relaxed model)."""
    Xm, Xc, S, _tau, _r = tr.unpack(x)
    zeta = np.vstack([Xm, S[:, :Xm.shape[1]]]) if tr.relaxed else Xm
    dX = sch.mesh_slopes(Xm, lambda: tr.point_values(zeta, Y[:, :Xm.shape[1]], theta, c, tau=tau,
                                                     tau_ref=tau_ref)[:tr.nx])
    return make_inverse(servo.model, reference, servo, sch, t_mesh, Xm, Xc, theta, dX=dX)


def _infeasible(model, reference, servo, setup, rb, sch, t_mesh, Y, theta, c, objective, slv, x_start, status,
                make_inverse, viol):
    """:class:`InfeasibleBoundsError` with the closest feasible relaxation (module doc, item 4), or,
    when the elastic problem meets every bound without relaxing one, that point (a start for a
    second bounded solve: IPOPT's infeasibility verdict was local)."""
    tr = ocp_transcription(servo, setup.selection, sch, t_mesh.size - 1, relaxed=True, bounded=rb.bounded,
                           rated=rb.rated, elastic=True)
    scale = []
    for kind, i, _side in tr.relax_labels:
        lo, hi = (rb.lo[i], rb.hi[i]) if kind == "X" else (rb.rate_lo[i], rb.rate_hi[i])
        scale.append(max([abs(v) for v in (lo, hi) if math.isfinite(v)] + [1e-3]))
    p = tr.parameters(t_mesh, Y, theta, setup.E0, setup.Ef, W=objective.output_weights(model),
                      rho=max(objective.slack, 1e-6), energy=objective.energy, rate=objective.rate, c=c,
                      relax_weights=1.0 / np.array(scale), eps=ELASTIC_EPS)
    # start where the bounded solve started, with the relaxations its bound rows need
    x0 = np.concatenate([x_start, np.zeros(tr.nr)])  # the elastic layout extends the bounded one
    lbx, ubx, lbg, ubg = _limits(tr, rb)
    g0 = np.array(tr.g_function()(x0, p)).ravel()
    base, n = tr.n_defect + tr.n_bc, len(tr.path_rows)
    need_up = g0[base:base + n] - ubg[base:base + n]
    need_lo = lbg[base + n:base + 2 * n] - g0[base + n:base + 2 * n]
    index = {lab: k for k, lab in enumerate(tr.relax_labels)}
    for q, r in enumerate(tr.path_rows):
        for side, need in (("upper", need_up[q]), ("lower", need_lo[q])):
            k = tr.i_r + index[(r.kind, r.entry, side)]
            if np.isfinite(need):
                x0[k] = max(x0[k], need + 1e-6 * scale[k - tr.i_r])
    # Gauss-Newton also when the bounded solve used the exact Hessian: the elastic objective is flat (ELASTIC_EPS) and
    # the exact Hessian's constraint curvature dominates it (|u2| <= 8 N, HS N = 20: max_iter with either barrier
    # update, 24 Gauss-Newton iterations)
    hessian = "gauss-newton" if _hessian(slv, "gauss-newton") in ("exact", "ad") else _hessian(slv, "gauss-newton")
    solver = tr.ipopt(_ipopt_options(slv, hessian), hessian=hessian)
    sol = solver(x0=x0, p=p, lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg)
    st = solver.stats()
    xe = np.array(sol["x"]).ravel()
    relax = xe[tr.i_r:]
    found = {}
    for (kind, i, side), r_, sc in zip(tr.relax_labels, relax, scale):
        if r_ <= 1e-7 * max(1.0, sc):
            continue
        label = rb.labels[i] if kind == "X" else rb.rate_labels[i]
        b = (rb.hi[i] if side == "upper" else rb.lo[i]) if kind == "X" else (
            rb.rate_hi[i] if side == "upper" else rb.rate_lo[i])
        found[f"{label}:{side}"] = {"bound": float(b), "relaxed": float(b + r_ if side == "upper" else b - r_),
                                    "by": float(r_)}
    partial = _inverse(tr, servo, reference, sch, t_mesh, xe, Y, theta, c, make_inverse)
    elastic_ok = bool(st.get("success", False))
    if not found and elastic_ok:
        return xe[:x_start.size]  # a point meeting every bound: the caller solves again from it
    if found:
        what = "; ".join(f"{k.split(':')[0]} {k.split(':')[1]} bound {v['bound']:.6g} -> {v['relaxed']:.6g}"
                         for k, v in sorted(found.items(), key=lambda kv: -kv[1]["by"]))
        return InfeasibleBoundsError(
            f"no trajectory satisfies the bounds with the boundary conditions on [{setup.T0:.6g}, {setup.Tf:.6g}] "
            f"(IPOPT: {status}, constraint violation {viol:.3g}); the closest feasible relaxation IPOPT found: {what}"
            + ("" if elastic_ok else f" (the elastic solve ended with {st.get('return_status')})"),
            partial=partial, diagnostics={"relaxation": found, "status": status, "elastic_status":
                                          st.get("return_status"), "constraint_violation": viol})
    # neither solve converged: whether the bounds can be met is not decided
    cls = InfeasibleBoundsError if status in INFEASIBLE else InversionFailed
    return cls(
        f"the bounded inversion did not converge (IPOPT: {status}, constraint violation {viol:.3g} on "
        f"[{setup.T0:.6g}, {setup.Tf:.6g}], {sch.name} N={t_mesh.size - 1}), and neither did the elastic problem "
        f"that relaxes the bounds with a penalty ({st.get('return_status')}, no bound relaxed at its last iterate): "
        "whether these bounds can be met is undecided. Try more iterations (max_iter), looser bounds to see where "
        "feasibility ends, or the last elastic iterate (exc.partial) as warm_start",
        partial=partial, diagnostics={"relaxation": {}, "status": status, "elastic_status": st.get("return_status"),
                                      "constraint_violation": viol})


def describe_active(active: list[dict], err: dict) -> str:
    """One paragraph for reports: what is active where, and the output error it costs."""
    if not active:
        return f"no bound active; output error {err['max']:.3g} (max)"
    parts = []
    for e in active:
        if "describe" in e:
            parts.append(e["describe"])
            continue
        iv = ", ".join(f"[{a:.4g}, {b:.4g}]" if b > a else f"{a:.4g}" for a, b in e["intervals"][:4])
        more = "" if len(e["intervals"]) <= 4 else f" (+{len(e['intervals']) - 4} more)"
        exc = (f"; the exact inverse exceeds it by {e['exact_inverse_excess']:.3g}"
               if e.get("exact_inverse_excess") else "")
        parts.append(f"{e['bound']} {e['side']} bound {e['value']:.6g} active at t = {iv}{more}{exc}; "
                     f"objective sensitivity {e['sensitivity']:.3g}")
    return ("; ".join(parts) + f". Output error they cost: max {err['max']:.3g} at t = {err['t_max']:.4g} s, "
            f"RMS {err['rms']:.3g}")
