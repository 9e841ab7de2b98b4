"""Contacts at scale: compiled Moreau-Jean with exact LCPs, and long runs in bounded memory (paper 000).

Rows (each with a peer measured in the same run):

1. steps/s against the number of contacts (1, 2, 4, 8, 16) on a forced chain of bodies with clearances
   between neighbours and a wall; peers: the same step with the LCPs solved by the numpy solvers
   (Lemke) in a Python loop, and the same compiled step with projected Gauss-Seidel (inexact);
   for <= 4 contacts also enumeration and Lemke against block principal pivoting;
2. steps/s against the number of bodies (4 contacts);
3. a bounded-memory long run (elastic bouncing ball, decimated and event records) with its peak RSS,
   measured in a child process, against a short run of the same kind.

``python benchmarks/bench_contacts.py [--smoke] [--long-steps 1e8]``

``--smoke`` (alias ``--quick``): the same rows at tiny sizes and short runs (checks that the benchmark
runs; its numbers are not the benchmark's).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import casadi as ca
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from invctl.control.pdplus import FeedbackLaw  # noqa: E402
from invctl.model import Gap, Model, ParamSet  # noqa: E402
from invctl.simulate.timestepping import MoreauJean, c_compiler  # noqa: E402

CHAIN = {"m": 1.0, "k": 100.0, "kc": 50.0, "c": 0.0, "e": 0.5, "cl": 0.01, "A": 2.0, "w": 8.0}


def chain(n: int, contacts: int | None = None, **values):
    """``n`` blocks on a line, each on a spring to its anchor (spacing 1) and coupled to its
    neighbours; coordinates are displacements from the anchors.  Gaps (restitution ``e``): the
    wall left of block 0 and the neighbour pairs, ``clearance cl`` at rest, the first ``contacts``
    of them.  Returns ``(model, law, potential)``: a sinusoidal force ``A sin(w (1 + i/10) t)`` on
    every block keeps impacts and persistent contacts going."""
    contacts = n if contacts is None else int(contacts)
    if not 1 <= contacts <= n:
        raise ValueError(f"contacts must lie in 1..{n}, got {contacts}")
    vals = {**CHAIN, **values}
    P = ParamSet(["m", "k", "kc", "c", "e", "cl"])
    q, v = ca.SX.sym("q", n), ca.SX.sym("v", n)
    f, U = [], 0
    for i in range(n):
        fi = -P["k"] * q[i] - P["c"] * v[i]
        U = U + 0.5 * P["k"] * q[i] ** 2
        if i > 0:
            fi = fi - P["kc"] * (q[i] - q[i - 1])
            U = U + 0.5 * P["kc"] * (q[i] - q[i - 1]) ** 2
        if i < n - 1:
            fi = fi - P["kc"] * (q[i] - q[i + 1])
        f.append(fi)
    gaps = [Gap("wall", q[0] + P["cl"], "e")] + [Gap(f"g{i}{i + 1}", q[i + 1] - q[i] + P["cl"], "e")
                                                 for i in range(n - 1)]
    model = Model(f"chain{n}_{contacts}", q, v, P, {k: vals[k] for k in P.names}, M=P["m"] * ca.SX.eye(n),
                  f=ca.vertcat(*f), B=ca.SX.eye(n), gaps=gaps[:contacts])

    def build(model, t, kappa):
        return ca.vertcat(*[kappa[0] * ca.sin(kappa[1] * (1 + 0.1 * i) * t) for i in range(n)]), None

    law = FeedbackLaw("forcing", ("A", "w"), (vals["A"], vals["w"]), build)
    return model, law, U


def piled_up(n: int, cl: float = CHAIN["cl"]):
    """Initial state: every gap 5 % of the clearance, every block moving to the wall at 0.5 m/s (the
    blocks pile up: many simultaneous, coupled contacts, then bounce and keep being forced)."""
    return -0.95 * cl * np.arange(1, n + 1), -0.5 * np.ones(n)


def _steps_per_s(mj, q0, v0, steps, h, repeat=2, **kw):
    best, tr = np.inf, None
    for _ in range(repeat):
        tr = mj.run(q0, v0, steps * h, h, **kw)
        best = min(best, tr.stats["wall_s"])
    return steps / best, tr


def _reference(mj, q0, v0, steps, h):
    tic = time.perf_counter()
    Q, V = mj.reference_run(q0, v0, steps, h, method="lemke")
    return steps / (time.perf_counter() - tic), Q


def contacts_rows(counts, steps, ref_steps, h=1e-3):
    print(f"\n1. steps/s against contacts: forced chain, n = contacts bodies, h = {h}, generated C, record_every=100;\n"
          f"   numpy Lemke = the same step with numpy LCPs in a Python loop ({ref_steps} steps), |dq| = max deviation\n"
          f"   of q from it over those steps, loaded = most contacts carrying an impulse in one of them")
    print(f"{'contacts':>8} {'LCP':>12} {'instr':>7} {'build s':>8} {'steps/s':>10} {'numpy Lemke':>12} {'ratio':>7} "
          f"{'|dq| vs numpy':>13} {'loaded':>6} {'PGS steps/s':>12} {'PGS |dq|':>9} {'impacts':>8} {'recomp':>6}")
    out = []
    for c in counts:
        model, law, U = chain(c)
        q0, v0 = piled_up(c)
        methods = ["enumeration", "lemke", "pivoting"] if c <= 4 else ["pivoting"]
        for meth in methods:
            tic = time.perf_counter()
            mj = MoreauJean(model, law, potential=U, lcp=meth)
            mj.run(q0, v0, 2 * h, h)  # builds / compiles the loop (disk cache)
            build = time.perf_counter() - tic
            sps, tr = _steps_per_s(mj, q0, v0, steps, h, record_every=100)
            ref_sps, Q = _reference(mj, q0, v0, ref_steps, h)
            short = mj.run(q0, v0, ref_steps * h, h)
            dq = float(np.max(np.abs(short.q - Q)))
            multi = int(np.max(np.sum(short.P > 0, axis=0)))  # P: (contacts, steps)
            row = {"contacts": c, "lcp": meth, "instructions": mj.step.n_instructions(), "build_s": build,
                   "steps_per_s": sps, "numpy_lemke_steps_per_s": ref_sps, "ratio": sps / ref_sps, "dq_numpy": dq,
                   "impacts": tr.stats["n_impacts"], "recomputed": tr.stats["lcp_recomputed"],
                   "max_loaded_in_window": multi}
            if meth == methods[-1]:
                pg = MoreauJean(model, law, potential=U, lcp="pgs", pgs_sweeps=50)
                pg.run(q0, v0, 2 * h, h)
                row["pgs_steps_per_s"], _ = _steps_per_s(pg, q0, v0, steps, h, record_every=100)
                row["pgs_dq"] = float(np.max(np.abs(pg.run(q0, v0, ref_steps * h, h).q - Q)))
            out.append(row)
            pgs = (f"{row['pgs_steps_per_s']:12.3g} {row['pgs_dq']:9.1e}" if "pgs_dq" in row else f"{'':>12} {'':>9}")
            print(f"{c:8d} {meth:>12} {row['instructions']:7d} {build:8.1f} {sps:10.3g} {ref_sps:12.3g} "
                  f"{sps / ref_sps:6.0f}x {dq:13.1e} {multi:6d} {pgs} {row['impacts']:8d} {row['recomputed']:6d}",
                  flush=True)
    return out


def bodies_rows(ns, contacts, steps, ref_steps, h=1e-3):
    print(f"\n2. steps/s against bodies: forced chain with {contacts} contacts, h = {h}, generated C")
    print(f"{'bodies':>8} {'instr':>7} {'build s':>8} {'steps/s':>10} {'numpy Lemke':>12} {'ratio':>7} "
          f"{'|dq| vs numpy':>13}")
    out = []
    for n in ns:
        model, law, U = chain(n, contacts)
        q0, v0 = piled_up(n)
        tic = time.perf_counter()
        mj = MoreauJean(model, law, potential=U)
        mj.run(q0, v0, 2 * h, h)
        build = time.perf_counter() - tic
        sps, _ = _steps_per_s(mj, q0, v0, steps, h, record_every=100)
        ref_sps, Q = _reference(mj, q0, v0, ref_steps, h)
        dq = float(np.max(np.abs(mj.run(q0, v0, ref_steps * h, h).q - Q)))
        out.append({"bodies": n, "contacts": contacts, "instructions": mj.step.n_instructions(), "build_s": build,
                    "steps_per_s": sps, "numpy_lemke_steps_per_s": ref_sps, "ratio": sps / ref_sps, "dq_numpy": dq})
        print(f"{n:8d} {mj.step.n_instructions():7d} {build:8.1f} {sps:10.3g} {ref_sps:12.3g} {sps / ref_sps:6.0f}x "
              f"{dq:13.1e}", flush=True)
    return out


_CHILD = r"""
import json, resource, sys, time
sys.path.insert(0, {root!r})
import invctl_scenes.bouncing_ball as bb
from invctl.simulate.timestepping import MoreauJean
from invctl.errors import ResourceLimitError
steps, h, kw = {steps}, {h}, {kw}
m = bb.build(e=1.0)
mj = MoreauJean(m, potential=bb.potential(m))
mj.run([1.0], [0.0], 0.01, h)
rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
tic = time.perf_counter()
tr = mj.run([1.0], [0.0], steps * h, h, **kw)
wall = time.perf_counter() - tic
try:  # the estimate of an undecimated record (a 1-byte budget makes the run stop before it starts)
    mj.run([1.0], [0.0], steps * h, h, memory_budget=1)
