"""Cost of piecewise references and of animations.

Evaluation of a 50-piece reference (degree 9, C^4) with derivatives up to order 3 (what the
servo-constraint inversion samples) in one mapped call, for the coefficient-selection SX of
invctl.reference.piecewise and for the chain of if_else it replaces; the smoothing-spline fit;
frames per second of animate.  Run: python benchmarks/bench_references.py [--smoke]

``--smoke`` (alias ``--quick``): the same steps on 5 pieces, few samples and frames, one round (checks
that the benchmark runs; its numbers are not the benchmark's).
"""
import math
import sys
import tempfile
import time
from pathlib import Path

import casadi as ca
import numpy as np

from invctl.reference import Reference, from_samples, waypoints

SMOKE = bool({"--smoke", "--quick"} & set(sys.argv[1:]))


def best(fn, repeat=5):
    out = np.inf
    for _ in range(1 if SMOKE else repeat):
        t = time.perf_counter()
        fn()
        out = min(out, time.perf_counter() - t)
    return out


def if_else_chain(ref_breaks, coeffs):
    """The same piecewise polynomial as nested if_else over the pieces (for comparison)."""
    t = ca.SX.sym("t")
    b = ref_breaks
    P, D = coeffs.shape[:2]
    y = ca.SX(float(coeffs[-1, :, 0].sum()))
    for i in reversed(range(P)):
        tau = (t - b[i]) / (b[i + 1] - b[i])
        p = float(coeffs[i, -1, 0])
        for j in reversed(range(D - 1)):
            p = p * tau + float(coeffs[i, j, 0])
        y = ca.if_else(t < b[i + 1], p, y)
    return Reference(t, ca.if_else(t < b[0], float(coeffs[0, 0, 0]), y), b[0], b[-1], 4)


def main():
    rng = np.random.default_rng(0)
    P = 5 if SMOKE else 50
    tb = np.arange(P + 1.0)
    ref = waypoints(tb, rng.standard_normal(P + 1), smoothness=4)
    h = np.diff(tb)
    from scipy.interpolate import make_interp_spline

    rest = [(j, 0.0) for j in range(1, 5)]
    spl = make_interp_spline(tb, ref(tb)[0], k=9, bc_type=(rest, rest))
    coeffs = np.stack([spl(tb[:-1], nu=j) * h**j / math.factorial(j) for j in range(10)], axis=1)[:, :, None]
    chain = if_else_chain(tb, coeffs)
    tt = np.linspace(-1, P + 1, 1000 if SMOKE else 10000)
    print(f"{P} pieces, degree 9, derivatives 0..3 at {tt.size} times (one mapped call)")
    for name, r in (("coefficient selection", ref), ("if_else chain", chain)):
        fn = r.function(3).map(tt.size)
        s = best(lambda: fn(tt[None, :]))
        print(f"  {name:22s} {r.function(3).n_instructions():6d} instructions  {1e6 * s / tt.size:7.2f} us/time")
    err = np.max(np.abs(ref(tt, 3) - chain(tt, 3))) / np.max(np.abs(ref(tt, 3)))
    print(f"  same values: max relative difference of y''' {err:.1e}")

    for N in ((400,) if SMOKE else (400, 4000)):
        t = np.linspace(0, 2, N)
        y = np.sin(3 * t) ** 3 + 0.01 * rng.standard_normal(N)
        s = best(lambda: from_samples(t, y, 4), repeat=3)
        r = from_samples(t, y, 4)
        print(f"from_samples N={N:5d}: {1e3 * s:7.1f} ms  ({r.diagnostics['pieces']} pieces, "
              f"edf {r.diagnostics['outputs'][0]['edf']:.1f})")

    import invctl_scenes.cartpole as scene
    from invctl.plot.animate import Drawing, animate

    model = scene.build()
    x, th = model.q[0], model.q[1]
    l = model.params["l"]
    dr = Drawing({"cart": ca.vertcat(x, 0), "tip": ca.vertcat(x + 2 * l * ca.sin(th), 2 * l * ca.cos(th))},
                 links=[("cart", "tip")], segments=[((-1, 0), (1, 0))])
    t = np.linspace(0, 0.4 if SMOKE else 4, 41 if SMOKE else 401)
    frames = int(round(25 * t[-1])) + 1
    q = np.vstack([0.5 * np.sin(t), 0.3 * np.sin(3 * t)])
    with tempfile.TemporaryDirectory() as d:
        s = best(lambda: animate(model, dr, t, q, Path(d) / "a.gif", fps=25, trail="tip"), repeat=2)
    print(f"animate: {frames} frames (480 x 360 GIF) in {s:.2f} s = {1e3 * s / frames:.1f} ms/frame")


if __name__ == "__main__":
    main()
