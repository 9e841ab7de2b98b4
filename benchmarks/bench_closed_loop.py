"""Closed-loop wall time of the manipulator (003 Sect. 6, 2 s, mismatched plant m3 x 1.2).

Compiled: plant (Baumgarte index-1 DAE), funnel controller (48), feedforward spline and reference in
one CasADi graph driving CVODES (exact Jacobian by AD).  Peer: scipy ``solve_ivp`` (LSODA, the
method of the reference prototype) on a Python right-hand side that calls the model's index-1
function and the controller's compiled output per evaluation.  Both in the same run, same tolerances.

    python benchmarks/bench_closed_loop.py [--repeat 5] [--no-ff] [--smoke]

``--smoke`` (alias ``--quick``): one run of each loop (checks that the benchmark runs; its numbers
are not the benchmark's).

Target (issue 4): C1 in <= 0.1 s wall (the prototype: 0.53 s C1, 0.15 s C2 with LSODA).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("MPLBACKEND", "Agg")

import invctl_scenes.manipulator as scene  # noqa: E402
from invctl.simulate.closed_loop import scipy_reference_run  # noqa: E402
from invctl.studies.tracking import setup_tracking  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
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
    rows = []
    for name in controllers:
        loop = setup.loop(name)
        loop_tol = type(loop)(setup.plant, setup.reference, controller=loop.controller, u_ff=loop.u_ff_fn,
                              signals=setup.signals, t_end=setup.t_end, dt=setup.dt, name=name,
                              rtol=args.rtol, atol=args.rtol * 1e-2)
        walls = []
        for _ in range(args.repeat):
            res = loop_tol.run(setup.q0, controller_label=name)
            walls.append(res.wall_s)
        uff = setup.u_ff_samples() if name == "C1" else None
        t, X, wall_sp, nfev = scipy_reference_run(loop_tol, setup.q0, method="LSODA", rtol=args.rtol,
                                                  atol=args.rtol * 1e-2, u_ff=uff)
        diff = np.abs(X[:10] - np.vstack([res.q, res.v])).max()
        rows.append((name, min(walls), np.median(walls), wall_sp, nfev, diff, res.cumulative_output_error))
    print(f"\n2 s closed loop, rtol {args.rtol:g}, output grid {setup.dt:g} s")
    print(f"{'':4s} {'compiled min [s]':>17s} {'median':>8s} {'scipy LSODA [s]':>16s} {'nfev':>6s} "
          f"{'speed-up':>9s} {'max |dx|':>9s} {'cum. err':>9s}")
    for name, wmin, wmed, wsp, nfev, diff, cum in rows:
        print(f"{name:4s} {wmin:17.4f} {wmed:8.4f} {wsp:16.3f} {nfev:6d} {wsp / wmin:8.1f}x {diff:9.2g} {cum:9.4g}")
    return rows


if __name__ == "__main__":
    main()