except ResourceLimitError as exc:
    full = exc.diagnostics
print(json.dumps({{"steps": tr.stats["steps"], "wall_s": wall, "rows": int(tr.t.size),
    "rss_before_kib": rss0, "rss_peak_kib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
    "impacts": int(tr.stats["n_impacts"]), "dE_max": tr.stats["dE_max"], "E0": float(tr.energy[0]),
    "max_gap_violation": tr.max_gap_violation, "first_impact": float(tr.impact_times[0]),
    "last_impact": float(tr.impact_times[-1]), "full_record_bytes": full["record_rows"] * full["row_bytes"]}}))
"""


def long_run(steps: int, h: float, kw: dict):
    code = _CHILD.format(root=str(ROOT), steps=int(steps), h=h, kw=repr(kw))
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(res.stderr[-2000:])
    return json.loads(res.stdout.strip().splitlines()[-1])


def long_rows(long_steps: int, h=1e-4, short_steps: int = 10**6):
    print(f"\n3. bounded memory: elastic ball (e = 1, theta = 1/2), h = {h}, generated C, peak RSS of a child process\n"
          "   (RSS before = after imports, build and a warm-up run); full record = estimate for record_every=1;\n"
          "   impacts: counted in the loop over every step; exact = count of the exact motion (period\n"
          "   2 sqrt(2 H / g); the discrete period is longer by < 2 h); max dE/E0 = largest one-step energy\n"
          "   increase over every step")
    print(f"{'steps':>10} {'record':>22} {'rows':>8} {'wall s':>8} {'steps/s':>9} {'RSS before':>10} "
          f"{'peak RSS MiB':>12} "
          f"{'full record':>12} {'impacts':>8} {'exact':>8} {'max dE/E0':>9}")
    out = []
    T = 2 * np.sqrt(2 * 1.0 / 9.81)  # period of the elastic bounce from H = 1
    for steps in (short_steps, long_steps):
        for kw in ({"record_every": 10**4}, {"record": "events"}):
            r = long_run(steps, h, kw)
            t_end = steps * h
            expected = int(np.floor((t_end - T / 2) / T)) + 1
            r.update(kw=kw, expected_impacts=expected)
            out.append(r)
            rec = ", ".join(f"{k}={v}" for k, v in kw.items())
            print(f"{steps:10.0e} {rec:>22} {r['rows']:8d} {r['wall_s']:8.1f} {steps / r['wall_s']:9.3g} "
                  f"{r['rss_before_kib'] / 1024:10.1f} "
                  f"{r['rss_peak_kib'] / 1024:12.1f} {r['full_record_bytes'] / 2**30:9.1f} GiB {r['impacts']:8d} "
                  f"{expected:8d} {r['dE_max'] / r['E0']:9.1e}", flush=True)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--smoke", "--quick", action="store_true", help="tiny sizes: checks that the benchmark runs")
    ap.add_argument("--long-steps", type=float, default=1e8)
    ap.add_argument("--json", type=str, default=None, help="also write the rows to this file")
    args = ap.parse_args(argv)
    if c_compiler() is None:
        print("no C compiler: the figures below are for the CasADi VM")
    print(f"python {sys.version.split()[0]}, casadi {ca.__version__}, numpy {np.__version__}")
    if args.smoke:
        res = {"contacts": contacts_rows([1, 2], 2_000, 100), "bodies": bodies_rows([2], 2, 2_000, 100),
               "long": long_rows(int(min(args.long_steps, 2e4)), short_steps=10**4)}
    else:
        res = {"contacts": contacts_rows([1, 2, 4, 8, 16], 100_000, 2_000),
               "bodies": bodies_rows([4, 8, 16, 32], 4, 100_000, 2_000),
               "long": long_rows(int(args.long_steps))}
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=1, default=float))
    return res


if __name__ == "__main__":
    main()
