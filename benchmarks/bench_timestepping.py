"""Speed of the compiled Moreau-Jean loop (issue 6 targets).

2-DoF prismatic clearance scene, h = 1e-4, 1e5 steps, PD (36) on body 1;
the CasADi VM, generated C (when a compiler is present) and a plain numpy
loop implementing the same step are timed in the same run and printed as
ratios.  Parameters enter as an input held over the loop: a second run with
other gains reuses the compiled loop (timed separately).

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


def numba_kernel():
    """The same Moreau-Jean step as the compiled loop with the same records, as a numba kernel (``None`` without
    numba): every ``every``-th row ``(q, v, t, gap, U, E, V, u, P, active)`` (step 0 included) and the final state,
    and the exact running statistics over every step (smallest gaps, largest one-step increase of E and V,
    impacts, changes of the active or loaded set)."""
    try:
        from numba import njit
    except ImportError:
        return None

    @njit(cache=True)
    def run(q0, v0, N, h, every, m1, m2, l, L, e, Kp, Kv, qd, th=0.5, tol=1e-12, vtol=1e-8):
        nrec = (N + every - 1) // every + 1
        R = np.zeros((nrec, 16))
        q1, q2, v1, v2 = q0[0], q0[1], v0[0], v0[1]
        # W_hat = M + h th C + (h th)^2 K is diagonal here (PD on body 1); W columns: (-1, 1), (1, -1)
        w1, w2 = m1 + h * th * Kv + (h * th) ** 2 * Kp, m2
        D00 = 1.0 / w1 + 1.0 / w2  # D = W^T W_hat^-1 W = [[d, -d], [-d, d]]
        g1, g2, U1, U2 = q2 - q1 - l, q1 - q2 + L - l, v2 - v1, v1 - v2
        E = 0.5 * (m1 * v1 * v1 + m2 * v2 * v2)
        V = E + 0.5 * Kp * (q1 - qd) ** 2
        gmin1, gmin2, dEmax, dVmax = g1, g2, 0.0, 0.0
        n_imp, n_chg, a1o, a2o, l1o, l2o = 0, 0, 0.0, 0.0, 0.0, 0.0
        r = 0
        for k in range(N):
            u = -Kp * (q1 - qd) - Kv * v1
            vf1 = v1 + h * (u - h * th * Kp * v1) / w1
            vf2 = v2
            a1 = 1.0 if g1 + 0.5 * h * U1 <= tol else 0.0
            a2 = 1.0 if g2 + 0.5 * h * U2 <= tol else 0.0
            b1 = a1 * ((vf2 - vf1) + e * min(U1, 0.0))
            b2 = a2 * ((vf1 - vf2) + e * min(U2, 0.0))
            P1, P2 = 0.0, 0.0
            if a1 > 0 and a2 > 0:  # enumeration of the 2x2 LCP (D singular: the single-contact pieces first)
                if b1 < 0 and b2 + (-D00) * (-b1 / D00) >= 0:
                    P1 = -b1 / D00
                elif b2 < 0 and b1 + (-D00) * (-b2 / D00) >= 0:
                    P2 = -b2 / D00
            elif a1 > 0 and b1 < 0:
                P1 = -b1 / D00
            elif a2 > 0 and b2 < 0:
                P2 = -b2 / D00
            vn1 = vf1 + (-P1 + P2) / w1
            vn2 = vf2 + (P1 - P2) / w2
            if k % every == 0:
                R[r, 0], R[r, 1], R[r, 2], R[r, 3], R[r, 4] = q1, q2, v1, v2, k * h
                R[r, 5], R[r, 6], R[r, 7], R[r, 8], R[r, 9], R[r, 10] = g1, g2, U1, U2, E, V
                R[r, 11], R[r, 12], R[r, 13], R[r, 14], R[r, 15] = u, P1, P2, a1, a2
                r += 1
            q1 += h * (th * vn1 + (1 - th) * v1)
            q2 += h * (th * vn2 + (1 - th) * v2)
            l1, l2 = 1.0 if P1 > 0 else 0.0, 1.0 if P2 > 0 else 0.0
            n_imp += int(l1 * (1 - l1o) * (U1 < -vtol)) + int(l2 * (1 - l2o) * (U2 < -vtol))
            if a1 != a1o or a2 != a2o or l1 != l1o or l2 != l2o:
                n_chg += 1
            a1o, a2o, l1o, l2o = a1, a2, l1, l2
            v1, v2 = vn1, vn2
            g1, g2, U1, U2 = q2 - q1 - l, q1 - q2 + L - l, v2 - v1, v1 - v2
            En = 0.5 * (m1 * v1 * v1 + m2 * v2 * v2)
            Vn = En + 0.5 * Kp * (q1 - qd) ** 2
            dEmax, dVmax = max(dEmax, En - E), max(dVmax, Vn - V)
            E, V = En, Vn
            gmin1, gmin2 = min(gmin1, g1), min(gmin2, g2)
        R[r, 0], R[r, 1], R[r, 2], R[r, 3], R[r, 4] = q1, q2, v1, v2, N * h
        R[r, 5], R[r, 6], R[r, 7], R[r, 8], R[r, 9], R[r, 10] = g1, g2, U1, U2, E, V
        R[r, 11] = -Kp * (q1 - qd) - Kv * v1
        return R[:r + 1], np.array([gmin1, gmin2, dEmax, dVmax, n_imp, n_chg])

    return run


def _interleaved(calls, rounds):
    """Whole calls timed in interleaved rounds: ``{name: (min_s, median_s, last result)}``."""
    walls = {k: [] for k in calls}
    last = {}
    for _ in range(rounds):
        for k, fn in calls.items():
            tic = time.perf_counter()
            last[k] = fn()
            walls[k].append(time.perf_counter() - tic)
    return {k: (min(w), float(np.median(w)), last[k]) for k, w in walls.items()}


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=1_000_000)
    ap.add_argument("--vm-steps", type=int, default=100_000)
    ap.add_argument("--numpy-steps", type=int, default=20_000)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--smoke", "--quick", action="store_true", help="tiny run: checks that the benchmark runs")
    args = ap.parse_args(argv)
    rounds = args.rounds
    if args.smoke:
        args.steps, args.vm_steps, args.numpy_steps, rounds = 4000, 2000, 500, 1
    N, h = args.steps, 1e-4
    p = scene.PARAMS
    model = scene.build(actuators=1)
    law = pd_gravity(model, Kp=p["Kp"], Kv=p["Kv"], q_d=p["qd"], idx=[0])
    q0 = [0.0, p["l"] + 0.5 * (p["L"] - 2 * p["l"])]
    v0 = [0.0, p["v20"]]
    consts = (p["m1"], p["m2"], p["l"], p["L"], p["e"], p["Kp"], p["Kv"], p["qd"])
    print(f"2-DoF clearance, PD on body 1, h = {h}; whole run() calls, {rounds} interleaved rounds (min / median)")
    results = {}
    backends = ["vm", "c"] if c_compiler() else ["vm"]
    for backend in backends:
        tic = time.perf_counter()
        mj = MoreauJean(model, law, backend=backend)
        mj.run(q0, v0, 10 * h * mj.chunk, h)  # builds/compiles the loop (disk cache)
        results[backend + "_build"] = time.perf_counter() - tic
        n_b = N if backend == "c" else min(N, args.vm_steps)
        calls = {backend: lambda: mj.run(q0, v0, n_b * h, h),
                 backend + "_new_params": lambda: mj.run(q0, v0, n_b * h, h, gains=law.values(Kp1=200.0, Kv1=30.0),
                                                         params=[1.0, 0.4, 0.05, 0.11, 0.3])}
        calls[backend]()  # the loop of this run length
        loops = len(mj._loops)
        for k, (wmin, wmed, tr) in _interleaved(calls, rounds).items():
            results[k] = (n_b / wmin, n_b / wmed)
            results[k + "_traj"] = tr
        assert len(mj._loops) == loops, "new parameters must not rebuild the loop"
        results[backend + "_mj"] = mj
    tic = time.perf_counter()
    ref = numpy_loop(np.array(q0), np.array(v0), args.numpy_steps, h, *consts)
    results["numpy"] = args.numpy_steps / (time.perf_counter() - tic)
    tr = results["vm_traj"]
    dev = np.max(np.abs(tr.q[:, 1:args.numpy_steps + 1] - ref[:, :2].T))  # tr.q: (n, len(t)), ref: rows per step
    print(f"  numpy loop          {results['numpy']:12.4g} steps/s   (1x)")
    for b in backends:
        n_b = N if b == "c" else min(N, args.vm_steps)
        print(f"  CasADi {b.upper():3s}          {results[b][0]:12.4g} steps/s   ({results[b][0] / results['numpy']:.0f}x numpy)"
              f"   median {results[b][1]:.4g}; new gains/params, same loop: {results[b + '_new_params'][0]:.4g} steps/s"
              f"   ({n_b} steps; build {results[b + '_build']:.2f} s)")
    print(f"  max |q_compiled - q_numpy| over {args.numpy_steps} steps: {dev:.2e}")
    kernel = numba_kernel()
    best = backends[-1]
    if kernel is None:
        print("  numba kernel: numba is not installed (pip install invctl[bench]); its column is skipped")
        return results
    # the statistics the kernel updates on every step (smallest gaps, impacts, largest increase of E and of V,
    # active/loaded-set changes); invctl's "lyapunov" also splits the V increase into impact and other steps
    same = ("gaps", "impacts", "energy", "lyapunov", "active_set")
    mjs = {"all": results[best + "_mj"], "same": MoreauJean(model, law, backend=best, monitor=same)}
    mjs["same"].run(q0, v0, 10 * h * mjs["same"].chunk, h)  # builds/compiles its loop
    tic = time.perf_counter()
    kernel(np.array(q0), np.array(v0), 10, h, 1, *consts)
    results["numba_build"] = time.perf_counter() - tic
    print(f"\n  vs a numba kernel of the same step with the same records ({N} steps, CasADi {best.upper()}; "
          f"numba compile {results['numba_build']:.2f} s); invctl monitoring all its running statistics "
          f"(monitor='all') and the kernel's (monitor={same}), interleaved with the kernel in the same rounds")
    print(f"  {'record_every':>12s} {'invctl steps/s':>15s} {'median':>10s} {'numba steps/s':>14s} {'median':>10s} "
          f"{'ratio':>7s} {'max |dq|':>9s} {'impacts':>9s} {'|d gap_min|':>11s}  monitor")
    for every in (1, 1000):
        calls = {k: (lambda mj=mj: mj.run(q0, v0, N * h, h, record_every=every)) for k, mj in mjs.items()}
        calls["numba"] = lambda: kernel(np.array(q0), np.array(v0), N, h, every, *consts)
        out = _interleaved(calls, rounds)
        R, st = out["numba"][2]
        sps_nb = N / out["numba"][0]
        for k in mjs:
            tr = out[k][2]
            dq = float(np.max(np.abs(tr.q - R[:, 0:2].T)))
            dg = float(np.max(np.abs(tr.stats["gap_min"] - st[:2])))
            dEV = max(abs(tr.stats["dE_max"] - st[2]), abs(tr.stats["dV_max"] - st[3]))
            imp = f"{tr.stats['n_impacts']}/{int(st[4])}"
            sps = N / out[k][0]
            results[f"numba_every{every}" + ("" if k == "all" else "_same")] = (sps, sps_nb, dq)
            if not (dq <= 1e-12 and dg <= 1e-12 and dEV <= 1e-12 and tr.stats["n_impacts"] == int(st[4])
                    and tr.stats["n_changes"] == int(st[5])):
                raise SystemExit(f"the numba kernel's records differ from invctl's (max |dq| {dq:.2e}, impacts {imp}, "
                                 f"|d dE_max|, |d dV_max| <= {dEV:.2e}, changes {tr.stats['n_changes']}/{int(st[5])})")
            label = "all" if k == "all" else "the kernel's"
            print(f"  {every:12d} {sps:15.4g} {N / out[k][1]:10.4g} {sps_nb:14.4g} {N / out['numba'][1]:10.4g} "
                  f"{sps / sps_nb:6.2f}x {dq:9.1e} {imp:>9s} {dg:11.1e}  {label}")
    print("  ratio: invctl / numba steps/s (min times); impacts: invctl/numba; monitor: the running statistics "
          "invctl updates on every step (all of them, or the kernel's)")
    for k, what in (("", "all statistics"), ("_same", "the kernel's statistics")):
        slow = [e for e in (1, 1000) if results[f"numba_every{e}{k}"][0] < results[f"numba_every{e}{k}"][1]]
        if slow:
            print(f"  below the kernel with {what} at record_every={slow}: both run the same dependency chain per "
                  "step" + (", invctl with more instructions (the running statistics the kernel does not keep: rest "
                            "times, LCP residual, impulse sums, the V increase split at impacts)" if not k else ""))
    return results


if __name__ == "__main__":
    main()
