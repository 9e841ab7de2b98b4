"""Bounded inversion and minimum time: invctl against the same problems written by hand in CasADi Opti.

The manipulator runs on its former default parameters (``--preset guess``: m3 = 0.5, c = 5, D = 0.05), on which
the committed output was measured (the scene's defaults are now the identified set of 003 Sect. 6).

Two problems, each solved twice:

1. the manipulator (003 Sect. 6) with |u2| <= 8 N (the exact inverse needs 9.7 N): least-squares
   tracking with the relaxed servo constraint, Hermite-Simpson N = 100 on the automatic setup's
   mesh, horizon and boundary conditions;
2. the cart-pole with |F| <= 1 N: the minimum duration of the reference's shape (exact tracking,
   free transition time, the intervals of [t0, tf] scaled with tau).

The peers are what a competent user writes with CasADi's Opti stack: decision variables for the
mesh states (and slacks, and tau), the same Hermite-Simpson equations with the same right-hand side
(``invctl.inversion.ocp.relaxed_rhs``) mapped over all mesh points and midpoints at once
(``Function.map``, one matrix defect, no Python loop over intervals), the same Simpson objective,
bounds at the mesh points and midpoints, the same boundary conditions, equilibria and initial
guess, the model parameters as an Opti parameter, IPOPT with the same options (and the same
objective scaling invctl ended with).  Opti differentiates its graph by AD (exact Hessian);
``expand=True`` (SX) is the usual speed-up; the MX graph is timed as well.  A peer's build
(``Opti`` + ``solver``) is timed apart from its first solve; its re-solve calls ``opti.solve()`` again
on the built solver (nothing rebuilt).  invctl's first call clears its caches; its re-solve is the
same ``invert``/``minimum_time`` call again.  Re-solves run in interleaved rounds (min and median).
invctl's bounded least squares uses the Gauss-Newton Hessian by default; the row
``hessian='exact'`` is the same call with the exact Hessian, Opti's choice.  Problem 1 adds what a user of a held
solver does: re-solve after a parameter change (the bound 8.0 <-> 7.9 N, alternating), invctl's held
``InversionSolver`` (from its last primal-dual optimum) against Opti re-solving on its built solver warm-started
from its last primal-dual solution (``set_initial`` of the variables and of ``lam_g``, IPOPT
``warm_start_init_point`` with invctl's warm options), both whole calls in interleaved rounds.  Problem 2 adds invctl's held
solver (``MinimumTimeSolver``: its first call builds, its re-solve starts at its last optimum).  Reported: the optimum
(objective, duration), the largest state difference, iterations, and the time ratios.

    python benchmarks/bench_ocp.py [--smoke]        (output: benchmarks/bench_ocp_output.txt)

``--smoke`` (alias ``--quick``): the same problems on coarse meshes, one value per trade-off, output
not written (checks that the benchmark runs; its numbers are not the benchmark's).
"""
from __future__ import annotations

import os
import sys
import time
from types import SimpleNamespace

import casadi as ca
import numpy as np

import invctl_scenes.cartpole as cp
import invctl_scenes.manipulator as mn
from invctl.errors import InversionFailed
from invctl.inversion import Bounds, invert, servo_model
from invctl.inversion.backends import IPOPT_DEFAULTS
from invctl.inversion import InversionSolver
from invctl.inversion.bounded import IPOPT_BOUNDED_DEFAULTS, IPOPT_WARM
from invctl.inversion.mintime import MinimumTimeSolver, minimum_time
from invctl.inversion.ocp import relaxed_rhs, slack_scale

SMOKE = bool({"--smoke", "--quick"} & set(sys.argv[1:]))
N_MANIP = 20 if SMOKE else 100
N_CART = 30 if SMOKE else 100


def values(*vs):
    """The trade-off values of a run (the first one only in smoke mode)."""
    return vs[:1] if SMOKE else vs


def ipopt_opts(scale):
    o = dict(IPOPT_DEFAULTS)
    o.update(IPOPT_BOUNDED_DEFAULTS)
    o.update({"ipopt.max_iter": 300, "ipopt.obj_scaling_factor": float(scale)})
    return o


# ----------------------------------------------------------------------------- timing
ROUNDS = 2 if SMOKE else 5


