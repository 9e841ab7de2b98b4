"""Trajectory-library throughput: 100 manipulator transitions (a 10 x 10 grid of end points).

The manipulator runs on its former default parameters (``--preset guess``: m3 = 0.5, c = 5, D = 0.05), on which
the committed output was measured (the scene's defaults are now the identified set of 003 Sect. 6).

The end point ``rf`` of the end-effector path of 003 Sect. 6 runs over ``[0.8, 1.0] x [-0.9, -0.7]`` m.
The base inversion is refined to a forward-check error of 1e-6 (Hermite-Simpson); every point is solved
on that discretization and afterwards forward-checked (an independent CVODES simulation of the model
under the point's feedforward).  Printed:

* warm-started library (continuation from solved neighbours, Newton on the collocation system compiled
  to C once per machine), in this process; the same in CasADi's virtual machine (``compiled=False``);
* the same library with every point from its quasi-static guess (``continuation=False``);
* ``invert()`` per point from its quasi-static guess (what a script without the library does) on a
  subset of the points, same mesh and boundary selection;
* the warm library on a local process pool (2 workers);
* agreement of the warm and cold libraries, and the forward-check error of all 100 points.

Timings are the best of two runs (the machine is shared; the load average is printed).  ``traj/s`` is
points over the wall time of the library; ``CPU traj/s`` points over the CPU time the solving processes
spent on them (what an otherwise idle core would deliver; less sensitive to the other load).

    python benchmarks/bench_generate.py [--smoke]

``--smoke`` (alias ``--quick``): a 2 x 2 grid, one run each (checks that the benchmark runs; its
numbers are not the benchmark's).
"""
from __future__ import annotations

import os
import sys
import time

import numpy as np

import invctl_scenes.manipulator as scene
from invctl.inversion import forward_check, invert
from invctl.studies.library import generate

SMOKE = bool({"--smoke", "--quick"} & set(sys.argv[1:]))
GRID = ["rf[0]=0.8:1.0:10", "rf[1]=-0.9:-0.7:10"] if not SMOKE else ["rf[0]=0.8:1.0:2", "rf[1]=-0.9:-0.7:2"]
ROUNDS = 1 if SMOKE else 2
TOL = 1e-6


def best_of(k, fn):
    out = []
    for _ in range(k):
        t0 = time.perf_counter()
        lib = fn()
        out.append((time.perf_counter() - t0, lib))
    return min(out, key=lambda x: x[1].info["solve_wall_s"])


