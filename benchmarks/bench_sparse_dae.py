"""Prototype, not library code: the stable inversion of the Cartesian flexible arm transcribed as a DAE.

How fast could the inversion of ``flexible_arm --set coordinates=cartesian`` be if the transcription
kept the sparsity of the model?  invctl's inverse model is the index-reduced ODE X' = F(X) in
X = (q, v, lam, u), whose z' = -A_z^-1 (...) is dense (docs/gallery.md).  Here instead, per node of a
separated Hermite-Simpson mesh, the unknowns are (q, v, a, lam, u) and the equations

    q' = v, v' = a                                     (collocation)
    M a - f - G^T lam - B u = 0                        (dynamics, algebraic)
    C a + (C v)'_q v - (0, y_ref'') + 2 w Phi_v + w^2 Phi_p = 0,   C = [G; h'],   w = 10/s
                                                       (constraints and servo constraint at acceleration
                                                        level, Baumgarte-stabilized)

so every row touches O(1) links and the Jacobian has O(n) nonzeros per node.  Boundary conditions
(6n, the differential states (q, v)): at T0 the state lies on the unstable eigenvector of the
linearization at the start equilibrium (6n - 1 rows: the drift of the constraints and the stable
internal modes are fixed), at Tf the unstable mode is zero at the end equilibrium (1 row).  The
horizon is the one invctl's plan derives for the angle model (same tails); the mesh is uniform with
N intervals.  IPOPT solves the square system with a zero Hessian (Newton), the project's options.

    python benchmarks/bench_sparse_dae.py [--n 2 4 8 16 32] [--N 200] [--smoke]

``--smoke`` (alias ``--quick``): n = 2, 3 and N = 20 (checks that the benchmark runs; its numbers are
not the benchmark's).

Prints per n: build and IPOPT time, iterations, unknowns, Jacobian nonzeros per node, and the largest
difference of u to invctl's inverse of the angle model on the same horizon (accuracy check), then the
fitted exponents.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import casadi as ca
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

import invctl_scenes.flexible_arm as fa  # noqa: E402
from invctl.inversion import EquilibriumSolver, invert  # noqa: E402
from invctl.inversion.backends import IPOPT_DEFAULTS, IPOPT_SQUARE_DEFAULTS  # noqa: E402

W = 10.0


def node_functions(model):
    """SX functions of one node: the algebraic residual (dynamics, stabilized acceleration level)."""
    th = ca.DM(model.theta_values)
    sub = lambda e: ca.substitute(ca.SX(e), model.theta, th)  # noqa: E731
    q, v = model.q, model.v
    k, l = model.n, model.ell
    a, z = ca.SX.sym("a", k), ca.SX.sym("z", l + 1)
    Y = ca.SX.sym("Y", 3)  # y_ref, y_ref', y_ref''
    M, f, B, g, G, h = (sub(e) for e in (model.M, model.f, model.B, model.g, model.G, model.h))
    H = ca.jacobian(h, q)
    C = ca.vertcat(G, H)
    dyn = ca.mtimes(M, a) - f - ca.mtimes(G.T, z[:l]) - B * z[l]
    Cv = ca.mtimes(C, v)
    phi_p = ca.vertcat(g, h - Y[0])
    phi_v = Cv - ca.vertcat(ca.SX.zeros(l), Y[1])
    acc = ca.mtimes(C, a) + ca.jtimes(Cv, q, v) - ca.vertcat(ca.SX.zeros(l), Y[2])
    alg = ca.vertcat(dyn, acc + 2 * W * phi_v + W * W * phi_p)
    return ca.Function("alg", [q, v, a, z, Y], [alg]), (q, v, a, z, Y, alg)


def linearization(parts, x_eq, z_eq, y):
    """A of x' = A x (x = (q, v)) at an equilibrium: (a, z) eliminated by the algebraic equations."""
    q, v, a, z, Y, alg = parts
    k = q.shape[0]
    Jx = ca.Function("jx", [q, v, a, z, Y], [ca.jacobian(alg, ca.vertcat(q, v))])
    Jw = ca.Function("jw", [q, v, a, z, Y], [ca.jacobian(alg, ca.vertcat(a, z))])
    args = [x_eq[:k], x_eq[k:], np.zeros(k), z_eq, [y, 0.0, 0.0]]
    dw = -np.linalg.solve(np.array(Jw(*args)), np.array(Jx(*args)))
    A = np.zeros((2 * k, 2 * k))
    A[:k, k:] = np.eye(k)
    A[k:, :] = dw[:k]
    return A