def interleaved(calls: dict) -> dict:
    """Wall times of each zero-argument call over ``ROUNDS`` interleaved rounds: name -> (min, median, last result)."""
    times: dict = {k: [] for k in calls}
    last: dict = {}
    for _ in range(ROUNDS):
        for k, call in calls.items():
            t0 = time.perf_counter()
            last[k] = call()
            times[k].append(time.perf_counter() - t0)
    return {k: (min(v), float(np.median(v)), last[k]) for k, v in times.items()}


def hs_opti(sv, t_mesh, Yn, Ym, *, relaxed: bool, tau_ref=None, mask=None):
    """The Hermite-Simpson transcription in Opti, vectorised: the right-hand side mapped over the mesh
    points and the midpoints (``Function.map``), one matrix defect; ``tau`` (free time) scales the
    intervals inside [t0, tf] (``mask``) and the reference's derivatives, as in invctl."""
    N, nx, m = t_mesh.size - 1, sv.layout.nx, sv.model.m
    f = relaxed_rhs(sv)
    opti = ca.Opti()
    X = opti.variable(nx, N + 1)
    th = opti.parameter(sv.model.theta.shape[0])
    H = ca.DM(np.diff(t_mesh)).T
    S = opti.variable(m, N + 1) if relaxed else ca.DM.zeros(m, N + 1)
    Sm = opti.variable(m, N) if relaxed else ca.DM.zeros(m, N)
    tau = None
    if tau_ref is not None:
        tau = opti.variable()
        r = tau / tau_ref
        sc = ca.vertcat(*[ca.repmat(r ** (-k), m, 1) for k in range(4)])
        Yn, Ym = Yn * ca.repmat(sc, 1, N + 1), Ym * ca.repmat(sc, 1, N)
        H = H * (1 + ca.DM(mask).T * (r - 1))
    c = 1.0 if tau_ref is not None else slack_scale(sv, float(t_mesh[-1] - t_mesh[0]))
    F = f.map(N + 1)(X, Yn, th, S, c)
    Xm = 0.5 * (X[:, :N] + X[:, 1:]) + ca.repmat(H / 8, nx, 1) * (F[:, :N] - F[:, 1:])
    Fm = f.map(N)(Xm, Ym, th, Sm, c)
    opti.subject_to(ca.vec(X[:, 1:] - X[:, :N] - ca.repmat(H / 6, nx, 1) * (F[:, :N] + 4 * Fm + F[:, 1:])) == 0)
    return SimpleNamespace(opti=opti, X=X, S=S, Sm=Sm, Xm=Xm, H=H, th=th, tau=tau, N=N, Yn=Yn, Ym=Ym)


# ----------------------------------------------------------------------------- problem 1
def opti_bounded(md, ref, inv, exact, *, expand: bool, warm: bool = False):
    """The bounded least-squares inversion written in Opti (module doc); returns its first solve and a
    call that re-solves with the same solver (nothing rebuilt).  ``warm``: IPOPT started from the last
    primal-dual solution (``IPOPT_WARM``, invctl's options of a held re-solve), and the re-solve call takes
    the bound (an Opti parameter)."""
    sv = servo_model(md)
    d = inv.diagnostics
    t_mesh = inv.t_mesh
    h = np.diff(t_mesh)
    m = md.m
    tm = t_mesh[:-1] + 0.5 * h
    Yn, Ym = sv.reference_samples(ref, t_mesh), sv.reference_samples(ref, tm)
    rho = 1e-2  # Objective() default slack weight; output weights 1
    iu2 = sv.layout.blocks["u"].start + 1
    plan = d["plan"]
    from invctl.inversion import resolve_selection

    sel = resolve_selection(sv, plan["start"], plan["end"])
    E0, Ef = exact.X(exact.T0)[:, 0], exact.X(exact.Tf)[:, 0]
    t_build = time.perf_counter()
    p = hs_opti(sv, t_mesh, Yn, Ym, relaxed=True)
    opti, X, N = p.opti, p.X, p.N
    Xs, Ys, ths, ss = (ca.SX.sym(n, k) for n, k in (("X", sv.layout.nx), ("Y", 4 * m), ("th", md.theta.shape[0]),
                                                     ("s", m)))
    L = ca.Function("L", [Xs, Ys, ths, ss], [ca.sumsqr(sv.output(Xs, Ys, ths) - Ys[:m]) + rho * ca.sumsqr(ss)])
    Ln, Lm = L.map(N + 1)(X, Yn, p.th, p.S), L.map(N)(p.Xm, Ym, p.th, p.Sm)
    J = ca.sum2(p.H / 6 * (Ln[:, :N] + 4 * Lm + Ln[:, 1:]))
    ub = opti.parameter()
    opti.subject_to(opti.bounded(-ub, p.Xm[iu2, :], ub))
    opti.subject_to(opti.bounded(-ub, X[iu2, :], ub))
    opti.subject_to(X[list(sel.start), 0] == E0[list(sel.start)])
    opti.subject_to(X[list(sel.end), N] == Ef[list(sel.end)])
    opti.minimize(J)
    opti.set_value(p.th, md.theta_values)
    opti.set_value(ub, 8.0)
    opti.set_initial(X, exact.X(t_mesh))
    opti.solver("ipopt", {**ipopt_opts(d["objective_scale"]), "expand": expand})
    build = time.perf_counter() - t_build
    last = {}

    def solve():
        sol = last["sol"] = opti.solve()
        st = sol.stats()
        return {"objective": float(sol.value(J)), "X": np.array(sol.value(X)), "iterations": st["iter_count"],
                "status": st["return_status"]}

    t0 = time.perf_counter()
    first = solve()
    first = {**first, "build_s": build, "first_solve_s": time.perf_counter() - t0}
    if not warm:
        return first, solve
    opti.solver("ipopt", {**ipopt_opts(d["objective_scale"]), **IPOPT_WARM, "expand": expand})

    def warm_solve(bound):
        sol = last["sol"]
        opti.set_value(ub, bound)
        opti.set_initial(sol.value_variables())
        opti.set_initial(opti.lam_g, sol.value(opti.lam_g))
        return solve()

    warm_solve(8.0)  # builds the warm-started solver
    return first, warm_solve


