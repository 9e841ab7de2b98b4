"""Moreau-Jean time-stepping (theta-method, impulse-level complementarity).

One step from ``(q_k, v_k, t_k)`` (event-capturing: impacts are not located,
they are absorbed in the step where the gap closes):

1. ``W_hat = M + h theta C + (h theta)^2 K`` with ``K = -dF/dq``,
   ``C = -dF/dv`` of the closed-loop force ``F = f + B u(q, v, t)``;
   ``v_free = v_k + W_hat^{-1} h (F_theta - h theta K v_k)`` (one Newton step of
   the theta-method; exact for forces linear in (q, v)).
2. Active set: contact ``i`` is active when its predicted gap
   ``f_i(q_k) + h/2 W_i^T v_k <= tol_act`` (the *activation tolerance*,
   default 1e-12: a strict test ``<= 0`` lets round-off open a pre-loaded
   contact, after which the gap drifts to O(h^2 |a|), see docs/clearances.md).
3. Impulse LCP (Newton's law at velocity level, 000 (4)):
   ``0 <= W^T v_{k+1} + e min(W^T v_k, 0)  _|_  P >= 0`` on active contacts,
   ``v_{k+1} = v_free + W_hat^{-1} W P``, solved exactly and branch-free
   (:func:`invctl.contact.lcp.lcp_sx`: enumeration for <= 4 contacts, block
   principal pivoting beyond, or Lemke), with a convergence flag per step.
4. ``q_{k+1} = q_k + h (theta v_{k+1} + (1-theta) v_k)``; optional
   position projection (a few linearized LCP projections in the metric M) so
   that every gap is >= -1e-10 whatever h.

Bilateral constraints ``g(q) = 0`` are enforced at velocity level
(``G v_{k+1} = 0``) through the projected operator of 000 (8).

The time loop is compiled: the step is a CasADi Function whose state carries
every number (model parameters, gains, h, theta, tolerances) and the exact
running statistics (smallest gaps, largest energy/V increase, rest time,
impact and active-set change counts), iterated by ``mapaccum`` in chunks; the chunk
runs in the CasADi virtual machine or as generated C compiled with the system
C compiler (cached on disk), chosen automatically (``backend="auto"``).
Chunks stream into a :class:`~invctl.simulate.contact_record.ChunkRecorder`
that keeps every step, every ``record_every``-th step or the event steps;
the memory of a run is estimated before it starts.  A step whose LCP flag
says "not solved" is recomputed exactly (numpy LCP) or stops the run.
"""
from __future__ import annotations

import hashlib
import subprocess
import sys
import time

import casadi as ca
import numpy as np

from ..contact.lcp import lcp_residual, lcp_sx, solve_lcp
from ..contact.mechanics import ContactSystem
from ..control.pdplus import FeedbackLaw, zero_input
from ..errors import (ContactError, ParameterError, ResourceLimitError, SimulationFailed, check_interrupt,
                      INTERRUPT_LIKE, is_interrupt)
from ..results import Status
from .codegen import Layout, c_compiler, compile_c, cse, generate_c, small_solve
from .contact_record import ChunkRecorder, ContactTrajectory, RowLayout, check_budget

__all__ = ["MoreauJean", "ContactTrajectory", "DEFAULT_ACTIVATION_TOL", "c_compiler"]

#: default activation tolerance on the predicted gap (same units as the gaps)
DEFAULT_ACTIVATION_TOL = 1e-12
#: instruction count of one fused loop iteration above which fewer steps are fused and C is built at -O1
_LARGE_STEP = 20000
#: contacts up to which the C driver has one compiled step per active set
_MAX_SPECIALIZED = 3


