"""Every benchmark runs: ``benchmarks/bench_*.py --smoke`` in a fresh process exits 0 and prints its
table and ratio lines (the same code paths as the full run, at tiny sizes; the numbers are not
checked, only that they are printed)."""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = sorted((ROOT / "benchmarks").glob("bench_*.py"))
NUM = r"[-+]?(\d+\.?\d*|\.\d+)(e[-+]?\d+)?"

#: per benchmark, lines its output must contain (regular expressions, multi-line mode)
EXPECTED = {
    "bench_analysis": [rf"^  sect3: +{NUM} us per point", rf"ratio sect2 / sect3 = {NUM}",
                       rf"linearization \(2 points\): .* ratio {NUM}"],
    "bench_closed_loop": [r"invctl min \[s\] .* peer min \[s\] .* speed-up", rf"^C1 +{NUM} .* {NUM}x ",
                          rf"^C2 +{NUM} .* {NUM}x ", r"scipy LSODA on one fused CasADi right-hand side"],
    "bench_contacts": [r"contacts +LCP .* numpy Lemke +ratio", rf"^ +2 +pivoting .* {NUM}x ",
                       rf"^ +2 +\d+ +{NUM} +{NUM} +{NUM} +{NUM}x", r"peak RSS MiB", r"record=events +\d+"],
    "bench_generate": [rf"^library, warm starts \(continuation\) +4 +{NUM}", rf"^invert\(\) per point .* {NUM}",
                       rf"compiled / virtual machine: {NUM}x wall", r"4 of 4 <= 1e-06"],
    "bench_inversion": [rf"^radau3 +40 +{NUM}", rf"hermite-simpson +fitted {NUM}", rf"DOP853 +{NUM} ms",
                        r"re-solve with m3 \+ 1 % on the built problem", r"ratios \(ours / scipy",
                        rf"repeated solve >= 10x faster than scipy: Newton {NUM}x", r"Pareto plot: ",
                        rf"^  newton automatic horizon \(re-planned\) *: +{NUM} ms whole call",
                        rf"re-solve after a parameter change vs scipy repeated solve_bvp .*: Newton {NUM}x, IPOPT {NUM}x",
                        rf"first solve in-process vs scipy solve_bvp .*: IPOPT {NUM}x, Newton {NUM}x",
                        rf"at equal accuracy \(the smallest N .*: N = \d+, error {NUM}\): Newton {NUM}x",
                        r"what limits the re-solve: the solve alone. Newton: \d+ simplified iterations",
                        rf"first run on a new machine vs the virtual-machine path \(goal: <= 1\): {NUM}"],
    "bench_ocp": [r"formulation +first_s +re-solve min_s +median_s",
                  rf"^   Opti expand=True +{NUM} +{NUM} +{NUM} +\d+ +{NUM}x +{NUM}x",
                  r"cart-pole time-energy trade"],
    "bench_references": [rf"coefficient selection +\d+ instructions +{NUM} us/time", r"if_else chain +\d+ instr",
                         rf"from_samples N= +400: +{NUM} ms", rf"{NUM} ms/frame"],
    "bench_scaling": [rf"^ +angles +2 +{NUM} +{NUM}", rf"^ +cartesian +2 +{NUM} +{NUM}",
                      rf"n = +2: +{NUM} s / +{NUM} s = +{NUM}",
                      rf"acrobot \(URDF, n = 2, m = 1\): inversion {NUM} s.* ratio {NUM}"],
    "bench_sparse_dae": [rf"^ +2 +{NUM} +{NUM} .*Solve_Succeeded", rf"^ +3 +{NUM} .*Solve_Succeeded",
                         rf"solve_s +p = +{NUM}"],
    "bench_startup": [rf"python -c 'import casadi' +{NUM} ms \({NUM}x numpy\)",
                      rf"^analyze cartpole +{NUM} ms +{NUM} +{NUM} s +{NUM} +\d+ ms +0$"],
    "bench_switched": [rf"ratio +{NUM}x +events [1-9]\d*/[1-9]\d*", r"\(Radau\) exact"],
    "bench_timestepping": [rf"numpy loop +{NUM} steps/s", rf"CasADi VM +{NUM} steps/s +\({NUM}x numpy\)",
                           rf"max \|q_compiled - q_numpy\| over 500 steps: {NUM}",
                           # the numba peer, or the note that it is skipped (numba is in the bench extra only)
                           rf"(^ +1000 +{NUM} +{NUM} +{NUM} +{NUM} +{NUM}x|numba is not installed)"],
}


def test_benchmarks_are_found():
    assert len(BENCHMARKS) >= 12, [p.name for p in BENCHMARKS]


@pytest.mark.parametrize("path", BENCHMARKS, ids=[p.stem for p in BENCHMARKS])
def test_smoke_mode_runs(path, tmp_path):
    assert path.stem in EXPECTED, f"{path.name}: add the lines its --smoke output must contain to EXPECTED"
    env = {**os.environ, "MPLBACKEND": "Agg", "PYTHONPATH": os.pathsep.join(
        [str(ROOT)] + ([os.environ["PYTHONPATH"]] if os.environ.get("PYTHONPATH") else []))}
    proc = subprocess.run([sys.executable, str(path), "--smoke"], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=240)
    out = proc.stdout
    assert proc.returncode == 0, (f"{path.name} --smoke: exit code {proc.returncode}\n{out[-2000:]}\n"
                                  f"{proc.stderr[-3000:]}")
    assert "Traceback" not in out and not re.search(r"failed: \w+(Error|Failed)", out), out[-3000:]
    missing = [rx for rx in EXPECTED[path.stem] if not re.search(rx, out, re.MULTILINE)]
    assert not missing, f"{path.name} --smoke: no line matches {missing}\n{out[-3000:]}"
