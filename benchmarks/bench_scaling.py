"""Scaling of analysis, inversion and closed loop with the size of the model (issue 11, "Performance").

The n-link flexible arm (invctl_scenes/flexible_arm.py) for n = 2, 4, 8, 16, 32, each n in a fresh
process (cold caches, its own peak memory), at fixed accuracy: the automatic inversion setup (plan
tails 1e-8, Hermite-Simpson, N = 200 on the graded mesh) and a 2 s closed loop (C1: feedforward +
funnel on the plant with 20 % heavier links).  Per n it prints the wall time of

  analysis     model, plant, internal dynamics (003 Sect. 3) and their linearization, funnel design
  inversion    invert(): plan (selection, horizon), servo model, transcription, IPOPT
  closed loop  build and run of C1 over [0, 2] s

with the breakdown of the inversion (build / equilibria and guess / solve, IPOPT iterations), the
peak memory of the process, the forward-check error of the inverse (the accuracy that is held
fixed), the funnel margin of C1 and the size of the servo ODE's Jacobian (SX instructions); then the
growth exponents fitted in n (least squares of log time over log n, all n and n >= 8).  Timing is
wall time on a shared machine (single runs vary by up to 70 % at n = 32 under load): each n runs
``--repeat`` times and the fastest run is kept.

Both formulations of the arm are measured (``--coordinates angles|cartesian|both``, default both):
absolute link angles (dense M(q), O(n^2) Jacobian entries per node) and Cartesian coordinates with
pin constraints (``--set coordinates=cartesian``: constant diagonal M, 2n constraints, O(n) entries
in the model's Jacobians, but dense (8n + 1)^2 blocks per node in the index-reduced inverse model that
the inversion collocates; the scene limits it to n <= 10, so larger n are reported as rejected); with ``both`` every n runs both in turn, and a last table gives the ratio of their
inversion times in the same run.  ``--pivot-order K`` passes ``ipopt.mumps_pivot_order = K`` to the
inversion (MUMPS ordering: 0 AMD, the project default for square systems; 2 AMF; 4 PORD; 5 METIS
and 3 SCOTCH when MUMPS was built with them; 6 QAMD; 7 automatic).

    python benchmarks/bench_scaling.py [--n 2 4 8] [--repeat 2] [--timeout 600]
                                       [--coordinates angles|cartesian|both] [--pivot-order K]
                                       [--max-memory-gb 8] [--smoke] [--robots NAME ...]
                                       [--robot-dynamics newton-euler|lagrangian|both]

``--smoke`` (alias ``--quick``): n = 2, both formulations, one run each (checks that the benchmark runs;
its numbers are not the benchmark's).

Robots from URDF (``--robots``, default ``ur5_elastic``; ``acrobot`` with ``--smoke``): the inversion time of
the scene built from a robot description (docs/robots.md) beside the hand-written flexible arm with as many
coordinates (angles, same run; the arm has one input, the UR5 five), fastest of ``--repeat`` runs each, with
the SX sizes of M, f and the servo ODE's Jacobian.  ``--robot-dynamics newton-euler|lagrangian|both`` chooses
how the URDF model forms M and f (default newton-euler, what the scenes use; both: one line each).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

import numpy as np

NS = (2, 4, 8, 16, 32)


def worker(n: int, coordinates: str = "angles", pivot_order: int | None = None) -> dict:
    from invctl.inversion import forward_check
    from invctl.inversion import servo_model
    from invctl.scenes import load_scene
    from invctl.studies.tracking import invert_tracking, run_controller, setup_tracking

    scene = load_scene("flexible_arm")
    out = {"n": n, "coordinates": coordinates}
    params = {"n": n} if coordinates == "angles" else {"n": n, "coordinates": coordinates}
    options = {} if pivot_order is None else {"ipopt_options": {"ipopt.mumps_pivot_order": pivot_order}}
    t = time.perf_counter()
    setup = setup_tracking(scene, params, invert=False)
    out["analysis_s"] = time.perf_counter() - t
    out["analysis_parts"] = {k: setup.timings[k] for k in ("analysis", "controller")}
    t = time.perf_counter()
    inv = invert_tracking(scene, setup.model, setup.reference, **options)
    setup.inverse = inv
    out["inversion_s"] = time.perf_counter() - t
    d = inv.diagnostics
    out["inversion_parts"] = {"build_s": d["build_s"], "guess_s": d["guess_s"], "solve_s": d["solve_s"],
                              "iterations": d["iterations"], "T0": d["T0"], "Tf": d["Tf"], "N": d["N"]}
    out["inversion_parts"]["plan_and_rest_s"] = out["inversion_s"] - d["build_s"] - d["guess_s"] - d["solve_s"]
    t = time.perf_counter()
    loop = setup.loop("C1")
    build = time.perf_counter() - t
    res = run_controller(setup, "C1")
    out["closed_loop_s"] = time.perf_counter() - t
    out["closed_loop_parts"] = {"build_s": build, "run_s": res.wall_s, "t_end": float(res.t[-1])}
    out["funnel_ratio"] = res.max_funnel_ratio
    out["status"] = res.status
    out["steps"] = loop.integrator.stats().get("nsteps")
    t = time.perf_counter()
    fc = forward_check(setup.model, inv, setup.reference)
    out["forward_check_s"] = time.perf_counter() - t
    out["forward_error"] = fc["error"]
    servo = servo_model(setup.model, "baumgarte", 10.0)
    out["rhs_jac_instructions"] = servo.rhs_jac.n_instructions()
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return out


def robot_worker(name: str, dynamics: str = "newton-euler") -> dict:
    """Inversion of a scene built from a URDF (the automatic setup, like the arm's), its model formed by
    ``dynamics`` (Robot.model's default for this process), with the sizes of M, f and the servo Jacobian."""
    from invctl.inversion import forward_check
    from invctl.inversion import servo_model
    from invctl.model.urdf import Robot
    from invctl.scenes import load_scene
    from invctl.studies.tracking import invert_tracking, tracking_model

    Robot.model.__kwdefaults__["dynamics"] = dynamics
    scene = load_scene(name)
    t = time.perf_counter()
    model, ref = tracking_model(scene, {})
    out = {"scene": name, "dynamics": dynamics, "n": model.n, "m": model.m, "model_s": time.perf_counter() - t}
    out.update({f"{k}_instructions": model.function(k).n_instructions() for k in ("M", "f")})
    out["rhs_jac_instructions"] = servo_model(model, "baumgarte", 10.0).rhs_jac.n_instructions()
    t = time.perf_counter()
    inv = invert_tracking(scene, model, ref)
    out["inversion_s"] = time.perf_counter() - t
    out["iterations"] = inv.diagnostics["iterations"]
    out["forward_error"] = forward_check(model, inv, ref)["error"]
    return out


def _limit_memory(gb: float):
    """A ``preexec_fn`` capping the worker's address space (a MemoryError in the worker instead of the
    kernel's OOM killer acting on the whole machine: the cartesian n = 16 run reached 22 GB)."""
    def apply():
        limit = int(gb * 2**30)
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    return apply


def run_worker(n: int, timeout: float, coordinates: str = "angles", pivot_order: int | None = None,
               max_memory_gb: float = 8.0, robot_dynamics: str = "newton-euler") -> dict:
    """One fresh process for ``n``; its result dict, or ``{"n", "error"}``."""
    t = time.perf_counter()
    cmd = [sys.executable, __file__, "--worker", str(n), "--coordinates", coordinates]
    if isinstance(n, str):
        cmd = [sys.executable, __file__, "--robot-worker", n, "--robot-dynamics", robot_dynamics]
    if pivot_order is not None:
        cmd += ["--pivot-order", str(pivot_order)]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=dict(os.environ),
                              preexec_fn=_limit_memory(max_memory_gb) if max_memory_gb > 0 else None)
        line = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
        if not line:
            why = proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else "no output"
            raise RuntimeError(f"no result (exit code {proc.returncode}: {why}) after {time.perf_counter() - t:.0f} s")
        return json.loads(line[0][7:])
    except subprocess.TimeoutExpired:
        return {"n": n, "error": f"not finished in {timeout:.0f} s"}
    except RuntimeError as exc:
        return {"n": n, "error": str(exc)}


def fit(ns, ts) -> float:
    ns, ts = np.asarray(ns, float), np.asarray(ts, float)
    ok = np.isfinite(ts) & (ts > 0)
    if ok.sum() < 2:
        return float("nan")
    return float(np.polyfit(np.log(ns[ok]), np.log(ts[ok]), 1)[0])


def report(rows: list[dict], coordinates: str) -> None:
    """Breakdown and fitted exponents of one formulation's rows."""
    done = [r for r in rows if "error" not in r]
    if not done:
        return
    print(f"\n[{coordinates}] where the time goes (s): analysis = [model, plant, internal dynamics, linearization | "
          "funnel design]; inversion = [plan and equilibria | build | guess | IPOPT solve]; closed loop = [build | run]")
    for r in done:
        a, i, c = r["analysis_parts"], r["inversion_parts"], r["closed_loop_parts"]
        print(f"{r['n']:3d}  analysis [{a['analysis']:.2f} | {a['controller']:.2f}]  inversion "
              f"[{i['plan_and_rest_s']:.2f} | {i['build_s']:.2f} | {i['guess_s']:.2f} | {i['solve_s']:.2f}, "
              f"{i['iterations']} it, horizon [{i['T0']:.2f}, {i['Tf']:.2f}]]  closed loop [{c['build_s']:.2f} | "
              f"{c['run_s']:.2f}]  (forward check {r['forward_check_s']:.2f})")
    ns = [r["n"] for r in done]
    print(f"\n[{coordinates}] fitted growth exponents (time ~ n^p), least squares of log t over log n:")
    for r in done:
        r["solve_per_iteration_s"] = r["inversion_parts"]["solve_s"] / max(1, r["inversion_parts"]["iterations"])
    for key, label in (("analysis_s", "analysis"), ("inversion_s", "inversion"),
                       ("solve_per_iteration_s", "IPOPT per iteration"), ("closed_loop_s", "closed loop"),
                       ("rhs_jac_instructions", "servo Jacobian size")):
        vals = [r[key] for r in done]
        big = [(n, v) for n, v in zip(ns, vals) if n >= 8]
        tail = fit(*zip(*big)) if len(big) >= 2 else float("nan")
        print(f"  {label:20s} p = {fit(ns, vals):5.2f} (all n), {tail:5.2f} (n >= 8)")
    totals = {r["n"]: r["analysis_s"] + r["inversion_s"] + r["closed_loop_s"] for r in done}
    if 32 in totals:
        print(f"\n[{coordinates}] n = 32: analysis + inversion + closed loop = {totals[32]:.1f} s (target < 60 s)")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, nargs="*", default=list(NS))
    ap.add_argument("--timeout", type=float, default=600.0,
                    help="seconds per process; a formulation that does not finish skips its larger n")
    ap.add_argument("--repeat", type=int, default=2, help="runs per n; the fastest (total) is kept")
    ap.add_argument("--coordinates", choices=("angles", "cartesian", "both"), default="both",
                    help="formulation of the arm (both: each n in both, ratio of inversion times)")
    ap.add_argument("--pivot-order", type=int, default=None,
                    help="ipopt.mumps_pivot_order of the inversion (default: the project's, 0 = AMD)")
    ap.add_argument("--max-memory-gb", type=float, default=8.0,
                    help="address-space limit of each worker process (0: none); a formulation that exceeds it "
                         "skips its larger n")
    ap.add_argument("--robots", nargs="*", default=None,
                    help="scenes from URDF whose inversion time is compared (default ur5_elastic; acrobot with --smoke)")
    ap.add_argument("--worker", type=int, default=None)
    ap.add_argument("--robot-worker", default=None)
    ap.add_argument("--robot-dynamics", choices=("newton-euler", "lagrangian", "both"), default="newton-euler",
                    help="how the URDF scenes' M and f are formed (both: one line each)")
    ap.add_argument("--smoke", "--quick", action="store_true", help="n = 2, one run: checks that the benchmark runs")
    args = ap.parse_args()
    if args.smoke:
        args.n, args.repeat = [2], 1
    if args.robots is None:
        args.robots = ["acrobot"] if args.smoke else ["ur5_elastic"]
    if args.robot_worker is not None:
        print("RESULT " + json.dumps(robot_worker(args.robot_worker, args.robot_dynamics)))
        return
    if args.worker is not None:
        coords = "angles" if args.coordinates == "both" else args.coordinates
        print("RESULT " + json.dumps(worker(args.worker, coords, args.pivot_order)))
        return
    forms = ("angles", "cartesian") if args.coordinates == "both" else (args.coordinates,)
    rows = {c: [] for c in forms}
    order = "project default (AMD)" if args.pivot_order is None else f"mumps_pivot_order = {args.pivot_order}"
    print("n-link flexible arm (invctl_scenes/flexible_arm.py): analysis, inversion, 2 s closed loop (C1); "
          f"one fresh process per run, fastest of {args.repeat} per n; formulations: {', '.join(forms)}; "
          f"IPOPT/MUMPS ordering: {order}")
    head = (f"{'coordinates':>11s} {'n':>3s} {'analysis':>9s} {'inversion':>10s} {'closed loop':>12s} {'total':>8s} "
            f"{'peak MB':>8s} {'fwd err':>9s} {'C1 phi|e|':>9s} {'iter':>4s} {'jac SX instr':>12s}")
    print(head)
    print("-" * len(head))
    stopped = {}  # formulation -> the n that did not finish (larger n are skipped)
    for n in args.n:
        for c in forms:
            if c in stopped:
                rows[c].append({"n": n, "error": f"skipped (n = {stopped[c]} did not finish)"})
                print(f"{c:>11s} {n:3d}  {rows[c][-1]['error']}", flush=True)
                continue
            t_run = time.perf_counter()
            runs = [run_worker(n, args.timeout, c, args.pivot_order, args.max_memory_gb)
                    for _ in range(max(1, args.repeat))]
            if all("error" in r for r in runs):
                stopped[c] = n
            good = [r for r in runs if "error" not in r]
            r = min(good, key=lambda x: x["analysis_s"] + x["inversion_s"] + x["closed_loop_s"]) if good else runs[0]
            rows[c].append(r)
            if "error" in r:
                print(f"{c:>11s} {n:3d}  {r['error']}", flush=True)
                continue
            total = r["analysis_s"] + r["inversion_s"] + r["closed_loop_s"]
            print(f"{c:>11s} {n:3d} {r['analysis_s']:9.2f} {r['inversion_s']:10.2f} {r['closed_loop_s']:12.2f} "
                  f"{total:8.2f} {r['peak_rss_mb']:8.0f} {r['forward_error']:9.1e} {r['funnel_ratio']:9.3f} "
                  f"{r['inversion_parts']['iterations']:4d} {r['rhs_jac_instructions']:12d}   "
                  f"(wall {time.perf_counter() - t_run:.0f} s for {len(runs)} process(es))", flush=True)
    for c in forms:
        report(rows[c], c)
    if len(forms) == 2:
        print("\ninversion time, angles / cartesian (same run):")
        for ra, rc in zip(rows["angles"], rows["cartesian"]):
            if "error" in ra or "error" in rc:
                print(f"  n = {ra['n']:3d}: -")
                continue
            print(f"  n = {ra['n']:3d}: {ra['inversion_s']:7.2f} s / {rc['inversion_s']:7.2f} s = "
                  f"{ra['inversion_s'] / rc['inversion_s']:6.2f}   (IPOPT solve {ra['inversion_parts']['solve_s']:.2f} / "
                  f"{rc['inversion_parts']['solve_s']:.2f} s)")
    robots(args, rows.get("angles", []))


