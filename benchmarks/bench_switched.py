"""Exact switched propagation (matrix exponentials, located events) vs scipy solve_ivp with events.

Same closed loop (002 (1)-(3) + App. A reference), same horizon; the peer restarts an
explicit (DOP853) or implicit (Radau) integrator at every wall crossing.  Prints wall
times, the ratio, and the largest difference of the event times.

    python benchmarks/bench_switched.py [--smoke]

``--smoke`` (alias ``--quick``): the same four cases up to just past the first contact (checks that the
benchmark runs; its numbers are not the benchmark's).
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from test_switched_sim import ivp_reference  # noqa: E402  (the independent integration of the tests)

import invctl_scenes.stiff_wall as wall  # noqa: E402
from invctl.studies.switched import build_loop, simulate_scenario  # noqa: E402

SMOKE = bool({"--smoke", "--quick"} & set(sys.argv[1:]))


def run(label, t_end=0.35, method="DOP853", rtol=1e-10, **overrides):
    p = wall.build(**overrides).params
    t_end = min(t_end, 0.158) if SMOKE else t_end  # smoke: to just past the first contact (0.1567 s)
    simulate_scenario(p, t_end=0.01)  # warm-up (imports)
    t0 = time.perf_counter()
    sim = simulate_scenario(p, t_end=t_end)
    t_exact = time.perf_counter() - t0
    t0 = time.perf_counter()
    ev, _ = ivp_reference(p, build_loop(p).reference, t_end, method=method, rtol=rtol)
    t_ivp = time.perf_counter() - t0
    d = np.max(np.abs(sim.event_t - ev)) if ev.size == sim.event_t.size and ev.size else float("nan")
    print(f"{label:34s} exact {t_exact * 1e3:8.1f} ms   solve_ivp({method}, rtol={rtol:g}) "
          f"{t_ivp * 1e3:9.1f} ms   ratio {t_ivp / t_exact:7.1f}x   events {sim.event_t.size}/{ev.size}  "
          f"max |dt_event| {d:.2e} s")


if __name__ == "__main__":
    run("bf = 5, ke = 1e6 (Fig. 3)", bf=5.0)
    run("bf = 9000, ke = 1e6 (Fig. 4)", bf=9000.0)
    run("bf = 5, ke = 1e8", bf=5.0, ke=1e8)
    run("bf = 5, ke = 1e9, be = 1e-3 (Radau)", t_end=0.2, method="Radau", ke=1e9, be=1e-3, be_hat=10.0)
