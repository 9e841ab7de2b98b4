"""Bounded inversion and minimum time: invctl against the same problems written by hand in CasADi Opti.

The manipulator runs on its former default parameters (``--preset guess``: m3 = 0.5, c = 5, D = 0.05), on which
the committed output was measured (the scene's defaults are now the identified set of 003 Sect. 6).

Two problems, each solved twice:

1. the manipulator (003 Sect. 6) with |u2| <= 8 N (the exact inverse needs 9.7 N): least-squares
   tracking with the relaxed servo constraint, Hermite-Simpson N = 100 on the automatic setup's
   mesh, horizon and boundary conditions;
2. the cart-pole with |F| <= 1 N: the minimum duration of the reference's shape (exact tracking,
   free transition time, the intervals of [t0, tf] scaled with tau).

The Opti versions are what a user writes with CasADi's Opti stack: decision variables for the
mesh states (and slacks, and tau), a Python loop over the intervals stating the same
Hermite-Simpson equations with the same right-hand side (``invctl.inversion.ocp.relaxed_rhs``),
the same Simpson objective, bounds at the mesh points and midpoints, the same boundary
conditions, equilibria and initial guess, IPOPT with the same options (and the same objective
scaling invctl ended with).  Opti differentiates its graph by AD (exact Hessian); ``expand=True``
(SX) is the usual speed-up and is timed as well.  Reported: the optimum (objective, duration),
the largest state difference, iterations, build and solve time, and the time ratios.

    python benchmarks/bench_ocp.py [--smoke]        (output: benchmarks/bench_ocp_output.txt)

``--smoke`` (alias ``--quick``): the same problems on coarse meshes, one value per trade-off, output
not written (checks that the benchmark runs; its numbers are not the benchmark's).
"""
from __future__ import annotations

import sys
import time

import casadi as ca
import numpy as np

import invctl_scenes.cartpole as cp
import invctl_scenes.manipulator as mn
from invctl.inversion import Bounds, invert, servo_model
from invctl.inversion import cache as _cache
from invctl.inversion.backends import IPOPT_DEFAULTS
from invctl.inversion.bounded import IPOPT_BOUNDED_DEFAULTS
from invctl.inversion.mintime import minimum_time
from invctl.inversion.ocp import relaxed_rhs, slack_scale

SMOKE = bool({"--smoke", "--quick"} & set(sys.argv[1:]))
N_MANIP = 20 if SMOKE else 100
N_CART = 30 if SMOKE else 100


def values(*vs):
    """The trade-off values of a run (the first one only in smoke mode)."""
    return vs[:1] if SMOKE else vs


def clear_caches():
    for c in (_cache._TRANS_CACHE, _cache._OCP_CACHE, _cache._SERVO_CACHE, _cache._EQ_CACHE, _cache._QS_LAST):
        c.clear()


def ipopt_opts(scale):
    o = dict(IPOPT_DEFAULTS)
    o.update(IPOPT_BOUNDED_DEFAULTS)
    o.update({"ipopt.max_iter": 300, "ipopt.obj_scaling_factor": float(scale)})
    return o


# ----------------------------------------------------------------------------- problem 1
def opti_bounded(md, ref, inv, exact, *, expand: bool):
    """The bounded least-squares inversion written in Opti (module doc)."""
    sv = servo_model(md)
    d = inv.diagnostics
    t_mesh = inv.t_mesh
    N, nx, m = t_mesh.size - 1, sv.layout.nx, md.m
    h = np.diff(t_mesh)
    tm = t_mesh[:-1] + 0.5 * h
    Yn, Ym = sv.reference_samples(ref, t_mesh), sv.reference_samples(ref, tm)
    th = md.theta_values
    f = relaxed_rhs(sv)
    c = slack_scale(sv, ref.tf - ref.t0)
    rho = 1e-2  # Objective() default slack weight; output weights 1
    iu2 = sv.layout.blocks["u"].start + 1
    plan = d["plan"]
    from invctl.inversion import resolve_selection

    sel = resolve_selection(sv, plan["start"], plan["end"])
    E0, Ef = exact.X(exact.T0)[:, 0], exact.X(exact.Tf)[:, 0]
    t_build = time.perf_counter()
    opti = ca.Opti()
    X = opti.variable(nx, N + 1)
    S = opti.variable(m, N + 1)
    Sm = opti.variable(m, N)

    def L(Xk, Yk, sk):
        e = sv.output(Xk, Yk, th) - Yk[:m]
        return ca.sumsqr(e) + rho * ca.sumsqr(sk)

    J = 0
    F = [f(X[:, k], Yn[:, k], th, S[:, k], c) for k in range(N + 1)]
    for k in range(N):
        Xm = 0.5 * (X[:, k] + X[:, k + 1]) + h[k] / 8 * (F[k] - F[k + 1])
        Fm = f(Xm, Ym[:, k], th, Sm[:, k], c)
        opti.subject_to(X[:, k + 1] - X[:, k] - h[k] / 6 * (F[k] + 4 * Fm + F[k + 1]) == 0)
        J += h[k] / 6 * (L(X[:, k], Yn[:, k], S[:, k]) + 4 * L(Xm, Ym[:, k], Sm[:, k])
                         + L(X[:, k + 1], Yn[:, k + 1], S[:, k + 1]))
        opti.subject_to(opti.bounded(-8.0, Xm[iu2], 8.0))
    opti.subject_to(opti.bounded(-8.0, X[iu2, :], 8.0))
    opti.subject_to(X[list(sel.start), 0] == E0[list(sel.start)])
    opti.subject_to(X[list(sel.end), N] == Ef[list(sel.end)])
    opti.minimize(J)
    opti.set_initial(X, exact.X(t_mesh))
    opti.solver("ipopt", {**ipopt_opts(d["objective_scale"]), "expand": expand})
    build = time.perf_counter() - t_build
    t0 = time.perf_counter()
    sol = opti.solve()
    solve = time.perf_counter() - t0
    st = sol.stats()
    return {"objective": float(sol.value(J)), "X": np.array(sol.value(X)), "iterations": st["iter_count"],
            "build_s": build, "solve_s": solve, "status": st["return_status"]}