def _rows_and_lines(lines, ours: dict, peers: dict, label, inv_value, X_ref, fmt):
    """Print each peer's agreement with invctl, then the timing table: first calls, and re-solves over
    interleaved rounds (``ours``: name -> (first call s, call, iterations); ``peers``: name -> (first solve
    record, re-solve call))."""
    timed = interleaved({**{name: call for name, (_f, call, _it) in ours.items()},
                         **{name: call for name, (_r, call) in peers.items()}})
    for name, (r, _call) in peers.items():
        dx = float(np.max(np.abs(timed[name][2]["X"] - X_ref)))
        lines.append(f"   {name}: {r['status']}, {r['iterations']} iterations, {label} {fmt(r)} (rel. diff "
                     f"{abs(r[label] / inv_value - 1):.1e}), max |X - X_invctl| {dx:.1e}; build {r['build_s']:.2f} s, "
                     f"first solve {r['first_solve_s']:.2f} s")
    lines.append(f"   times: first call (invctl: caches cleared, everything; a peer: its build + first solve); re-solve "
                 f"= the same call again, {ROUNDS} interleaved rounds (a peer re-solves with its built solver)")
    lines.append("   formulation               first_s  re-solve min_s  median_s  iter   first/invctl  "
                 "re-solve min/invctl")
    base = next(iter(ours))
    rows = [(name, first, it) for name, (first, _c, it) in ours.items()]
    rows += [(name, r["build_s"] + r["first_solve_s"], r["iterations"]) for name, (r, _call) in peers.items()]
    for name, first, it in rows:
        mn, med = timed[name][0], timed[name][1]
        lines.append(f"   {name:24s} {first:8.2f} {mn:15.3f} {med:9.3f} {it:5d} {first / ours[base][0]:13.2f}x "
                     f"{mn / timed[base][0]:19.2f}x")
    return rows