def robots(args, arm_rows: list[dict]) -> None:
    """The inversion time of the URDF scenes beside the hand-written arm with as many coordinates."""
    if not args.robots:
        return
    print("\nrobots from URDF: inversion time beside the hand-written flexible arm (angles) with as many coordinates")
    kinds = ("lagrangian", "newton-euler") if args.robot_dynamics == "both" else (args.robot_dynamics,)
    for name, dynamics in ((name, k) for name in args.robots for k in kinds):
        runs = [run_worker(name, args.timeout, max_memory_gb=args.max_memory_gb, robot_dynamics=dynamics)
                for _ in range(max(1, args.repeat))]
        good = [r for r in runs if "error" not in r]
        if not good:
            print(f"  {name} ({dynamics}): {runs[0]['error']}")
            continue
        r = min(good, key=lambda x: x["inversion_s"])
        arm = [a for a in arm_rows if a.get("n") == r["n"] and "error" not in a]
        if not arm:
            arm = [a for a in (run_worker(r["n"], args.timeout, "angles", args.pivot_order, args.max_memory_gb)
                               for _ in range(max(1, args.repeat))) if "error" not in a]
            arm_rows.extend(arm)
        a = min(arm, key=lambda x: x["inversion_s"]) if arm else None
        line = (f"  {name} (URDF, n = {r['n']}, m = {r['m']}): inversion {r['inversion_s']:.2f} s ({dynamics}), "
                f"{r['iterations']} it, fwd err {r['forward_error']:.1e}; SX instructions M {r['M_instructions']}, "
                f"f {r['f_instructions']}, servo Jacobian {r['rhs_jac_instructions']}")
        if a is not None:
            line += (f"  |  flexible_arm n = {a['n']} (hand-written, m = 1): {a['inversion_s']:.2f} s, "
                     f"{a['inversion_parts']['iterations']} it, servo Jacobian {a['rhs_jac_instructions']}  |  "
                     f"ratio {r['inversion_s'] / a['inversion_s']:.2f}")
        print(line, flush=True)


if __name__ == "__main__":
    main()
