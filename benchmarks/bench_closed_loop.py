"""Closed-loop wall time of the manipulator (003 Sect. 6, 2 s, mismatched plant m3 x 1.2).

invctl: plant (Baumgarte index-1 DAE), funnel controller (48), feedforward spline and reference in
one CasADi graph driving CVODES (exact Jacobian by AD), the whole ``ClosedLoop.run`` call timed
(integration, monitor outputs, funnel and region checks, result).  Peer: what a competent user would
write: the SAME closed-loop right-hand side as ONE CasADi Function (expanded to SX) plus its Jacobian as
one Function, called by scipy ``solve_ivp(method="LSODA", jac=...)`` on the same output grid, same
tolerances (the whole ``solve_ivp`` call; it returns the states only).  Rounds interleave invctl and the
peer; min and median of each; building either side is reported beside.

    python benchmarks/bench_closed_loop.py [--repeat 7] [--no-ff] [--smoke]

``--smoke`` (alias ``--quick``): one round (checks that the benchmark runs; its numbers are not the
benchmark's).

Goal (issue 20): the 2 s loop >= 5x faster than the peer.  See the output file for the ratios reached and
what limits them.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import casadi as ca
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("MPLBACKEND", "Agg")

import invctl_scenes.manipulator as scene  # noqa: E402
from invctl.studies.tracking import setup_tracking  # noqa: E402


def fused_peer(loop, theta):
    """``(fun, jac)`` for ``solve_ivp``: the loop's whole right-hand side (plant + controller + feedforward +
    reference) as one expanded CasADi Function of ``(t, x)`` and its Jacobian in ``x`` as another."""
    dae = loop.dae
    ode = ca.substitute(dae["ode"], dae["p"], ca.DM(np.concatenate([theta, [0.0]])))
    f = ca.Function("cl_rhs", [dae["t"], dae["x"]], [ode]).expand()
    jf = ca.Function("cl_rhs_jac", [dae["t"], dae["x"]], [ca.jacobian(ode, dae["x"])]).expand()
    return (lambda t, x: np.asarray(f(t, x)).ravel()), (lambda t, x: np.asarray(jf(t, x)))


def peer_run(loop, fun, jac, x0, rtol, atol):
    from scipy.integrate import solve_ivp

    t_eval = np.linspace(0.0, loop.t_end, loop.n_steps + 1)
    sol = solve_ivp(fun, (0.0, loop.t_end), x0, method="LSODA", rtol=rtol, atol=atol, t_eval=t_eval, jac=jac)
    if not sol.success:
        raise RuntimeError(f"peer: {sol.message}")
    return sol


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--no-ff", action="store_true", help="skip C1 (no inversion)")
    ap.add_argument("--rtol", type=float, default=1e-6)
    ap.add_argument("--smoke", "--quick", action="store_true", help="one run each: checks that the benchmark runs")
    args = ap.parse_args(argv)
    if args.smoke:
        args.repeat = 1
    controllers = ["C2"] if args.no_ff else ["C1", "C2"]
    t0 = time.perf_counter()
    setup = setup_tracking(scene.SCENE, invert=not args.no_ff, progress=True)
    print(f"setup (analysis, controller, inversion): {time.perf_counter() - t0:.2f} s  {setup.timings}")
    rows, backends = [], []
    atol = args.rtol * 1e-2
    for name in controllers:
        loop = setup.loop(name)
        tic = time.perf_counter()
        loop_tol = type(loop)(setup.plant, setup.reference, controller=loop.controller, u_ff=loop.u_ff_fn,
                              signals=setup.signals, t_end=setup.t_end, dt=setup.dt, name=name,
                              rtol=args.rtol, atol=atol)
        build = time.perf_counter() - tic
        theta = setup.plant.theta_values
        tic = time.perf_counter()
        fun, jac = fused_peer(loop_tol, theta)
        build_peer = time.perf_counter() - tic
        backends.append((loop_tol.rhs_backend, "c" if loop_tol.monitor.class_name() == "External" else "vm"))
        res = loop_tol.run(setup.q0, controller_label=name)  # first call (not timed: both sides warm)
        x0 = np.concatenate([res.q[:, 0], res.v[:, 0], res.z[:, 0]])
        sol = peer_run(loop_tol, fun, jac, x0, args.rtol, atol)
        walls, walls_sp = [], []
        for _ in range(args.repeat):  # interleaved rounds, whole calls
            tic = time.perf_counter()
            res = loop_tol.run(setup.q0, controller_label=name)
            walls.append(time.perf_counter() - tic)
            tic = time.perf_counter()
            sol = peer_run(loop_tol, fun, jac, x0, args.rtol, atol)
            walls_sp.append(time.perf_counter() - tic)
        diff = np.abs(sol.y - np.vstack([res.q, res.v, res.z])).max()
        rows.append((name, min(walls), np.median(walls), min(walls_sp), np.median(walls_sp), sol.nfev, sol.njev,
                     diff, res.cumulative_output_error, build, build_peer))
    print(f"\n2 s closed loop, rtol {args.rtol:g}, atol {atol:g}, output grid {setup.dt:g} s, {args.repeat} interleaved "
          "rounds, whole calls")
    print(f"{'':4s} {'invctl min [s]':>15s} {'median':>8s} {'peer min [s]':>13s} {'median':>8s} {'nfev':>5s} "
          f"{'njev':>5s} {'speed-up':>9s} {'max |dx|':>9s} {'cum. err':>9s} {'build [s]':>9s} {'peer build':>10s}")
    for name, wmin, wmed, smin, smed, nfev, njev, diff, cum, build, build_peer in rows:
        print(f"{name:4s} {wmin:15.4f} {wmed:8.4f} {smin:13.4f} {smed:8.4f} {nfev:5d} {njev:5d} {smin / wmin:8.1f}x "
              f"{diff:9.2g} {cum:9.4g} {build:9.3f} {build_peer:10.3f}")
    print("speed-up: peer min / invctl min (peer: scipy LSODA on one fused CasADi right-hand side + its Jacobian)")
    print("invctl right-hand side and monitor: " + ", ".join(f"{r[0]} {b}/{m}" for r, (b, m) in zip(rows, backends))
          + " (c = generated C from the disk cache, vm = SX virtual machine: a graph's first run compiles it in "
          "the background)")
    return rows


if __name__ == "__main__":
    main()