class MoreauJean:
    """Compiled Moreau-Jean stepper for a model with gaps under a feedback law.

    Build once, run many times with other parameters, gains, h, theta or
    tolerances (all carried in the compiled loop's state: no re-tracing).

    Parameters
    ----------
    model : Model
        Model with ``gaps`` (unilateral constraints).
    law : FeedbackLaw, optional
        Closed-loop input; default ``u = 0`` with ``V`` = mechanical energy.
    potential : casadi.SX, optional
        Potential energy ``U(q, theta)`` for the energy history.
    projection : bool
        Add the position projection (gaps >= -1e-10 for any h).
    projection_iters : int
        Linearized projection passes (1 is exact for linear gaps).
    backend : {"auto", "vm", "c"}
        ``auto`` uses generated C when a compiler is present, else the VM.
    chunk : int, optional
        Steps per compiled call (the granularity of the streaming, and the
        work redone after a step whose LCP had to be recomputed); default
        8192, fewer (down to 256) for large steps.
    substeps : int
        Steps inlined in one loop iteration (fewer VM dispatches); reduced
        automatically for large steps (many contacts or bodies).
    max_enum : int
        Contacts up to which ``lcp="auto"`` solves the LCPs by enumeration.
    lcp : {"auto", "enumeration", "pivoting", "lemke", "pgs"}
        LCP method inside the step (see :func:`invctl.contact.lcp.lcp_sx`);
        all but ``pgs`` are exact and every step carries a convergence flag.
    lcp_iters : int, optional
        Iteration (pivoting) or pivot (Lemke) budget per LCP.
    """

    def __init__(self, model, law: FeedbackLaw | None = None, *, potential=None, projection: bool = False,
                 projection_iters: int = 8, backend: str = "auto", chunk: int | None = None, substeps: int = 4,
                 max_enum: int = 4, lcp: str = "auto", lcp_iters: int | None = None, pgs_sweeps: int = 50,
                 verbose: bool = False):
        if backend not in ("auto", "vm", "c"):
            raise ParameterError(f"backend must be 'auto', 'vm' or 'c', got {backend!r}")
        if lcp not in ("auto", "enumeration", "pivoting", "lemke", "pgs"):
            raise ParameterError(f"lcp must be 'auto', 'enumeration', 'pivoting', 'lemke' or 'pgs', got {lcp!r}")
        self.model = model
        self.cs = ContactSystem(model)
        self.law = law or zero_input(potential)
        self.potential = potential
        self.projection = bool(projection)
        self.projection_iters = int(projection_iters)
        self.substeps = int(substeps)
        self.chunk = None if chunk is None else int(chunk)
        if self.substeps < 1 or (chunk is not None and (self.chunk % self.substeps or self.chunk < 64)):
            raise ParameterError(f"chunk ({chunk}) must be >= 64 and a multiple of substeps ({substeps})")
        self.max_enum = int(max_enum)
        self.lcp = lcp
        self.lcp_iters = lcp_iters
        self.pgs_sweeps = int(pgs_sweeps)
        self.verbose = verbose
        self._build()
        if self.chunk is None:
            # about 2e7 instructions per chunk: streaming overhead < 1 %, little work lost on a recomputed step
            self.chunk = int(min(8192, max(256, 1 << int(np.log2(2e7 / self.step.n_instructions())))))
        if backend == "auto":
            backend = "c" if c_compiler() else "vm"
        self.backend = backend
        self._loops: dict = {}

    # ----------------------------------------------------------------- build
    def _solve_lcp(self, A, b):
        return lcp_sx(A, b, method=self.lcp, max_enum=self.max_enum, max_iter=self.lcp_iters,
                      pgs_sweeps=self.pgs_sweeps, with_flag=True)

    def _build(self):
        mdl, cs = self.model, self.cs
        n, mu = mdl.n, cs.m_u
        q, v, th = mdl.q, mdl.v, mdl.theta
        t = ca.SX.sym("t")
        u, V, kappa = self.law.symbolic(mdl, t)
        th_c = ca.SX.sym("theta_ctrl", th.shape[0])  # the controller's model parameters (nominal)
        u, V = ca.substitute([u, V], [th], [th_c])
        self.n_theta, self.n_kappa = th.shape[0], kappa.shape[0]
        # the run's numbers: an input held constant over the loop (not carried state)
        play = Layout([("th", self.n_theta), ("thc", self.n_theta), ("kappa", self.n_kappa), ("h", 1), ("thm", 1),
                       ("tol", 1), ("t0", 1), ("vtol", 1), ("rtol", 1)])
        # the loop state: (q, v, t), values at the current state, exact running statistics
        lay = Layout([("q", n), ("v", n), ("t", 1), ("k", 1), ("gap", mu), ("U", mu), ("E", 1), ("V", 1),
                      ("loaded", mu), ("act", mu), ("gap_min", mu), ("dE_max", 1), ("dV_max", 1),
                      ("dV_max_impact", 1), ("dV_max_smooth", 1), ("rest_last_bad", mu), ("n_impacts", 1),
                      ("n_changes", 1), ("lcp_res_max", 1), ("P_sum", mu)])
        self._lay, self._play = lay, play
        self.nx, self.np_ = lay.size, play.size
        sym = {"q": q, "v": v, "t": t, "th": th, "thc": th_c, "kappa": kappa}
        for name, size in lay.parts + play.parts:
            if name not in sym:
                sym[name] = ca.SX.sym(name, size)
        X = ca.vertcat(*[sym[name] for name, _ in lay.parts])
        Pr = ca.vertcat(*[sym[name] for name, _ in play.parts])
        h, thm, tol, t0, kk = sym["h"], sym["thm"], sym["tol"], sym["t0"], sym["k"]
        t_next = t0 + (kk + 1) * h
        E = 0.5 * ca.mtimes([v.T, mdl.M, v]) + (0 if self.potential is None else self.potential)
        U = ca.mtimes(cs.W.T, v)
        # values at a state: evaluated once at the start, then carried from step to step
        self._post = ca.Function("mj_post", [X, Pr], [cs.gap, U, E, V, u], ["x", "p"], ["gap", "U", "E", "V", "u"])
        self.f_uV = ca.Function("uV", [q, v, t, th_c, kappa], [u, V])

        # stage 1: free velocity, Delassus matrix and impulse LCP data (000 (4), (8))
        F = mdl.f + ca.mtimes(mdl.B, u)
        Kq = -ca.jacobian(F, q)
        Cv = -ca.jacobian(F, v)
        Fth = thm * ca.substitute(F, t, t_next) + (1 - thm) * F if ca.depends_on(F, t) else F
        What = mdl.M + h * thm * Cv + (h * thm) ** 2 * Kq
        r = h * (Fth - h * thm * ca.mtimes(Kq, v))
        Wn = cs.W
        sol = small_solve(What, ca.horzcat(r, Wn))
        if mdl.ell:
            G = mdl.G
            WiG = small_solve(What, G.T)
            S = ca.mtimes(G, WiG)
            # velocity-level G v_{k+1} = 0 through the projected operator of 000 (8)
            corr = ca.mtimes(WiG, small_solve(S, ca.mtimes(G, ca.horzcat(v, ca.SX.zeros(n, mu)) + sol)))
            sol = sol - corr
        dv_free, WiW = sol[:, 0], sol[:, 1:]
        v_free = v + dv_free
        gap_c, U_c = sym["gap"], sym["U"]
        act = ca.if_else(gap_c + 0.5 * h * U_c <= tol, 1, 0) if mu else ca.SX(0, 1)
        D = ca.mtimes(Wn.T, WiW)
        # Newton's law acts on approaching contacts only (000 (4): v_n(t-) <= 0)
        b = ca.mtimes(Wn.T, v_free) + cs.e * ca.fmin(U_c, 0)
        a_s = ca.SX.sym("a", mu)  # the active set (1/0)
        Dm = ca.SX(D)
        for i in range(mu):
            for j in range(mu):
                Dm[i, j] = a_s[i] * a_s[j] * D[i, j] + (1 - a_s[i] if i == j else 0)
        f_lcp_a = ca.Function("mj_lcp_a", [X, Pr, a_s], [Dm, a_s * b])
        self._f_lcp = ca.Function("mj_lcp", [X, Pr], [*f_lcp_a(X, Pr, act), act], ["x", "p"], ["D", "b", "active"])
        Ps = ca.SX.sym("P", mu)
        vn = v_free + ca.mtimes(WiW, Ps)
        self._f_after = ca.Function("mj_after", [X, Pr, Ps], [q + h * (thm * vn + (1 - thm) * v), vn],
                                    ["x", "p", "P"], ["q_next", "v_next"])
        # position projection data at a configuration qq (metric M(qq))
        qq = ca.SX.sym("qq", n)
        Wq = ca.substitute(Wn, q, qq)
        MiW = small_solve(ca.substitute(mdl.M, q, qq), Wq)
        self._f_proj = ca.Function("mj_proj", [qq, X, Pr],
                                   [ca.mtimes(Wq.T, MiW), ca.substitute(cs.gap, q, qq), MiW],
                                   ["q", "x", "p"], ["A", "gap", "MiW"])

        # stage 3: the new state with its carried values and running statistics, and the step's output row
        qn_s, vn_s, act_s = ca.SX.sym("qn", n), ca.SX.sym("vn", n), ca.SX.sym("act_s", mu)
        ok_s, res_s = ca.SX.sym("ok"), ca.SX.sym("res")
        core_n = ca.vertcat(qn_s, vn_s, t_next)
        Xpost = ca.vertcat(core_n, X[lay["t"].stop:])
        gap_n, U_n, E_n, V_n, _ = self._post(Xpost, Pr)
        loaded = Ps > 0
        s = sym
        imp = loaded * (1 - s["loaded"]) * (U_c < -s["vtol"])
        any_imp = ca.mmax(imp) if mu else ca.SX(0)
        chg = (ca.sumsqr(act_s - s["act"]) + ca.sumsqr(loaded - s["loaded"])) > 0
        dE, dV = E_n - s["E"], V_n - s["V"]
        still = (ca.fabs(U_n) <= s["rtol"]) * (gap_n <= ca.fmax(1e-9, 10 * h * s["rtol"]))
        new = {"k": kk + 1, "gap": gap_n, "U": U_n, "E": E_n, "V": V_n, "loaded": loaded, "act": act_s,
               "gap_min": ca.fmin(s["gap_min"], gap_n), "dE_max": ca.fmax(s["dE_max"], dE),
               "dV_max": ca.fmax(s["dV_max"], dV),
               "dV_max_impact": ca.if_else(any_imp, ca.fmax(s["dV_max_impact"], dV), s["dV_max_impact"]),
               "dV_max_smooth": ca.if_else(any_imp, s["dV_max_smooth"], ca.fmax(s["dV_max_smooth"], dV)),
               "rest_last_bad": ca.if_else(still, s["rest_last_bad"], kk + 1),
               "n_impacts": s["n_impacts"] + ca.sum1(imp), "n_changes": s["n_changes"] + chg,
               "lcp_res_max": ca.fmax(s["lcp_res_max"], res_s),
               "P_sum": s["P_sum"] + Ps}
        Xn = ca.vertcat(core_n, *[new[name] for name, _ in lay.parts[lay.parts.index(("k", 1)):]])
        Yrow = ca.vertcat(q, v, t, gap_c, U_c, s["E"], s["V"], u, Ps, act_s, U_n, imp, ca.fmax(any_imp, chg), ok_s)
        self._f_finish = ca.Function("mj_finish", [X, Pr, Ps, act_s, qn_s, vn_s, ok_s, res_s], [Xn, Yrow],
                                     ["x", "p", "P", "active", "q_next", "v_next", "ok", "res"], ["x_next", "y"])
        self.rows = RowLayout(n, mu, mdl.m)
        assert Yrow.shape[0] == self.rows.ny

        # the compiled step: stages composed with the symbolic LCP solver
        def step_with(a):
            """The step's new state and row for the active set ``a`` (symbolic, or constant 0/1)."""
            Dm_x, bm_x = f_lcp_a(X, Pr, a)
            P, ok = self._solve_lcp(Dm_x, bm_x)
            res = ca.mmax(ca.fabs(ca.fmin(P, ca.mtimes(Dm_x, P) + bm_x))) if mu else ca.SX(0)
            qn, vn = self._f_after(X, Pr, P)
            if self.projection:
                for _ in range(self.projection_iters):
                    Ap, gp, MiWp = self._f_proj(qn, X, Pr)
                    mu_p, ok_p = self._solve_lcp(Ap, gp)
                    qn = qn + ca.mtimes(MiWp, mu_p)
                    ok = ok * ok_p
            return cse(*self._f_finish(X, Pr, P, a, qn, vn, ok, res))

        Xn, Y = step_with(act)
        self.ny = Y.shape[0]
        self.step = ca.Function("mj_step", [X, Pr], [Xn, Y], ["x", "p"], ["x_next", "y"])
        # for the C driver: the step with its purely parametric part hoisted out of the loop (``mj_pre(p) -> c``,
        # computed once per call), and the same step for a known active set (constants fold: no LCP without
        # active contacts, only the active contacts' subsets else); ``mj_act(x, c)`` picks the variant:
        # one per active set up to _MAX_SPECIALIZED contacts, else the step without active contacts and the
        # generic step.  The same operations in the same order: the same numbers to the last bit.
        L = self.rows
        ok_i, ev_i = L.sl("ok").start, L.sl("event").start
        if mu <= _MAX_SPECIALIZED:
            masks = [[(code >> i) & 1 for i in range(mu)] for code in range(1 << mu)]
            pick = sum((2 ** i) * act[i] for i in range(mu)) if mu else ca.SX(0)
            variants = [step_with(ca.SX(ca.DM(mk))) if mu else (Xn, Y) for mk in masks]
        else:
            pick = ca.fmin(ca.sum1(act), 1)
            variants = [step_with(ca.SX.zeros(mu)), (Xn, Y)]
        exprs = [pick]
        for Xv, Yv in variants:
            # flags: the LCP flag, the event flag, the variant of the next step (its active set)
            fl = ca.vertcat(Yv[ok_i], Yv[ev_i], ca.substitute(pick, X, Xv))
            exprs += [Xv, Yv, fl]
        outs, csym, cexpr = ca.extract_parametric(exprs, Pr, {"extract_trivial": True})
        C = ca.vertcat(*csym) if csym else ca.SX(0, 1)
        self._pre = ca.Function("mj_pre", [Pr], [ca.vertcat(*cexpr) if cexpr else ca.SX(0, 1)], ["p"], ["c"])
        self._pick = ca.Function("mj_pick", [X, C], [outs[0]], ["x", "c"], ["variant"])
        # each variant with its row (recorded steps) and without (the others: less work)
        self._variants = []
        for i in range(len(variants)):
            Xv, Yv, fl = outs[1 + 3 * i:4 + 3 * i]
            self._variants += [ca.Function(f"mj_row{i}", [X, C], [Xv, Yv, fl], ["x", "c"], ["x_next", "y", "flags"]),
                               ca.Function(f"mj_fast{i}", [X, C], [Xv, fl], ["x", "c"], ["x_next", "flags"])]

    def _substeps(self) -> int:
        s = self.substeps
        while s > 1 and self.step.n_instructions() * s > _LARGE_STEP:
            s //= 2
        while self.chunk % s:
            s -= 1
        return max(s, 1)

    def _fused(self, S: int):
        """``S`` steps inlined in one Function (fewer VM calls); its second
        output stacks the rows ``y`` of the steps."""
        X, Pr = ca.SX.sym("x", self.nx), ca.SX.sym("p", self.np_)
        xs, ys = X, []
        for _ in range(S):
            xs, y = self.step(xs, Pr)
            ys.append(y)
        return ca.Function("mj_fused", [X, Pr], [xs, ca.vertcat(*ys)], ["x", "p"], ["x_next", "y"])

    def _loop(self, backend: str, size: int, S: int):
        """The chunk runner: a C driver loop around the compiled step (``backend="c"``), else
        ``mapaccum`` of the fused steps in the CasADi VM."""
        key = (backend, size, S)
        if key in self._loops:
            return self._loops[key]
        runner = None
        if backend == "c":
            try:
                lib = compile_c(_driver_code(self), large=self.step.n_instructions() > _LARGE_STEP,
                                verbose=self.verbose)
                runner = None if lib is None else _CDriver(self, lib, size)
            except (OSError, RuntimeError, subprocess.SubprocessError) as exc:
                print(f"invctl: generated-C backend unavailable ({exc}); using the CasADi VM", file=sys.stderr)
        if runner is None:
            fused = self._fused(S)
            acc = fused.mapaccum("mj_acc", size // S)
            Xs, Ps = ca.MX.sym("x", self.nx), ca.MX.sym("p", self.np_)
            # a name unique to this loop's code: several loops may live in one process
            tag = hashlib.sha256(fused.serialize().encode() + str(size).encode()).hexdigest()[:16]
            loop = ca.Function(f"mj_{tag}", [Xs, Ps], acc(Xs, ca.repmat(Ps, 1, size // S)), ["x", "p"],
                               ["x_acc", "y"])
            runner = _VMChunks(self, loop, size, S)
        self._loops[key] = runner
        return runner

    # ------------------------------------------------------------------- run
    def initial_state(self, q0, v0, t0=0.0, *, h, theta=0.5, params=None, gains=None,
                      activation_tol=DEFAULT_ACTIVATION_TOL, ctrl_params=None, impact_vel_tol: float = 1e-8,
                      rest_vel_tol: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(x, p)``: the loop state at ``(q0, v0, t0)`` (the values at the state:
        gaps, normal velocities, energy, V, and the statistics seeds) and the
        numbers of the run (parameters, gains, h, theta, tolerances)."""
        mdl, lay, play = self.model, self._lay, self._play
        th = mdl.theta_values if params is None else np.asarray(params, float).ravel()
        thc = th if ctrl_params is None else np.asarray(ctrl_params, float).ravel()
        if th.size != self.n_theta or thc.size != self.n_theta:
            raise ParameterError(f"params must have length {self.n_theta} ({mdl.params.names})")
        kap = np.asarray(self.law.kappa_values if gains is None else gains, float).ravel()
        if kap.size != self.n_kappa:
            raise ParameterError(f"gains has length {kap.size}, law {self.law.name!r} has {self.law.kappa_names}")
        if not (h > 0 and np.isfinite(h)):
            raise ParameterError(f"time step h must be positive and finite, got {h}")
        if not 0.0 <= theta <= 1.0:
            raise ParameterError(f"theta of the theta-method must lie in [0, 1], got {theta}")
        if not (impact_vel_tol >= 0 and np.isfinite(impact_vel_tol)):
            raise ParameterError(f"impact_vel_tol must be >= 0 and finite, got {impact_vel_tol}")
        rtol = 10 * impact_vel_tol if rest_vel_tol is None else float(rest_vel_tol)
        if not (rtol >= 0 and np.isfinite(rtol)):
            raise ParameterError(f"rest_vel_tol must be >= 0 and finite, got {rest_vel_tol}")
        q0 = np.asarray(q0, float).ravel()
        v0 = np.asarray(v0, float).ravel()
        if q0.size != mdl.n or v0.size != mdl.n:
            raise ParameterError(f"q0, v0 must have length n = {mdl.n}, got {q0.size}, {v0.size}")
        x, p = np.zeros(self.nx), np.zeros(self.np_)
        for name, val in (("q", q0), ("v", v0), ("t", t0)):
            x[lay[name]] = val
        for name, val in (("th", th), ("thc", thc), ("kappa", kap), ("h", h), ("thm", theta),
                          ("tol", activation_tol), ("t0", t0), ("vtol", impact_vel_tol), ("rtol", rtol)):
            p[play[name]] = val
        gap, U, E, V, _ = (np.array(a, float).ravel() for a in self._post(x, p))
        if not (np.all(np.isfinite(gap)) and np.all(np.isfinite(U)) and np.isfinite(E[0]) and np.isfinite(V[0])):
            raise ParameterError(f"the initial state gives non-finite gaps/energy/V (gaps {gap.tolist()}, E {E[0]}, "
                                 f"V {V[0]}); check q0, v0 and the parameters")
        still = (np.abs(U) <= rtol) & (gap <= max(1e-9, 10 * h * rtol))
        for name, val in (("gap", gap), ("U", U), ("E", E), ("V", V), ("gap_min", gap),
                          ("rest_last_bad", np.where(still, -1.0, 0.0))):
            x[lay[name]] = val
        return x, p

    def reference_step(self, x, p, *, method: str = "auto"):
        """One step from loop state ``x`` (run numbers ``p``) with the LCPs solved by the numpy
        solvers (:func:`~invctl.contact.lcp.solve_lcp`: enumeration or Lemke,
        exact, any size).  Used to recompute a step whose compiled LCP did not
        converge, and as the numpy reference of the compiled loop.

        Returns ``(x_next, y)`` (loop state and output row); raises
        :class:`ContactError` when an LCP has no solution.
        """
        x = np.asarray(x, float)
        Dm, bm, act = (np.array(a, float) for a in self._f_lcp(x, p))
        mu = self.cs.m_u
        P = solve_lcp(Dm.reshape(mu, mu), bm.ravel(), method=method, check_unique=False).z if mu else np.zeros(0)
        qn, vn = (np.array(a, float).ravel() for a in self._f_after(x, p, P))
        if self.projection:
            for _ in range(self.projection_iters):
                Ap, gp, MiW = (np.array(a, float) for a in self._f_proj(qn, x, p))
                mu_p = solve_lcp(Ap.reshape(mu, mu), gp.ravel(), method=method, check_unique=False).z
                qn = qn + MiW.reshape(-1, mu) @ mu_p
        res = lcp_residual(Dm.reshape(mu, mu), bm.ravel(), P) if mu else 0.0
        xn, y = self._f_finish(x, p, P, act, qn, vn, 1.0, res)
        return np.array(xn, float).ravel(), np.array(y, float).ravel()

    def reference_run(self, q0, v0, steps: int, h: float, *, method: str = "lemke", **kw):
        """``steps`` steps of :meth:`reference_step` in a Python loop (numpy LCP
        solvers); returns ``(q, v)``, each ``(n, steps + 1)`` with time along
        the last axis like :attr:`ContactTrajectory.q`.  A slow, independent
        check of the compiled loop, not for production runs."""
        x, p = self.initial_state(q0, v0, kw.pop("t0", 0.0), h=h, **kw)
        lay = self._lay
        Q, Vv = np.empty((self.model.n, steps + 1)), np.empty((self.model.n, steps + 1))
        Q[:, 0], Vv[:, 0] = x[lay["q"]], x[lay["v"]]
        for k in range(steps):
            x, _ = self.reference_step(x, p, method=method)
            Q[:, k + 1], Vv[:, k + 1] = x[lay["q"]], x[lay["v"]]
        return Q, Vv

    def _state_at(self, x_in, p, Xacc, use: int, size: int, S: int) -> np.ndarray:
        """Loop state after ``use`` steps of a chunk started at ``x_in``:
        the accumulated state after the last whole fused group, then at most
        ``S - 1`` single steps (the statistics must stop exactly at ``use``)."""
        if use == size:
            return Xacc[:, -1].copy()
        g = use // S
        x = x_in.copy() if g == 0 else Xacc[:, g - 1].copy()
        for _ in range(use - g * S):
            x = np.array(self.step(x, p)[0], float).ravel()
        return x

    def _final_row(self, x, p) -> np.ndarray:
        lay, L = self._lay, self.rows
        row = np.zeros(L.ncols)
        gap, U, E, V, u = (np.array(a, float).ravel() for a in self._post(x, p))
        for name, val in (("q", x[lay["q"]]), ("v", x[lay["v"]]), ("t", x[lay["t"]]), ("gap", x[lay["gap"]]),
                          ("U", x[lay["U"]]), ("E", x[lay["E"]]), ("V", x[lay["V"]]), ("u", u)):
            row[L.sl(name)] = val
        return row

    def run(self, q0, v0, t_end: float, h: float, *, t0: float = 0.0, theta: float = 0.5, params=None,
            gains=None, activation_tol: float = DEFAULT_ACTIVATION_TOL, backend: str | None = None,
            ctrl_params=None, impact_vel_tol: float | None = None, progress: bool | None = None,
            record: str = "steps", record_every: int = 1, memory_budget=None, rest_vel_tol: float | None = None,
            on_lcp_failure: str = "recompute") -> ContactTrajectory:
        """Simulate from ``(q0, v0)`` at ``t0`` to ``t_end`` with step ``h``.

        Parameters
        ----------
        params : array, optional
            Plant parameter vector (default: the model's values).
        ctrl_params : array, optional
            Parameter vector the law is evaluated with (default: ``params``);
            differs from ``params`` for a mismatched plant.
        gains : array, optional
            Law parameters (default: the law's values; see ``law.values(...)``).
        theta : float
            Theta of the theta-method (1/2: energy-conserving for linear
            conservative forces and e = 1; 1: implicit Euler, dissipative).
        activation_tol : float
            Predicted-gap threshold of the active-set decision.
        impact_vel_tol : float, optional
            Approach speed above which a newly loaded contact counts as an
            impact (default 1e-8).
        rest_vel_tol : float, optional
            Normal speed below which a closed contact counts as at rest for
            :meth:`ContactTrajectory.rest_time` (default ``10 impact_vel_tol``).
        progress : bool, optional
            Report progress on stderr (default: only for runs of more than 5e6 steps).
        record : {"steps", "events"}
            ``steps``: every ``record_every``-th step (step 0 included) and the
            final state.  ``events``: the steps with an impact or a change of
            the active or loaded set, the first step and the final state (and
            every ``record_every``-th step when ``record_every > 1``).
            Statistics that need every step are exact either way.
        record_every : int
            Decimation of the record (1: every step).
        memory_budget : float, optional
            Bytes the run may use (default: half the memory available when it
            starts).  The need is estimated before the run; a run that does
            not fit raises :class:`ResourceLimitError` naming the settings that
            fit; an event record that outgrows the budget stops with the
            record so far in ``exc.partial``.
        on_lcp_failure : {"recompute", "raise"}
            What to do with a step whose compiled LCP did not converge (its
            flag is 0): recompute that step with the exact numpy solvers and
            continue (counted in ``stats["lcp_recomputed"]``), or raise
            :class:`ContactError` with the trajectory so far in ``partial``.
        """
        if record not in ("steps", "events"):
            raise ParameterError(f"record must be 'steps' or 'events', got {record!r}")
        try:
            every = int(record_every)
        except (TypeError, ValueError):
            raise ParameterError(f"record_every must be a positive integer, got {record_every!r}") from None
        if every < 1 or every != record_every:
            raise ParameterError(f"record_every must be a positive integer, got {record_every!r}")
        if on_lcp_failure not in ("recompute", "raise"):
            raise ParameterError(f"on_lcp_failure must be 'recompute' or 'raise', got {on_lcp_failure!r}")
        vtol = 1e-8 if impact_vel_tol is None else float(impact_vel_tol)
        x, p = self.initial_state(q0, v0, t0, h=h, theta=theta, params=params, gains=gains,
                                  activation_tol=activation_tol, ctrl_params=ctrl_params, impact_vel_tol=vtol,
                                  rest_vel_tol=rest_vel_tol)
        if not np.isfinite(t_end):
            raise ParameterError(f"t_end must be finite, got {t_end}")
        N = int(np.ceil((t_end - t0) / h - 1e-9))
        if N <= 0:
            raise ParameterError(f"t_end = {t_end} must exceed t0 = {t0}")
        backend = backend or self.backend
        if backend not in ("vm", "c"):
            raise ParameterError(f"backend must be 'vm' or 'c', got {backend!r}")
        if progress is None:
            progress = N > 5_000_000
        S = self._substeps()
        # one compiled chunk size for C (compiled once, cached on disk); smaller VM loops for short runs
        size = self.chunk if (N >= self.chunk or backend == "c") else max(64, 1 << (N - 1).bit_length())
        size = max(size, S) // S * S
        L = self.rows
        events = record == "events"
        loop = self._loop(backend, size, S)
        buffer_bytes = loop.nbytes + 8 * L.ncols * size
        est = check_budget(N=N, h=h, t0=t0, every=every, events=events, row_bytes=ChunkRecorder.row_bytes_of(L),
                           buffer_bytes=buffer_bytes, budget=memory_budget)
        limit = est["budget_bytes"]
        rec = ChunkRecorder(L, N, every, events, t0, h)
        # rows the recorder may keep: every ``every``-th step, and with the impact table the event steps
        # and the steps after them
        keep_events = int(rec.impacts)
        xin = np.array(x, float)
        x_init = xin.copy()
        done, recomputed, c = 0, 0, 0
        meta = dict(h=h, backend=loop.backend, est=est, every=every, record=record, vtol=vtol, x_init=x_init,
                    p=p)
        tic = time.perf_counter()
        try:
            while done < N:
                check_interrupt()
                Ych, cols, use, status, x_after = loop(xin, p, done, min(N - done, size), every, keep_events)
                if status == _NONFINITE:
                    rec.consume(Ych, use, done, self._after_values(x_after), cols)
                    raise SimulationFailed(
                        f"Moreau-Jean: non-finite state at step {done + use} (t = {t0 + (done + use) * h:.6g}); "
                        "reduce h or check the model/gains", partial=self._package(rec, None, done + use, 0.0, meta),
                        diagnostics={"step": done + use})
                rec.consume(Ych, use, done, self._after_values(x_after), cols)
                done += use
                if status == _LCP_FAILED:
                    if on_lcp_failure == "raise":
                        Dm, bm, _ = self._f_lcp(x_after, p)
                        raise ContactError(
                            f"Moreau-Jean: the compiled LCP ({self.lcp}) did not converge at step {done} "
                            f"(t = {t0 + done * h:.6g}); raise lcp_iters, use lcp='lemke', or "
                            "on_lcp_failure='recompute' (exact numpy LCP for such steps)",
                            partial=self._package(rec, x_after, done, time.perf_counter() - tic, meta),
                            diagnostics={"step": done, "D": np.array(Dm).tolist(), "b": np.array(bm).ravel().tolist()})
                    try:
                        x_after, yrow = self.reference_step(x_after, p)
                    except ContactError as exc:
                        raise ContactError(f"Moreau-Jean step {done} (t = {t0 + done * h:.6g}): {exc}",
                                           partial=self._package(rec, None, done, time.perf_counter() - tic, meta),
                                           diagnostics={"step": done, **exc.diagnostics}) from exc
                    rec.consume(yrow.reshape(-1, 1), 1, done, self._after_values(x_after))
                    done += 1
                    recomputed += 1
                xin[:] = x_after
                if rec.nbytes() + buffer_bytes > limit:
                    raise ResourceLimitError(
                        f"Moreau-Jean: the record ({rec.nbytes() / 2**20:.4g} MiB after {done} of {N} steps: "
                        f"{rec.n_imp_rows} impacts) outgrew the memory budget {limit / 2**20:.4g} MiB; use "
                        f"record_every > {every} without record='events', a shorter t_end or a larger memory_budget",
                        partial=self._package(rec, xin.copy(), done, time.perf_counter() - tic, meta),
                        diagnostics={"steps_done": done, "record_bytes": rec.nbytes(), "budget_bytes": limit})
                c += 1
                if progress and c % 50 == 0:
                    print(f"\rinvctl: moreau-jean {done}/{N} steps", end="", file=sys.stderr)
        except INTERRUPT_LIKE as _exc:
            if not is_interrupt(_exc):
                raise
            from ..errors import RunInterrupted

            rec.settle()
            if not rec.rows()[0].shape[0]:  # interrupted before the first row was kept: the initial state
                rec.finish(self._final_row(meta["x_init"], p), 0)
            part = self._package(rec, None, done, time.perf_counter() - tic, meta)
            part.status, part.message = Status.INTERRUPTED, f"interrupted after {done} of {N} steps"
            raise RunInterrupted(f"Moreau-Jean interrupted after {done} of {N} steps (t = {t0 + done * h:.6g})",
                                 partial=part) from None
        wall = time.perf_counter() - tic
        if progress:
            print(file=sys.stderr)
        meta["recomputed"] = recomputed
        return self._package(rec, xin, N, wall, meta)

    def _after_values(self, x):
        """``v``, ``V``, ``E`` of a loop state (the post-impact values of the last step of a chunk)."""
        lay = self._lay
        return {"v": x[lay["v"]], "V": x[lay["V"]][0], "E": x[lay["E"]][0]}

    def _package(self, rec: ChunkRecorder, x_final, N: int, wall: float, meta: dict) -> ContactTrajectory:
        """The trajectory of the recorded rows (and ``x_final``, the state after
        step ``N``, with the run's statistics; None for a partial record)."""
        L, lay = self.rows, self._lay
        if x_final is not None:
            rec.finish(self._final_row(x_final, meta["p"]), N)
        R, Sx = rec.rows()
        col = lambda name: R[:, L.sl(name)].T  # noqa: E731  (views, time along the last axis)
        nP = R.shape[0] - 1 if x_final is not None else R.shape[0]
        x0, play = meta["p"], self._play
        stats = {"wall_s": wall, "steps": N, "steps_per_s": N / wall if wall > 0 else float("inf"),
                 "backend": meta["backend"], "Un": col("U"), "u": col("u"), "theta_m": float(x0[play["thm"]][0]),
                 "activation_tol": float(x0[play["tol"]][0]), "projection": int(self.projection),
                 "record": meta["record"], "record_every": meta["every"], "step_index": Sx,
                 "lcp_method": self.lcp, "lcp_recomputed": int(meta.get("recomputed", 0)),
                 "memory_estimate_bytes": meta["est"]["estimate_bytes"],
                 "memory_budget_bytes": meta["est"]["budget_bytes"], "rest_vel_tol": float(x0[play["rtol"]][0])}
        if x_final is not None:
            for name in ("gap_min", "P_sum", "rest_last_bad"):
                stats[name] = np.array(x_final[lay[name]])
            for name in ("dE_max", "dV_max", "dV_max_impact", "dV_max_smooth", "lcp_res_max"):
                stats[name] = float(x_final[lay[name]][0])
            for name in ("n_impacts", "n_changes"):
                stats[name] = int(round(x_final[lay[name]][0]))
            stats["rest_last_bad"] = stats["rest_last_bad"].astype(np.int64)
        else:
            stats["partial"] = True
        if not rec.complete:
            stats.update(rec.impact_table())
        names = {"q": list(self.model.q_names), "gaps": list(self.cs.names), "u": list(self.model.u_names)}
        return ContactTrajectory(col("t")[0], col("q"), col("v"), col("P")[:, :nP], col("act")[:, :nP] > 0.5,
                                 col("gap"), col("E")[0], col("V")[0], meta["h"], names, stats, meta["vtol"])


# ---------------------------------------------------------------- chunk runners
#: status of a chunk: all steps done, a step whose compiled LCP did not converge, a non-finite state
_DONE, _LCP_FAILED, _NONFINITE = 0, 1, 2


class _VMChunks:
    """Chunks of ``size`` steps through ``mapaccum`` of ``S`` fused steps (CasADi VM): every row is output."""

    backend = "vm"

    def __init__(self, mj: MoreauJean, loop: ca.Function, size: int, S: int):
        self.mj, self.size, self.S = mj, size, S
        self.Xacc = np.zeros((mj.nx, size // S), order="F")
        self.Y = np.zeros((mj.ny, size), order="F")
        self.nbytes = 8 * (self.Y.size + self.Xacc.size)
        self.xin, self.p = np.zeros(mj.nx), np.zeros(mj.np_)
        self.buf, self.call = loop.buffer()
        self.buf.set_arg(0, memoryview(self.xin))  # type: ignore[arg-type]
        self.buf.set_arg(1, memoryview(self.p))  # type: ignore[arg-type]
        self.buf.set_res(0, memoryview(self.Xacc.reshape(-1, order="F")))  # type: ignore[arg-type]
        self.buf.set_res(1, memoryview(self.Y.reshape(-1, order="F")))  # type: ignore[arg-type]

    def __call__(self, x, p, base: int, n: int, every: int, keep_events: int):
        """``(Y, None, use, status, x_after)``: the rows of steps ``0..use-1`` are ``Y[:, :use]``."""
        mj, Y = self.mj, self.Y
        self.xin[:], self.p[:] = x, p
        self.call()
        use, status = n, _DONE
        okrow = Y[mj.rows.sl("ok").start, :use]
        if not okrow.all():
            use, status = int(np.argmin(okrow > 0.5)), _LCP_FAILED
        x_after = mj._state_at(self.xin, p, self.Xacc, use, self.size, self.S)
        nv = mj._lay["v"].stop
        if not np.all(np.isfinite(x_after[:nv])):
            bad = np.flatnonzero(~np.all(np.isfinite(Y[:nv, :use]), axis=0))
            if bad.size:
                use = int(bad[0])
                x_after = mj._state_at(self.xin, p, self.Xacc, use, self.size, self.S)
            status = _NONFINITE
        return Y, None, use, status, x_after


def _driver_code(mj: MoreauJean) -> str:
    """C of the step (``mj_pre``, ``mj_core``) and of the loop around it: ``mj_drive`` computes the
    parametric part once, then runs the steps, keeping the rows of every ``every``-th step (global
    index) and, with ``keep_events``, of the event steps and the steps after them; it stops before
    a step whose LCP flag is 0 and after a step that leaves a non-finite ``(q, v)``."""
    fns = (mj._pre, mj._pick, *mj._variants)
    nv = len(mj._variants) // 2
    sz = {k: max(getattr(f, f"sz_{k}")() for f in fns) for k in ("arg", "res", "iw", "w")}
    row_case = "\n".join(f"      case {i}: mj_row{i}(arg, res, iw, w, 0); break;" for i in range(nv))
    fast_case = "\n".join(f"      case {i}: mj_fast{i}(arg, res, iw, w, 0); break;" for i in range(nv))
    code = generate_c(*fns)
    # fmin/fmax with C99's semantics (a NaN operand loses), inlined instead of libm calls
    for name, op in (("fmin", "<"), ("fmax", ">")):
        code = code.replace(f"return {name}(x, y);", f"return x {op} y ? x : (y == y ? y : x);")
    return code + f"""
#include <string.h>
#define MJ_NX {mj.nx}
#define MJ_NY {mj.ny}
#define MJ_NC {max(1, mj._pre.nnz_out(0))}
#define MJ_NQV {mj._lay["v"].stop}

static void mj_row(int v, const casadi_real** arg, casadi_real** res, casadi_int* iw, casadi_real* w) {{
    switch (v) {{
{row_case}
    }}
}}

CASADI_SYMBOL_EXPORT int mj_drive(const casadi_real* p, casadi_real* x, casadi_real* Y, long long* cols,
                                  long long n, long long base, long long every, int keep_events,
                                  long long* out) {{
  const casadi_real* arg[{sz["arg"] + 2}];
  casadi_real* res[{sz["res"] + 3}];
  casadi_int iw[{sz["iw"] + 1}];
  casadi_real w[{sz["w"] + 1}], c[MJ_NC], xb[MJ_NX], fl[3], s;
  casadi_real *xc = x, *xn = xb, *xt;
  long long j, r = 0, cnt = (every - base % every) % every;
  int i, v, rec, ev, prev_ev = 0, status = 0;
  arg[0] = p; res[0] = c;
  if (mj_pre(arg, res, iw, w, 0)) return 1;
  arg[1] = c;
  arg[0] = x; res[0] = fl + 2;
  mj_pick(arg, res, iw, w, 0);
  for (j = 0; j < n; ++j) {{
    v = (int)fl[2];
    rec = cnt == 0 || prev_ev;
    arg[0] = xc; res[0] = xn;
    if (rec) {{
      res[1] = Y + r * MJ_NY; res[2] = fl;
      mj_row(v, arg, res, iw, w);
    }} else {{
      res[1] = fl;
      switch (v) {{
{fast_case}
      }}
    }}
    if (!(fl[0] > 0.5)) {{ status = 1; break; }}
    ev = keep_events && fl[1] > 0.5;
    if (ev && !rec) {{  /* an event step: its row, the same step again */
      res[1] = Y + r * MJ_NY; res[2] = fl;
      mj_row(v, arg, res, iw, w);
      rec = 1;
    }}
    if (rec) cols[r++] = j;
    prev_ev = ev;
    cnt = cnt == 0 ? every - 1 : cnt - 1;
    s = 0;
    for (i = 0; i < MJ_NQV; ++i) s += xn[i];
    xt = xc; xc = xn; xn = xt;
    if (!(s - s == 0)) {{ status = 2; ++j; break; }}
  }}
  if (xc != x) memcpy(x, xc, MJ_NX * sizeof(casadi_real));
  out[0] = j; out[1] = r; out[2] = status;
  return 0;
}}
"""


class _CDriver:
    """Chunks through ``mj_drive`` (generated C, loaded with ctypes): only the kept rows are written."""

    backend = "c"

    def __init__(self, mj: MoreauJean, lib, size: int):
        import ctypes

        self.mj, self.size = mj, size
        self.lib = ctypes.CDLL(str(lib))
        f = self.lib.mj_drive
        vp, ll = ctypes.c_void_p, ctypes.c_longlong
        f.argtypes = [vp, vp, vp, vp, ll, ll, ll, ctypes.c_int, vp]
        f.restype = ctypes.c_int
        self.f = f
        self.Y = np.zeros((mj.ny, size), order="F")
        self.cols = np.zeros(size, np.int64)
        self.out = np.zeros(3, np.int64)
        self.x, self.p = np.zeros(mj.nx), np.zeros(mj.np_)
        self.nbytes = 8 * (self.Y.size + size)
        self._ptr = [a.ctypes.data for a in (self.p, self.x, self.Y, self.cols)] + [self.out.ctypes.data]

    def __call__(self, x, p, base: int, n: int, every: int, keep_events: int):
        """``(Y, cols, use, status, x_after)``: the kept rows ``Y[:, :r]`` are steps ``cols``."""
        self.x[:], self.p[:] = x, p
        pp, px, pY, pc, po = self._ptr
        if self.f(pp, px, pY, pc, n, base, every, keep_events, po):
            raise SimulationFailed("Moreau-Jean: the compiled parametric part of the step failed")
        use, r, status = (int(v) for v in self.out)
        return self.Y, self.cols[:r], use, status, self.x.copy()
