"""Internal dynamics of the manipulator: Sect. 3 (Newton on q only, velocities linear) vs Sect. 2
(Newton on the full state), and the cost of each analysis step.

Both routes give the same numbers (tests/test_analysis_manipulator.py); this measures what the
Sect. 3 coordinates save (003 Remark 3.4).  Run: python benchmarks/bench_analysis.py [--smoke]

``--smoke`` (alias ``--quick``): the same steps on few samples and points, one round (checks that the
benchmark runs; its numbers are not the benchmark's).
"""
import sys
import time

import numpy as np

import invctl_scenes.manipulator as scene
from invctl.analysis import internal_dynamics, linearize_internal, relative_degree

SMOKE = bool({"--smoke", "--quick"} & set(sys.argv[1:]))
REPEAT = 1 if SMOKE else 5
SAMPLES = 20 if SMOKE else 200


def timeit(fn, repeat=REPEAT):
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def main():
    t0 = time.perf_counter()
    model = scene.build()
    q0 = scene.initial_configuration(model)
    ref = scene.reference(model)
    print(f"build                        {1e3 * (time.perf_counter() - t0):8.2f} ms")
    t = time.perf_counter()
    relative_degree(model, samples=SAMPLES)
    print(f"relative degree ({SAMPLES} pts)    {1e3 * (time.perf_counter() - t):8.2f} ms "
          "(first call, derivation included)")
    routes = {}
    for method in ("sect3", "sect2"):
        t = time.perf_counter()
        routes[method] = internal_dynamics(model, method, scene.paper_internal_coordinates, point=q0, samples=SAMPLES)
        print(f"internal dynamics {method}      {1e3 * (time.perf_counter() - t):8.2f} ms (derivation + checks)")
    N = 40 if SMOKE else 400
    ts = np.linspace(ref.t0, ref.tf, N)
    Y = ref(ts)
    Yd = ref(ts, 1)
    eta = np.zeros((2, N))
    th = np.tile(model.theta_values[:, None], (1, N))
    rates = {}
    for method, idyn in routes.items():
        fmap = idyn.rhs.map(N)
        rates[method] = timeit(lambda: fmap(Y, Yd, eta, th)) / N
    print(f"rhs evaluation along the path ({N} points, mapped):")
    for method, r in rates.items():
        print(f"  {method}: {1e6 * r:8.2f} us per point")
    print(f"  ratio sect2 / sect3 = {rates['sect2'] / rates['sect3']:.2f}")
    lins = {}
    for method, idyn in routes.items():
        pts = [([ref(t).ravel(), np.zeros(2)], np.zeros(2)) for t in (ref.t0, ref.tf)]
        lins[method] = timeit(lambda: linearize_internal(model, idyn, pts, split="eig"))
    print(f"linearization (2 points): sect3 {1e3 * lins['sect3']:.2f} ms, sect2 {1e3 * lins['sect2']:.2f} ms, "
          f"ratio {lins['sect2'] / lins['sect3']:.2f}")


if __name__ == "__main__":
    main()