def solve(n: int, N: int, T0: float, Tf: float, pivot_order: int | None = None):
    model = fa.build(n=n, coordinates="cartesian")
    ref = fa.reference(model)
    k, l = model.n, model.ell
    t_build = time.perf_counter()
    alg_fn, parts = node_functions(model)
    nw = 2 * k + k + l + 1  # (q, v, a, z) per point
    # equilibria at both ends (the library's solver), as (q, v) and z
    eq = []
    for y in (float(ref(ref.t0).ravel()[0]), float(ref(ref.tf).ravel()[0])):
        X, _ = EquilibriumSolver(model).solve(np.array([y]), guess_q=fa.initial_configuration(model))
        X = np.asarray(X, float).ravel()
        eq.append((np.r_[X[:k], np.zeros(k)], X[2 * k:2 * k + l + 1], y))
    A0 = linearization(parts, *eq[0])
    Af = linearization(parts, *eq[1])
    ev0, V0 = np.linalg.eig(A0)
    iu = np.argmax(ev0.real)
    u0 = np.real(V0[:, iu])
    Qfull, _ = np.linalg.qr(np.c_[u0, np.eye(2 * k)[:, :2 * k - 1]])
    perp0 = Qfull[:, 1:]                   # orthonormal complement of the unstable direction
    evf, Vl = np.linalg.eig(Af.T)
    wu = np.real(Vl[:, np.argmax(evf.real)])  # left eigenvector of the unstable mode at the end
    # mesh and reference samples
    tm = np.linspace(T0, Tf, N + 1)
    hs = np.diff(tm)
    tc = 0.5 * (tm[:-1] + tm[1:])
    ts = np.empty(2 * N + 1)
    ts[0::2], ts[1::2] = tm, tc
    Ysamp = reference_samples(ref, ts)
    # one interval: node k, midpoint, node k+1 (variables w = (q, v, a, z))
    wk, wm, wk1 = (ca.SX.sym(s, nw) for s in ("wk", "wm", "wk1"))
    h = ca.SX.sym("h")

    def split(w):
        return w[:k], w[k:2 * k], w[2 * k:3 * k], w[3 * k:]

    qk, vk, ak, _ = split(wk)
    qm, vm, am, _ = split(wm)
    q1, v1, a1, _ = split(wk1)
    coll = ca.vertcat(q1 - qk - h / 6 * (vk + 4 * vm + v1), v1 - vk - h / 6 * (ak + 4 * am + a1),
                      qm - 0.5 * (qk + q1) - h / 8 * (vk - v1), vm - 0.5 * (vk + v1) - h / 8 * (ak - a1))
    interval = ca.Function("interval", [wk, wm, wk1, h], [coll])
    Ysym = ca.SX.sym("Ys", 3)
    wsym = ca.SX.sym("w", nw)
    node = ca.Function("node", [wsym, Ysym], [alg_fn(*split(wsym), Ysym)])
    x = ca.MX.sym("x", nw * (2 * N + 1))
    Wm = ca.reshape(x, nw, 2 * N + 1)
    g_coll = interval.map(N)(Wm[:, 0:-1:2], Wm[:, 1::2], Wm[:, 2::2], ca.DM(hs).T)
    g_alg = node.map(2 * N + 1)(Wm, ca.DM(Ysamp))
    x0, xf = Wm[:2 * k, 0], Wm[:2 * k, -1]
    bc = ca.vertcat(ca.mtimes(ca.DM(perp0.T), x0 - ca.DM(eq[0][0])), ca.mtimes(ca.DM(wu).T, xf - ca.DM(eq[1][0])))
    g = ca.vertcat(ca.vec(g_coll), ca.vec(g_alg), bc)
    assert g.shape[0] == x.shape[0], (g.shape, x.shape)
    opts = {**IPOPT_DEFAULTS, **IPOPT_SQUARE_DEFAULTS}
    lf, lg = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", g.shape[0])
    opts["hess_lag"] = ca.Function("zero_hess_lag", [x, ca.MX.sym("p", 0), lf, lg], [ca.MX(x.shape[0], x.shape[0])],
                                   ["x", "p", "lam_f", "lam_g"], ["triu_hess_gamma_x_x"])
    opts["ipopt.hessian_constant"] = "yes"
    if pivot_order is not None:
        opts["ipopt.mumps_pivot_order"] = pivot_order
    solver = ca.nlpsol("dae", "ipopt", {"x": x, "f": 0, "g": g}, opts)
    # guess: quasi-static blend of the two equilibria along the timing law
    s = (Ysamp[0] - eq[0][2]) / (eq[1][2] - eq[0][2])
    guess = np.zeros((nw, 2 * N + 1))
    for j, sj in enumerate(s):
        guess[:2 * k, j] = (1 - sj) * eq[0][0] + sj * eq[1][0]
        guess[3 * k:, j] = (1 - sj) * eq[0][1] + sj * eq[1][1]
    build_s = time.perf_counter() - t_build
    t = time.perf_counter()
    sol = solver(x0=guess.ravel(order="F"), lbg=0, ubg=0)
    solve_s = time.perf_counter() - t
    st = solver.stats()
    Wsol = np.array(sol["x"]).reshape(nw, 2 * N + 1, order="F")
    nnz = ca.Function("g", [x], [g]).sparsity_jac(0, 0).nnz()
    return {"n": n, "build_s": build_s, "solve_s": solve_s, "iterations": st["iter_count"],
            "status": st["return_status"],
            "eval_s": sum(st.get(f"t_wall_{f}", 0.0) for f in ("nlp_g", "nlp_jac_g", "nlp_f", "nlp_grad_f")), "unknowns": int(x.shape[0]), "nnz_per_node": nnz / (2 * N + 1),
            "t": ts, "u": Wsol[-1], "max_g": float(np.max(np.abs(np.array(sol["g"]))))}


