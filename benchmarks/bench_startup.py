"""Start-up time of ``invctl analyze/invert/simulate`` per scene, against ``python -c "import numpy"``.

Each command runs in a fresh process; we measure the time from process start to
its first output (first byte on stdout or stderr: a progress line or the
report) and to its end, best of ``--repeat`` runs, and print both as ratios
to the peer baseline measured in the same run: a fresh Python importing numpy
(the least any numerical command line pays).  ``import casadi`` is printed too,
as the floor of anything built on CasADi.

Run: python benchmarks/bench_startup.py [--repeat 3] [--smoke]

``--smoke`` (alias ``--quick``): two commands, one run each (checks that the benchmark runs; its numbers
are not the benchmark's).
"""
from __future__ import annotations

import argparse
import os
import selectors
import subprocess
import sys
import time
from pathlib import Path

INVCTL = [sys.executable, "-m", "invctl.cli"]

COMMANDS = [
    ("analyze", "cartpole", []),
    ("analyze", "two_link_arm", []),
    ("analyze", "knife_edge", []),
    ("analyze", "manipulator", []),
    ("analyze", "stiff_wall", []),
    ("analyze", "compliant_wrist", []),
    ("invert", "manipulator", []),
    ("simulate", "bouncing_ball", []),
    ("simulate", "prismatic_clearance", []),
    ("simulate", "gear_backlash", []),
    ("simulate", "slider_crank_clearance", []),
    ("simulate", "stiff_wall", []),
    ("simulate", "compliant_wrist", []),
    ("simulate", "manipulator", ["--controller", "C2"]),
]
SMOKE = {("analyze", "cartpole"), ("simulate", "bouncing_ball")}


def first_output(argv, timeout=300.0) -> tuple[float, float, int]:
    """(seconds to the first output byte, seconds to exit, return code) of a fresh process
    (a process with no output counts its exit as its first output)."""
    env = {**os.environ, "MPLBACKEND": "Agg"}
    t0 = time.perf_counter()
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
                            cwd=Path(__file__).resolve().parents[1])
    sel = selectors.DefaultSelector()
    sel.register(proc.stdout, selectors.EVENT_READ)
    sel.register(proc.stderr, selectors.EVENT_READ)
    t_first = None
    open_streams = 2
    while open_streams:
        if time.perf_counter() - t0 > timeout:
            proc.kill()
            raise TimeoutError(f"{argv} took more than {timeout} s")
        for key, _ in sel.select(timeout=1.0):
            chunk = os.read(key.fileobj.fileno(), 65536)
            if not chunk:
                sel.unregister(key.fileobj)
                open_streams -= 1
            elif t_first is None:
                t_first = time.perf_counter() - t0
    rc = proc.wait()
    t_end = time.perf_counter() - t0
    return (t_end if t_first is None else t_first), t_end, rc


def best(argv, repeat):
    runs = [first_output(argv) for _ in range(repeat)]
    return min(r[0] for r in runs), min(r[1] for r in runs), max(r[2] for r in runs)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--smoke", "--quick", action="store_true",
                    help="two commands, one run: checks that the benchmark runs")
    args = ap.parse_args(argv)
    if args.smoke:
        args.repeat = 1
    base = min(first_output([sys.executable, "-c", "import numpy"])[1] for _ in range(args.repeat))
    floor, _, _ = best([sys.executable, "-c", "import casadi"], args.repeat)
    help_first, _, _ = best(INVCTL + ["--help"], args.repeat)
    print(f"peer baseline: python -c 'import numpy'  {base * 1e3:8.1f} ms")
    print(f"floor:         python -c 'import casadi' {floor * 1e3:8.1f} ms ({floor / base:.1f}x numpy)")
    print(f"invctl --help                            {help_first * 1e3:8.1f} ms ({help_first / base:.1f}x numpy)")
    print("\nper command: best of the runs, each run right after a baseline run (the ratio uses the")
    print("best baseline of the same window, so load from other processes hits both alike)")
    print(f"{'command':<36} {'first output':>14} {'x numpy':>8} {'total':>10} {'x numpy':>8} {'numpy':>9}  rc")
    for cmd, scene, extra in COMMANDS:
        if args.smoke and (cmd, scene) not in SMOKE:
            continue
        b, runs = [], []
        for _ in range(args.repeat):
            b.append(first_output([sys.executable, "-c", "import numpy"])[1])
            runs.append(first_output(INVCTL + [cmd, scene, *extra]))
        first, total, rc = min(r[0] for r in runs), min(r[1] for r in runs), max(r[2] for r in runs)
        base = min(b)
        label = " ".join([cmd, scene, *extra])
        print(f"{label:<36} {first * 1e3:11.1f} ms {first / base:8.1f} {total:8.2f} s {total / base:8.1f} "
              f"{base * 1e3:6.0f} ms  {rc}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
