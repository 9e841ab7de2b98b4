"""Speed of the compiled Moreau-Jean loop (issue 6 targets).

2-DoF prismatic clearance scene, h = 1e-4, 1e5 steps, PD (36) on body 1;
the CasADi VM, generated C (when a compiler is present) and a plain numpy
loop implementing the same step are timed in the same run and printed as
ratios.  Parameters enter through the loop state: a second run with other
gains reuses the compiled loop (timed separately).

    python benchmarks/bench_timestepping.py [--steps 100000] [--smoke]

``--smoke`` (alias ``--quick``): 2000 steps (500 for numpy), one round (checks that the benchmark
runs; its numbers are not the benchmark's).
"""
from __future__ import annotations

import argparse
import time
import numpy as np

import invctl_scenes.prismatic_clearance as scene
from invctl.control.pdplus import pd_gravity
from invctl.simulate.timestepping import MoreauJean, c_compiler


def numpy_loop(q, v, N, h, m1, m2, l, L, e, Kp, Kv, qd, theta=0.5, tol=1e-12):
    """The same Moreau-Jean step as the compiled loop, written with numpy."""
    M = np.diag([m1, m2])
    W = np.array([[-1.0, 1.0], [1.0, -1.0]])  # columns: grad f1, grad f2
    K = np.array([[Kp, 0.0], [0.0, 0.0]])
    C = np.array([[Kv, 0.0], [0.0, 0.0]])
    Wh = M + h * theta * C + (h * theta) ** 2 * K
    Whi = np.linalg.inv(Wh)
    WiW = Whi @ W
    D = W.T @ WiW
    out = np.empty((N, 4))
    for k in range(N):
        F = np.array([-Kp * (q[0] - qd) - Kv * v[0], 0.0])
        vf = v + Whi @ (h * (F - h * theta * K @ v))
        g = np.array([q[1] - q[0] - l, q[0] - q[1] + L - l])
        U = W.T @ v
        act = g + 0.5 * h * U <= tol
        b = W.T @ vf + e * np.minimum(U, 0.0)
        P = np.zeros(2)
        idx = np.flatnonzero(act)
        if idx.size:
            best = None
            for S in ([idx.tolist()] + [[i] for i in idx] if idx.size == 2 else [idx.tolist()]):
                z = np.zeros(2)
                z[S] = np.linalg.solve(D[np.ix_(S, S)], -b[S])
                w = D @ z + b
                if z.min() >= 0 and all(w[i] >= -1e-13 for i in idx if i not in S):
                    best = z
                    break
            P = best if best is not None else np.zeros(2)
        vn = vf + WiW @ P
        q = q + h * (theta * vn + (1 - theta) * v)
        v = vn
        out[k] = (*q, *v)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=100_000)
    ap.add_argument("--numpy-steps", type=int, default=20_000)
    ap.add_argument("--smoke", "--quick", action="store_true", help="tiny run: checks that the benchmark runs")
    args = ap.parse_args(argv)
    rounds = 3
    if args.smoke:
        args.steps, args.numpy_steps, rounds = min(args.steps, 2000), min(args.numpy_steps, 500), 1
    N, h = args.steps, 1e-4
    p = scene.PARAMS
    model = scene.build(actuators=1)
    law = pd_gravity(model, Kp=p["Kp"], Kv=p["Kv"], q_d=p["qd"], idx=[0])
    q0 = [0.0, p["l"] + 0.5 * (p["L"] - 2 * p["l"])]
    v0 = [0.0, p["v20"]]
    t_end = N * h
    results = {}
    for backend in (["vm", "c"] if c_compiler() else ["vm"]):
        mj = MoreauJean(model, law, backend=backend)
        mj.run(q0, v0, 10 * h * mj.chunk, h)  # warm-up: builds/compiles the loop (cached)
        best = np.inf
        for _ in range(rounds):
            tr = mj.run(q0, v0, t_end, h)
            best = min(best, tr.stats["wall_s"])
        results[backend] = N / best
        loops = len(mj._loops)
        # new gains and parameters: same compiled loop, no re-tracing
        best2 = np.inf
        for k in range(rounds):
            tr2 = mj.run(q0, v0, t_end, h, gains=law.values(Kp1=200.0 + k, Kv1=30.0), params=[1.0, 0.4, 0.05, 0.11, 0.3])
            best2 = min(best2, tr2.stats["wall_s"])
        results[backend + "_new_params"] = N / best2
        assert len(mj._loops) == loops, "new parameters must not rebuild the loop"
        results[backend + "_traj"] = tr
    tic = time.perf_counter()
    ref = numpy_loop(np.array(q0), np.array(v0), args.numpy_steps, h, p["m1"], p["m2"], p["l"], p["L"], p["e"],
                     p["Kp"], p["Kv"], p["qd"])
    results["numpy"] = args.numpy_steps / (time.perf_counter() - tic)
    tr = results["vm_traj"]
    dev = np.max(np.abs(tr.q[:, 1:args.numpy_steps + 1] - ref[:, :2].T))  # tr.q: (n, len(t)), ref: rows per step
    print(f"2-DoF clearance, PD on body 1, h = {h}, {N} steps")
    print(f"  numpy loop          {results['numpy']:12.4g} steps/s   (1x)")
    for b in ("vm", "c"):
        if b in results:
            print(f"  CasADi {b.upper():3s}          {results[b]:12.4g} steps/s   ({results[b] / results['numpy']:.0f}x numpy)"
                  f"   new gains/params, same loop: {results[b + '_new_params']:.4g} steps/s")
    print(f"  max |q_compiled - q_numpy| over {args.numpy_steps} steps: {dev:.2e}")
    return results


if __name__ == "__main__":
    main()
