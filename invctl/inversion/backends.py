"""Solvers of the square collocation system: IPOPT with an exact zero Hessian (the package
defaults, measured in ``benchmarks/bench_inversion.py``) and Newton's method with banded LU."""
from __future__ import annotations

import sys
import time

import casadi as ca
import numpy as np
import scipy.sparse.linalg as spl

IPOPT_DEFAULTS = {
    "ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes",
    "ipopt.tol": 1e-10, "ipopt.constr_viol_tol": 1e-10, "ipopt.acceptable_tol": 1e-8,
    "ipopt.linear_solver": "mumps",
    # MUMPS: start with a generous workspace so IPOPT never enters its
    # "increase mem_percent and refactorize" loop on large meshes
    "ipopt.mumps_mem_percent": 4000,
}

#: Extra defaults for square systems (measured in benchmarks/bench_inversion.py, docs/inversion.md):
#: MUMPS's scaling and MC64 permutation in the analysis phase cost ~6 ms of every IPOPT call on a
#: 1.4k-unknown mesh and buy nothing on the banded collocation KKT matrix; AMD ordering; no
#: least-squares multiplier estimate at the start (an extra factorization) and no NLP scaling.
IPOPT_SQUARE_DEFAULTS = {
    "ipopt.mumps_scaling": 0, "ipopt.mumps_permuting_scaling": 0, "ipopt.mumps_pivot_order": 0,
    "ipopt.constr_mult_init_max": 0.0, "ipopt.nlp_scaling_method": "none",
    "ipopt.mu_strategy": "monotone", "ipopt.mu_init": 1e-10,
}


#: IPOPT statuses of a solve stopped by its time limit (no continuation after those)
_TIME_LIMIT = ("Maximum_WallTime_Exceeded", "Maximum_CpuTime_Exceeded")


class _Progress(ca.Callback):
    """IPOPT iteration callback printing one line per iteration to stderr.

    One per transcription (:func:`_progress_of`), kept alive with it: a cached solver keeps
    calling the callback it was built with, so the callback must not be part of what makes a
    solver new (and must outlive the solve)."""

    def __init__(self, nx, ng, np_, label):
        ca.Callback.__init__(self)
        self.nx, self.ng, self.np_, self.label = nx, ng, np_, label
        self.restart(label)
        self.construct("progress", {})

    def restart(self, label):
        self.label, self.k, self.t = label, 0, time.perf_counter()

    def get_n_in(self):
        return ca.nlpsol_n_out()

    def get_n_out(self):
        return 1

    def get_name_in(self, i):
        return ca.nlpsol_out(i)

    def get_name_out(self, i):
        return "ret"

    def get_sparsity_in(self, i):
        n = ca.nlpsol_out(i)
        if n in ("f",):
            return ca.Sparsity.dense(1)
        if n in ("x", "lam_x"):
            return ca.Sparsity.dense(self.nx)
        if n in ("g", "lam_g"):
            return ca.Sparsity.dense(self.ng)
        if n == "lam_p":
            return ca.Sparsity.dense(self.np_)
        return ca.Sparsity(0, 0)

    def eval(self, arg):
        g = np.array(arg[ca.nlpsol_out().index("g")]).ravel()
        viol = float(np.max(np.abs(g))) if g.size else 0.0
        print(f"  [{self.label}] iter {self.k:3d}  max|g| = {viol:.3e}  ({time.perf_counter() - self.t:.2f} s)",
              file=sys.stderr, flush=True)
        self.k += 1
        return [0]


def _progress_of(tr, label) -> _Progress:
    cb = getattr(tr, "_progress", None)
    if cb is None:
        cb = tr._progress = _Progress(tr.nX, tr.ng, tr.np, label)
    cb.restart(label)
    return cb


def _newton(tr, x0, p, *, max_iter, tol, max_wall_time=np.inf, progress=False, label="", banded=True, lu=None):
    """Newton's method on the square collocation system with Jacobian reuse.

    Residual and Jacobian come from :meth:`Transcription.evaluators`; the Jacobian, permuted
    to time order, is a band matrix factorized by LAPACK's banded LU (SuperLU when the band
    is too wide or ``banded=False``). The factorization is kept (also across calls on the
    same transcription, e.g. re-solves after a parameter change) while it contracts the
    residual by at least a factor 4 per step (simplified Newton), and refreshed
    otherwise; a refreshed step that does not decrease the residual is damped.  ``lu``: a factorization to
    start with (e.g. of a neighbouring problem; default: the transcription's kept one)."""
    x = np.array(x0, float)
    t_start = time.perf_counter()
    residual, residual_and_jacobian = tr.evaluators()
    band = tr.banded_pattern() if banded else None
    band = band if band is not None and band.worthwhile else None
    g = residual(x, p)
    nrm = np.linalg.norm(g)
    lu = getattr(tr, "_lu", None) if lu is None else lu
    fresh = False
    status, it, n_fact = "Maximum_Iterations_Exceeded", 0, 0
    for it in range(1, max_iter + 1):
        if np.max(np.abs(g)) < tol:
            status = "Solve_Succeeded"
            it -= 1
            break
        if time.perf_counter() - t_start > max_wall_time:
            status = "Maximum_WallTime_Exceeded"
            break
        if lu is not None and not fresh:
            dx = -lu.solve(g)
            g2 = residual(x + dx, p)
            n2 = np.linalg.norm(g2)
            if np.isfinite(n2) and (n2 <= 0.25 * nrm or np.max(np.abs(g2)) < tol):
                x, g, nrm = x + dx, g2, n2
                if progress:
                    print(f"  [{label}] newton {it:3d}  max|g| = {np.max(np.abs(g)):.3e}  (reused Jacobian)",
                          file=sys.stderr)
                continue
        _, J = residual_and_jacobian(x, p)
        try:
            lu = band.factor(J.data) if band is not None else spl.splu(J, permc_spec="COLAMD")
            n_fact += 1
        except RuntimeError:
            status = "Singular_Jacobian"
            break
        fresh = True
        dx = -lu.solve(g)
        s = 1.0
        while True:
            g2 = residual(x + s * dx, p)
            n2 = np.linalg.norm(g2)
            if np.isfinite(n2) and (n2 <= (1 - 1e-4 * s) * nrm or np.max(np.abs(g2)) < tol):
                break
            s *= 0.5
            if s < 1e-6:
                break
        if s < 1e-6:
            status = "Line_Search_Failed"
            break
        x, g, nrm = x + s * dx, g2, n2
        fresh = s < 1.0  # after a damped step refresh again
        if progress:
            print(f"  [{label}] newton {it:3d}  max|g| = {np.max(np.abs(g)):.3e}  step {s:.3g}", file=sys.stderr)
    else:
        if np.max(np.abs(g)) < tol:
            status = "Solve_Succeeded"
    if lu is not None and status == "Solve_Succeeded":
        tr._lu = lu
    return x, {"status": status, "iterations": it, "success": status == "Solve_Succeeded",
               "max_constraint_violation": float(np.max(np.abs(g))), "factorizations": n_fact}