def bench_bounded(lines):
    md, ref = mn.build(**mn.PRESETS["guess"]), None  # the set the bounds below were chosen for
    ref = mn.reference(md)
    q0 = mn.initial_configuration(md)
    clear_caches()
    t0 = time.perf_counter()
    inv = invert(md, ref, q_guess=q0, N=N_MANIP, bounds=Bounds(u={"u2": 8.0}))
    cold = time.perf_counter() - t0
    t0 = time.perf_counter()
    inv = invert(md, ref, q_guess=q0, N=N_MANIP, bounds=Bounds(u={"u2": 8.0}))
    warm = time.perf_counter() - t0
    exact = invert(md, ref, q_guess=q0, N=N_MANIP)
    d = inv.diagnostics
    lines.append(f"1. manipulator, |u2| <= 8 N, least-squares tracking, HS N = {N_MANIP} "
                 f"({d['unknowns']} unknowns, {d['equations']} constraints)")
    lines.append(f"   invctl: {d['status']}, {d['iterations']} iterations (Gauss-Newton Hessian), objective "
                 f"{d['objective']:.9e}, max output error {d['tracking']['max_output_error']:.4e}")
    lines.append(f"           first call {cold:.2f} s (setup, exact inverse, NLP build, solve), repeated call "
                 f"{warm:.2f} s (solve {d['solve_s']:.2f} s)")
    rows = [("invctl", cold, warm, d["iterations"], d["objective"], 0.0)]
    for expand in (False, True):
        r = opti_bounded(md, ref, inv, exact, expand=expand)
        dx = float(np.max(np.abs(r["X"] - inv.X_mesh)))
        name = "Opti expand=True" if expand else "Opti (MX, AD Hessian)"
        lines.append(f"   {name}: {r['status']}, {r['iterations']} iterations, objective {r['objective']:.9e} "
                     f"(rel. diff {abs(r['objective'] / d['objective'] - 1):.1e}), max |X - X_invctl| {dx:.1e}; "
                     f"build {r['build_s']:.2f} s, solve {r['solve_s']:.2f} s")
        rows.append((name, r["build_s"] + r["solve_s"], r["solve_s"], r["iterations"], r["objective"], dx))
    return rows