def main():
    print(f"load average at start: {', '.join(f'{x:.2f}' for x in os.getloadavg())} (2 cores, shared)")
    common = dict(tol=TOL, verify="none", progress=False, params=dict(scene.PRESETS["guess"]))
    _, warm = best_of(ROUNDS, lambda: generate("manipulator", GRID, executor="serial", **common))
    _, cold = best_of(ROUNDS, lambda: generate("manipulator", GRID, executor="serial", continuation=False, **common))
    _, warm_vm = best_of(ROUNDS, lambda: generate("manipulator", GRID, executor="serial", compiled=False, **common))
    P = len(warm.status)
    b = warm.info["base"]
    print(f"{P} points, grid {' x '.join(GRID)}; base: {b['scheme']} N = {b['N']} (refined to forward-check error "
          f"{b['max_output_error']:.2g} <= {TOL:g}), horizon [{b['T0']:g}, {b['Tf']:g}]")
    rows = []
    print(f"Newton's residual and Jacobian: compiled {warm.info['compiled']} (C compile {warm.info['compile_s']:.2f} s "
          "in this run; 0 once cached on disk)")
    for name, lib in (("library, warm starts (continuation)", warm), ("library, quasi-static starts", cold)):
        it = lib.stats["iterations"]
        rows.append((name, lib.counts()["solved"], lib.info["solve_wall_s"], lib.info["points_per_s"],
                     f"{np.nanmedian(it):.0f}", f"{np.nanmedian(lib.stats['factorizations']):.0f}",
                     P / np.nansum(lib.stats["cpu_s"])))
    # invert() per point, from its own guess, on the same mesh and selection
    model = scene.build(**scene.PRESETS["guess"])
    sub = list(range(0, P, max(1, P // 20)))
    t_inv = c_inv = 0.0
    its = []
    for i in sub:
        pt = warm.points[i]
        ref = scene.reference(model, rf=(pt["rf[0]"], pt["rf[1]"]))
        w = warm.inverse(i)
        t0, c0 = time.perf_counter(), time.process_time()
        inv = invert(model, ref, T0=w.T0, Tf=w.Tf, mesh=w.t_mesh, start=scene.BOUNDARY["start"],
                     end=scene.BOUNDARY["end"], backend="newton", q_guess=scene.initial_configuration(model))
        t_inv += time.perf_counter() - t0
        c_inv += time.process_time() - c0
        its.append(inv.diagnostics["iterations"])
    rows.append((f"invert() per point ({len(sub)} of the points)", len(sub), t_inv, len(sub) / t_inv,
                 f"{np.median(its):.0f}", "-", len(sub) / c_inv))
    vm_row = ("library, warm starts, virtual machine", warm_vm.counts()["solved"], warm_vm.info["solve_wall_s"],
              warm_vm.info["points_per_s"], f"{np.nanmedian(warm_vm.stats['iterations']):.0f}",
              f"{np.nanmedian(warm_vm.stats['factorizations']):.0f}", P / np.nansum(warm_vm.stats["cpu_s"]))
    _, pool = best_of(1, lambda: generate("manipulator", GRID, max_workers=2, **common))
    rows.append(("library, warm starts, process pool (2)", pool.counts()["solved"], pool.info["solve_wall_s"],
                 pool.info["points_per_s"], f"{np.nanmedian(pool.stats['iterations']):.0f}",
                 f"{np.nanmedian(pool.stats['factorizations']):.0f}", P / np.nansum(pool.stats["cpu_s"]) * 2))
    head = (f"{'':42s} {'solved':>6s} {'wall s':>7s} {'traj/s':>7s} {'CPU traj/s':>10s} {'Newton it':>9s} "
            f"{'LU':>3s}")
    print(head)
    print("-" * len(head))
    for r in rows + [vm_row]:
        print(f"{r[0]:42s} {r[1]:6d} {r[2]:7.2f} {r[3]:7.1f} {r[6]:10.1f} {r[4]:>9s} {r[5]:>3s}")
    print("(process pool: CPU traj/s of its 2 workers together)")
    rate_w, rate_c, rate_i = rows[0][3], rows[1][3], rows[2][3]
    cpu_w, cpu_c, cpu_i = rows[0][6], rows[1][6], rows[2][6]
    print(f"warm / quasi-static starts (same pipeline): {rate_w / rate_c:.1f}x wall, {cpu_w / cpu_c:.1f}x CPU;  "
          f"warm / invert() per point: {rate_w / rate_i:.1f}x wall, {cpu_w / cpu_i:.1f}x CPU;  "
          f"process pool / serial: {rows[3][3] / rate_w:.1f}x wall;  compiled / virtual machine: "
          f"{rate_w / vm_row[3]:.1f}x wall, {cpu_w / vm_row[6]:.1f}x CPU")
    # the same solutions, and their accuracy
    t = np.linspace(b["T0"], b["Tf"], 601)
    diff = max(np.max(np.abs(warm.inverse(i).u(t) - cold.inverse(i).u(t))) for i in range(P))
    print(f"warm vs quasi-static library: max |u_ff difference| = {diff:.2g} N (both Newton to max |g| < 1e-10)")
    diff = max(np.max(np.abs(warm.inverse(i).u(t) - warm_vm.inverse(i).u(t))) for i in range(P))
    print(f"compiled vs virtual machine library: max |u_ff difference| = {diff:.2g} N")
    t0 = time.perf_counter()
    errs = np.array([forward_check(model, warm.inverse(i), scene.reference(
        model, rf=(warm.points[i]["rf[0]"], warm.points[i]["rf[1]"])))["error"] for i in range(P)])
    k = int(np.argmax(errs))
    print(f"forward check of all {P} points ({time.perf_counter() - t0:.1f} s): max error {errs[k]:.3g} at "
          f"{warm.points[k]}, median {np.median(errs):.3g}; {int(np.sum(errs <= TOL))} of {P} <= {TOL:g}")
    print(f"targets: warm starts >= 5x: {cpu_w / cpu_c:.1f}x (CPU) against quasi-static starts in the library, "
          f"{cpu_w / cpu_i:.1f}x (CPU) against invert() per point; >= 50 trajectories/s (Newton, no bounds): "
          f"{rate_w:.0f}/s wall ({cpu_w:.0f}/s CPU) in one process, {rows[3][3]:.0f}/s wall on 2 processes")
    print(f"load average at end: {', '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