def bench_bounded(lines):
    md, ref = mn.build(**mn.PRESETS["guess"]), None  # the set the bounds below were chosen for
    ref = mn.reference(md)
    q0 = mn.initial_configuration(md)  # a fresh model object: nothing of the inversion is built yet
    t0 = time.perf_counter()
    inv = invert(md, ref, q_guess=q0, N=N_MANIP, bounds=Bounds(u={"u2": 8.0}))
    cold = time.perf_counter() - t0
    exact = invert(md, ref, q_guess=q0, N=N_MANIP)
    d = inv.diagnostics
    lines.append(f"1. manipulator, |u2| <= 8 N, least-squares tracking, HS N = {N_MANIP} "
                 f"({d['unknowns']} unknowns, {d['equations']} constraints)")
    lines.append(f"   invctl: {d['status']}, {d['iterations']} iterations (Gauss-Newton Hessian), objective "
                 f"{d['objective']:.9e}, max output error {d['tracking']['max_output_error']:.4e}; first call "
                 f"{cold:.2f} s (setup, exact inverse, NLP build, solve)")
    peers = {("Opti expand=True" if e else "Opti (MX, AD Hessian)"): opti_bounded(md, ref, inv, exact, expand=e)
             for e in (True, False)}
    ours = {"invctl": (cold, lambda: invert(md, ref, q_guess=q0, N=N_MANIP, bounds=Bounds(u={"u2": 8.0})),
                       d["iterations"])}
    t0 = time.perf_counter()
    try:  # the exact Hessian, as Opti's
        inv_x = invert(md, ref, q_guess=q0, N=N_MANIP, bounds=Bounds(u={"u2": 8.0}), hessian="exact")
    except InversionFailed as exc:
        lines.append(f"   invctl hessian='exact': failed ({str(exc)[:100]}...)")
    else:
        dx = inv_x.diagnostics
        lines.append(f"   invctl hessian='exact': {dx['status']}, {dx['iterations']} iterations, objective "
                     f"{dx['objective']:.9e} (rel. diff {abs(dx['objective'] / d['objective'] - 1):.1e})")
        ours["invctl hessian='exact'"] = (time.perf_counter() - t0, lambda: invert(
            md, ref, q_guess=q0, N=N_MANIP, bounds=Bounds(u={"u2": 8.0}), hessian="exact"), dx["iterations"])
    rows = _rows_and_lines(lines, ours, peers, "objective", d["objective"], inv.X_mesh,
                           lambda r: f"{r['objective']:.9e}")
    held_resolve(lines, md, ref, q0, inv, exact)
    return rows


def held_resolve(lines, md, ref, q0, inv, exact):
    """What a user of a held solver does: re-solve after a parameter change (the bound 8.0 <-> 7.9 N, alternating),
    invctl's held InversionSolver against Opti warm-started on its built solver from its last primal-dual solution."""
    t0 = time.perf_counter()
    held = InversionSolver(md, ref, q_guess=q0, N=N_MANIP, bounds=Bounds(u={"u2": 8.0}))
    held.solve()
    first = time.perf_counter() - t0
    opti_first, opti_warm = opti_bounded(md, ref, inv, exact, expand=True, warm=True)
    state = {"invctl": 8.0, "opti": 8.0}
    iterations: list = []  # of every held re-solve

    def flip(who):
        state[who] = 7.9 if state[who] == 8.0 else 8.0
        return state[who]

    def ours():
        b = flip("invctl")
        out = held.solve(bounds=Bounds(u={"u2": b}))
        iterations.append(out.diagnostics["iterations"])
        return {"objective": out.diagnostics["objective"], "X": out.X_mesh, "iterations": out.diagnostics["iterations"],
                "bound": b}

    def peer():
        b = flip("opti")
        return {**opti_warm(b), "bound": b}

    timed = interleaved({"invctl held InversionSolver": ours, "Opti expand=True, warm": peer})
    r_ours, r_peer = timed["invctl held InversionSolver"][2], timed["Opti expand=True, warm"][2]
    fresh = invert(md, ref, q_guess=q0, N=N_MANIP, bounds=Bounds(u={"u2": r_ours["bound"]})).diagnostics
    lines.append(f"   re-solve after a parameter change (|u2| bound 8.0 <-> 7.9 N, alternating; {ROUNDS} interleaved "
                 "rounds, whole calls): a held solver against Opti re-solving on its built solver from its last "
                 "primal-dual solution (IPOPT warm_start_init_point, invctl's warm options)")
    lines.append(f"   last round (bound {r_ours['bound']:.1f}): invctl held {r_ours['iterations']} iterations, objective "
                 f"rel. diff to a fresh invert {abs(r_ours['objective'] / fresh['objective'] - 1):.1e} (fresh: "
                 f"{fresh['iterations']} iterations); Opti warm {r_peer['iterations']} iterations, {r_peer['status']}, "
                 f"objective rel. diff {abs(r_peer['objective'] / fresh['objective'] - 1):.1e}; invctl held first call "
                 f"{first:.2f} s, Opti warm build + first solve {opti_first['build_s'] + opti_first['first_solve_s']:.2f} s")
    lines.append(f"   invctl held iterations, every round: {iterations} (IPOPT from the predicted start, "
                 f"{'predicted start' in held.info['reused']})")
    lines.append("   held re-solve                        min_s  median_s  min/invctl")
    base = timed["invctl held InversionSolver"][0]
    for name, (mn_, med, _r) in timed.items():
        lines.append(f"   {name:34s} {mn_:7.3f} {med:9.3f} {mn_ / base:10.2f}x")