# ----------------------------------------------------------------------------- problem 2
def opti_min_time(md, ref, inv, *, expand: bool):
    """The cart-pole minimum-time problem written in Opti (module doc)."""
    sv = servo_model(md)
    plan = inv.diagnostics["plan"]
    from invctl.inversion import resolve_selection
    from invctl.inversion.problem import prepare
    from invctl.inversion.options import Discretization, Horizon

    setup = prepare(md, ref, Discretization(N=inv.N), Horizon())
    t_mesh = setup.t_mesh
    N, nx = t_mesh.size - 1, sv.layout.nx
    h = np.diff(t_mesh)
    mask = ((t_mesh[:-1] >= ref.t0 - 1e-12) & (t_mesh[1:] <= ref.tf + 1e-12)).astype(float)
    tau_ref = ref.tf - ref.t0
    tm = t_mesh[:-1] + 0.5 * h
    Yn, Ym = sv.reference_samples(ref, t_mesh), sv.reference_samples(ref, tm)
    th = md.theta_values
    f = relaxed_rhs(sv)
    sel = resolve_selection(sv, plan["start"], plan["end"])
    exact = invert(md, ref, N=inv.N)
    t_build = time.perf_counter()
    opti = ca.Opti()
    X = opti.variable(nx, N + 1)
    tau = opti.variable()
    r = tau / tau_ref
    sc = ca.vertcat(*[ca.repmat(r ** (-k), md.m, 1) for k in range(4)])
    zero = ca.DM.zeros(md.m)
    F = [f(X[:, k], Yn[:, k] * sc, th, zero, 1.0) for k in range(N + 1)]
    iu = sv.layout.blocks["u"].start
    for k in range(N):
        hk = h[k] * (1 + mask[k] * (r - 1))
        Xm = 0.5 * (X[:, k] + X[:, k + 1]) + hk / 8 * (F[k] - F[k + 1])
        Fm = f(Xm, Ym[:, k] * sc, th, zero, 1.0)
        opti.subject_to(X[:, k + 1] - X[:, k] - hk / 6 * (F[k] + 4 * Fm + F[k + 1]) == 0)
        opti.subject_to(opti.bounded(-1.0, Xm[iu], 1.0))
    opti.subject_to(opti.bounded(-1.0, X[iu, :], 1.0))
    opti.subject_to(X[list(sel.start), 0] == setup.E0[list(sel.start)])
    opti.subject_to(X[list(sel.end), N] == setup.Ef[list(sel.end)])
    opti.subject_to(opti.bounded(0.02 * tau_ref, tau, 50 * tau_ref))
    opti.minimize(tau)
    opti.set_initial(X, exact.X(t_mesh))
    opti.set_initial(tau, tau_ref)
    opti.solver("ipopt", {**ipopt_opts(1.0), "expand": expand})
    build = time.perf_counter() - t_build
    t0 = time.perf_counter()
    sol = opti.solve()
    solve = time.perf_counter() - t0
    st = sol.stats()
    return {"tau": float(sol.value(tau)), "X": np.array(sol.value(X)), "iterations": st["iter_count"],
            "build_s": build, "solve_s": solve, "status": st["return_status"]}


def bench_min_time(lines):
    md = cp.build()
    ref = cp.reference(md)
    clear_caches()
    t0 = time.perf_counter()
    inv = minimum_time(md, ref, bounds=Bounds(u=1.0), N=N_CART)
    cold = time.perf_counter() - t0
    t0 = time.perf_counter()
    inv = minimum_time(md, ref, bounds=Bounds(u=1.0), N=N_CART)
    warm = time.perf_counter() - t0
    d, ft = inv.diagnostics, inv.diagnostics["free_time"]
    lines.append("2. cart-pole, |F| <= 1 N, minimum duration of the reference's shape (exact tracking), "
                 f"HS N = {N_CART}")
    lines.append(f"   invctl: {d['status']}, {d['iterations']} iterations (structured exact Hessian), duration "
                 f"{ft['duration']:.10f} s; first call {cold:.2f} s, repeated call {warm:.2f} s (solve "
                 f"{d['solve_s']:.2f} s)")
    rows = [("invctl", cold, warm, d["iterations"], ft["duration"], 0.0)]
    for expand in (False, True):
        r = opti_min_time(md, ref, inv, expand=expand)
        dx = float(np.max(np.abs(r["X"] - inv.X_mesh)))
        name = "Opti expand=True" if expand else "Opti (MX, AD Hessian)"
        lines.append(f"   {name}: {r['status']}, {r['iterations']} iterations, duration {r['tau']:.10f} s (rel. diff "
                     f"{abs(r['tau'] / ft['duration'] - 1):.1e}), max |X - X_invctl| {dx:.1e}; build "
                     f"{r['build_s']:.2f} s, solve {r['solve_s']:.2f} s")
        rows.append((name, r["build_s"] + r["solve_s"], r["solve_s"], r["iterations"], r["tau"], dx))
    return rows


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


def table(lines, title, rows):
    base_cold, base_warm = rows[0][1], rows[0][2]
    lines.append(f"   {title}")
    lines.append("   formulation               total_s  solve_s   iter   total/invctl_first  solve/invctl_repeat")
    for name, total, solve, it, _opt, _dx in rows:
        lines.append(f"   {name:24s} {total:8.2f} {solve:8.2f} {it:6d} {total / base_cold:16.2f}x "
                     f"{solve / base_warm:17.2f}x")


def main():
    lines = [f"bench_ocp: invctl bounded inversion / minimum time vs the same problems in CasADi Opti "
             f"(casadi {ca.__version__}; {'smoke' if SMOKE else 'full'} run)", ""]
    rows = bench_bounded(lines)
    table(lines, "times (invctl first call includes setup and the exact inverse; Opti total = build + solve)", rows)
    lines.append("")
    rows = bench_min_time(lines)
    table(lines, "times", rows)
    lines.append("")
    tradeoffs(lines)
    text = "\n".join(lines)
    print(text)
    if not SMOKE:
        with open(__file__.replace(".py", "_output.txt"), "w") as fh:
            fh.write(text + "\n")


if __name__ == "__main__":
    main()