def reference_samples(ref, ts):
    """(y_ref, y_ref', y_ref'') at the times ``ts`` (CasADi derivatives of the reference expression)."""
    t = ref.t
    e = ref.expr
    d1 = ca.jacobian(e, t)
    d2 = ca.jacobian(d1, t)
    f = ca.Function("yref", [t], [ca.vertcat(e, d1, d2)])
    return np.array(f.map(ts.size)(ca.DM(ts).T))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, nargs="*", default=[2, 4, 8, 16, 32])
    ap.add_argument("--N", type=int, default=200)
    ap.add_argument("--pivot-order", type=int, default=None,
                    help="ipopt.mumps_pivot_order (0 AMD, the project default; 2 AMF; 4 PORD; 6 QAMD; 7 auto)")
    ap.add_argument("--smoke", "--quick", action="store_true", help="tiny sizes: checks that the benchmark runs")
    args = ap.parse_args()
    if args.smoke:
        args.n, args.N = [2, 3], 20
    rows = []
    print(f"prototype sparse DAE transcription of the Cartesian flexible arm (HS separated, uniform N = {args.N}); "
          f"horizon of invctl's plan for the angle model; mumps_pivot_order = "
          f"{'project default (0, AMD)' if args.pivot_order is None else args.pivot_order}")
    print(f"{'n':>3s} {'build s':>8s} {'IPOPT s':>8s} {'(evals)':>8s} {'iter':>4s} {'unknowns':>9s} {'nnz/node':>9s} {'max|g|':>9s} "
          f"{'max|u - u_angles|':>17s} {'max|u|':>8s}  status")
    for n in args.n:
        A = fa.build(n=n)
        ra = fa.reference(A)
        ia = invert(A, ra, q_guess=np.zeros(n))
        T0, Tf = ia.diagnostics["T0"], ia.diagnostics["Tf"]
        r = solve(n, args.N, T0, Tf, args.pivot_order)
        ua = ia.u(r["t"]).ravel()
        r["du"] = float(np.max(np.abs(r["u"] - ua)))
        rows.append(r)
        print(f"{n:3d} {r['build_s']:8.2f} {r['solve_s']:8.2f} {r['eval_s']:8.2f} {r['iterations']:4d} {r['unknowns']:9d} "
              f"{r['nnz_per_node']:9.1f} {r['max_g']:9.1e} {r['du']:17.2e} {np.max(np.abs(ua)):8.3f}  {r['status']}",
              flush=True)
    ns = np.array([r["n"] for r in rows], float)
    for key in ("solve_s", "build_s", "nnz_per_node"):
        v = np.array([r[key] for r in rows], float)
        big = ns >= 8
        tail = np.polyfit(np.log(ns[big]), np.log(v[big]), 1)[0] if big.sum() >= 2 else float("nan")
        print(f"  {key:14s} p = {np.polyfit(np.log(ns), np.log(v), 1)[0]:5.2f} (all n), {tail:5.2f} (n >= 8)")


if __name__ == "__main__":
    main()