# ----------------------------------------------------------------------------- problem 2
def opti_min_time(md, ref, inv, *, expand: bool):
    """The cart-pole minimum-time problem written in Opti (module doc); first solve and a re-solve call."""
    sv = servo_model(md)
    plan = inv.diagnostics["plan"]
    from invctl.inversion import resolve_selection
    from invctl.inversion.problem import prepare
    from invctl.inversion.options import Discretization, Horizon

    setup = prepare(md, ref, Discretization(N=inv.N), Horizon())
    t_mesh = setup.t_mesh
    h = np.diff(t_mesh)
    mask = ((t_mesh[:-1] >= ref.t0 - 1e-12) & (t_mesh[1:] <= ref.tf + 1e-12)).astype(float)
    tau_ref = ref.tf - ref.t0
    tm = t_mesh[:-1] + 0.5 * h
    Yn, Ym = sv.reference_samples(ref, t_mesh), sv.reference_samples(ref, tm)
    sel = resolve_selection(sv, plan["start"], plan["end"])
    exact = invert(md, ref, N=inv.N)
    t_build = time.perf_counter()
    p = hs_opti(sv, t_mesh, Yn, Ym, relaxed=False, tau_ref=tau_ref, mask=mask)
    opti, X, tau, N = p.opti, p.X, p.tau, p.N
    iu = sv.layout.blocks["u"].start
    opti.subject_to(opti.bounded(-1.0, p.Xm[iu, :], 1.0))
    opti.subject_to(opti.bounded(-1.0, X[iu, :], 1.0))
    opti.subject_to(X[list(sel.start), 0] == setup.E0[list(sel.start)])
    opti.subject_to(X[list(sel.end), N] == setup.Ef[list(sel.end)])
    opti.subject_to(opti.bounded(0.02 * tau_ref, tau, 50 * tau_ref))
    opti.minimize(tau)
    opti.set_value(p.th, md.theta_values)
    opti.set_initial(X, exact.X(t_mesh))
    opti.set_initial(tau, tau_ref)
    opti.solver("ipopt", {**ipopt_opts(1.0), "expand": expand})
    build = time.perf_counter() - t_build

    def solve():
        sol = opti.solve()
        st = sol.stats()
        return {"tau": float(sol.value(tau)), "X": np.array(sol.value(X)), "iterations": st["iter_count"],
                "status": st["return_status"]}

    t0 = time.perf_counter()
    first = solve()
    return {**first, "build_s": build, "first_solve_s": time.perf_counter() - t0}, solve


def bench_min_time(lines):
    md = cp.build()
    ref = cp.reference(md)  # a fresh model object: nothing of the inversion is built yet
    t0 = time.perf_counter()
    inv = minimum_time(md, ref, bounds=Bounds(u=1.0), N=N_CART)
    cold = time.perf_counter() - t0
    d, ft = inv.diagnostics, inv.diagnostics["free_time"]
    lines.append("2. cart-pole, |F| <= 1 N, minimum duration of the reference's shape (exact tracking), "
                 f"HS N = {N_CART}")
    lines.append(f"   invctl: {d['status']}, {d['iterations']} iterations (structured exact Hessian), duration "
                 f"{ft['duration']:.10f} s; first call {cold:.2f} s")
    peers = {("Opti expand=True" if e else "Opti (MX, AD Hessian)"): opti_min_time(md, ref, inv, expand=e)
             for e in (True, False)}
    ours = {"invctl": (cold, lambda: minimum_time(md, ref, bounds=Bounds(u=1.0), N=N_CART), d["iterations"])}
    # the held solver: plan, setup, transcription and last solution kept; a re-solve starts at the last optimum
    t0 = time.perf_counter()
    held = MinimumTimeSolver(md, ref, bounds=Bounds(u=1.0), N=N_CART)
    dh = held.solve().diagnostics
    first_held = time.perf_counter() - t0
    dr = held.solve().diagnostics
    lines.append(f"   invctl MinimumTimeSolver: {dh['status']}, {dh['iterations']} iterations, duration "
                 f"{dh['free_time']['duration']:.10f} s (rel. diff {abs(dh['free_time']['duration'] / ft['duration'] - 1):.1e})"
                 f"; a re-solve starts at the last optimum (primal-dual): {dr['iterations']} iterations, duration "
                 f"rel. diff {abs(dr['free_time']['duration'] / ft['duration'] - 1):.1e}")
    ours["invctl MinimumTimeSolver"] = (first_held, held.solve, dh["iterations"])
    return _rows_and_lines(lines, ours, peers, "tau", ft["duration"], inv.X_mesh, lambda r: f"{r['tau']:.10f} s")


def tradeoffs(lines):
    """The numbers of docs/trajectories.md: what a bound costs in output error, what a shorter
    pre-actuation costs, how the minimum duration follows the bound, the time-energy trade."""
    md = mn.build(**mn.PRESETS["guess"])
    ref = mn.reference(md)
    q0 = mn.initial_configuration(md)
    exact = invert(md, ref, q_guess=q0, N=N_MANIP)
    peak = float(np.max(np.abs(exact.X_mesh[-1])))
    lines.append(f"3. trade-offs (manipulator HS N = {N_MANIP}; the exact inverse: |u2| <= {peak:.2f} N, "
                 f"pre-actuation {exact.t0 - exact.T0:.3f} s, solve {exact.diagnostics['solve_s']:.3f} s)")
    lines.append("   bound |u2| <= U: least-squares tracking       U [N]   max|e|      RMS e      iter  wall_s")
    for U in values(9.5, 9.0, 8.0, 7.0, 6.0):
        t0 = time.perf_counter()
        inv = invert(md, ref, q_guess=q0, N=N_MANIP, bounds=Bounds(u={"u2": U}))
        tr = inv.diagnostics["tracking"]
        lines.append(f"   {'':44s} {U:5.1f}  {tr['max_output_error']:.3e}  {tr['rms_output_error']:.3e}  "
                     f"{inv.diagnostics['iterations']:4d}  {time.perf_counter() - t0:6.2f}")
    lines.append("   pre-actuation <= p: start at rest at t0 - p    p [s]   max|e|      RMS e      iter  wall_s")
    for pre in values(0.05, 0.1, 0.2, 0.3, 0.4):
        t0 = time.perf_counter()
        inv = invert(md, ref, q_guess=q0, N=N_MANIP, bounds=Bounds(max_pre_actuation=pre))
        tr = inv.diagnostics["tracking"]
        lines.append(f"   {'':44s} {pre:5.2f}  {tr['max_output_error']:.3e}  {tr['rms_output_error']:.3e}  "
                     f"{inv.diagnostics['iterations']:4d}  {time.perf_counter() - t0:6.2f}")
    lines.append("   minimum duration of the shape, |u| <= U       U [N]   tau [s]     energy     iter  wall_s")
    for U in values(12.0, 10.0, 8.0, 6.0):
        t0 = time.perf_counter()
        inv = minimum_time(md, ref, bounds=Bounds(u=U), q_guess=q0, N=N_MANIP)
        ft = inv.diagnostics["free_time"]
        lines.append(f"   {'':44s} {U:5.1f}  {ft['duration']:.6f}  {ft['energy']:9.3f}  "
                     f"{inv.diagnostics['iterations']:4d}  {time.perf_counter() - t0:6.2f}")
    c = cp.build()
    cref = cp.reference(c)
    lines.append("   cart-pole time-energy trade tau + w int F^2    w       tau [s]     energy     iter  wall_s")
    for w in values(0.01, 0.1, 1.0):
        t0 = time.perf_counter()
        inv = minimum_time(c, cref, energy=w, N=N_CART)
        ft = inv.diagnostics["free_time"]
        lines.append(f"   {'':44s} {w:5.2f}  {ft['duration']:.6f}  {ft['energy']:9.4f}  "
                     f"{inv.diagnostics['iterations']:4d}  {time.perf_counter() - t0:6.2f}")


def main():
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    lines = [f"# {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, load average before: {load}, "
             f"{os.cpu_count()} cores: python benchmarks/bench_ocp.py",
             f"bench_ocp: invctl bounded inversion / minimum time vs the same problems in CasADi Opti "
             f"(casadi {ca.__version__}; {'smoke' if SMOKE else 'full'} run)", ""]
    bench_bounded(lines)
    lines.append("")
    bench_min_time(lines)
    lines.append("")
    tradeoffs(lines)
    text = "\n".join(lines)
    print(text)
    if not SMOKE:
        with open(__file__.replace(".py", "_output.txt"), "w") as fh:
            fh.write(text + "\n")


if __name__ == "__main__":
    main()
