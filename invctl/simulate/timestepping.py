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
   ``v_{k+1} = v_free + W_hat^{-1} W P``, solved branch-free
   (:func:`invctl.contact.lcp.lcp_sx`, exact enumeration for <= 4 contacts).
4. ``q_{k+1} = q_k + h (theta v_{k+1} + (1-theta) v_k)``; optional
   position projection (a few linearized LCP projections in the metric M) so
   that every gap is >= -1e-10 whatever h.

Bilateral constraints ``g(q) = 0`` are enforced at velocity level
(``G v_{k+1} = 0``) through the projected operator of 000 (8).

The time loop is compiled: the step is a CasADi Function whose state carries
every number (model parameters, gains, h, theta, tolerance), iterated by
``mapaccum`` in chunks; the chunk runs in the CasADi virtual machine or as
generated C compiled with the system C compiler (cached on disk), chosen
automatically (``backend="auto"``).
"""
from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import casadi as ca
import numpy as np

from ..contact.lcp import lcp_sx
from ..contact.mechanics import ContactSystem
from ..control.pdplus import FeedbackLaw, zero_input
from ..errors import ParameterError, SimulationFailed

__all__ = ["MoreauJean", "ContactTrajectory", "DEFAULT_ACTIVATION_TOL", "c_compiler"]

#: default activation tolerance on the predicted gap (same units as the gaps)
DEFAULT_ACTIVATION_TOL = 1e-12


def c_compiler() -> str | None:
    """Path of a C compiler (``$CC``, gcc, cc, clang) or None."""
    for name in (os.environ.get("CC"), "gcc", "cc", "clang"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


def _cache_dir() -> Path:
    """``$INVCTL_CACHE`` or ``~/.cache/invctl`` (a temporary folder if neither is writable)."""
    d = Path(os.environ.get("INVCTL_CACHE", Path.home() / ".cache" / "invctl"))
    try:
        d.mkdir(parents=True, exist_ok=True)
        if not os.access(d, os.W_OK):
            raise OSError(f"{d} is not writable")
    except OSError:
        d = Path(tempfile.gettempdir()) / f"invctl-cache-{os.getuid()}"
        d.mkdir(parents=True, exist_ok=True)
    return d


@dataclass
class ContactTrajectory:
    """Result of a time-stepping (or event-driven) contact simulation.

    Arrays have time along the first axis; ``q``, ``v`` include ``t[0]``.
    ``P`` are the impulses of each step (``P/h`` estimates the contact
    force), ``active`` the active-set flags, ``energy`` the mechanical
    energy and ``V`` the Lyapunov function of the law (at ``t[k]``).
    """

    t: np.ndarray
    q: np.ndarray
    v: np.ndarray
    P: np.ndarray
    active: np.ndarray
    gaps: np.ndarray
    energy: np.ndarray
    V: np.ndarray
    h: float
    names: dict = field(default_factory=dict)
    stats: dict = field(default_factory=dict)
    impact_vel_tol: float = 1e-8

    # ---------------------------------------------------------- derived data
    def impacts(self, contact: int | None = None):
        """Impact steps (see :meth:`impact_mask`); returns arrays
        ``(times, contact index, pre-impact normal velocity, post-impact
        normal velocity, post-impact v)``.  The impact time is reported as
        the mid-point of the step (first-order accurate)."""
        pre, post = self.stats["Un"][:-1], self.stats["Un"][1:]
        hit = self.impact_mask()
        if contact is not None:
            hit[:, [i for i in range(hit.shape[1]) if i != contact]] = False
        k, i = np.nonzero(hit)
        return self.t[k] + 0.5 * self.h, i, pre[k, i], post[k, i], self.v[k + 1]

    def impact_mask(self) -> np.ndarray:
        """``(steps, m_u)`` flags of impacts: the contact carries an impulse, was
        approaching (``W_i^T v_k < -impact_vel_tol``) and carried none in the
        previous step (so persistent contact along a curved boundary, whose
        normal velocity is O(h) each step, is not counted as impacts)."""
        Un = self.stats.get("Un")
        if Un is None:
            raise SimulationFailed("trajectory has no normal velocities (stats['Un'])")
        loaded = self.P > 0
        prev = np.vstack([np.zeros((1, loaded.shape[1]), bool), loaded[:-1]])
        return loaded & ~prev & (Un[:-1] < -self.impact_vel_tol)

    @property
    def impact_times(self) -> np.ndarray:
        """Sorted distinct impact times (event-driven results: the located times)."""
        if "impact_t" in self.stats:
            return np.unique(np.asarray(self.stats["impact_t"], float))
        return np.unique(self.impacts()[0])

    @property
    def max_gap_violation(self) -> float:
        """``max(0, -min gap)`` over the trajectory."""
        return float(max(0.0, -self.gaps.min())) if self.gaps.size else 0.0

    @property
    def max_V_increase(self) -> float:
        """Largest one-step increase of ``V`` (should be <= round-off for
        dissipative laws, 000 (39)/(55))."""
        return float(np.max(np.diff(self.V), initial=0.0))

    def rest_time(self, contact: int = 0, vel_tol: float | None = None) -> float:
        """First time after which contact ``contact`` stays closed with zero
        normal velocity (nan if it never settles)."""
        Un = self.stats["Un"][:, contact]
        tol = vel_tol if vel_tol is not None else 10 * self.impact_vel_tol
        still = (np.abs(Un) <= tol) & (self.gaps[:, contact] <= max(1e-9, 10 * self.h * tol))
        bad = np.flatnonzero(~still)
        if bad.size == 0:
            return float(self.t[0])
        if bad[-1] == still.size - 1:
            return float("nan")
        return float(self.t[bad[-1] + 1])

    # ------------------------------------------------------------ save / plot
    def save(self, path) -> Path:
        """Write to ``.npz``."""
        path = Path(path)
        extra = {f"stats_{k}": np.asarray(v) for k, v in self.stats.items()
                 if isinstance(v, (int, float, np.ndarray, np.floating, str))}
        np.savez(path, t=self.t, q=self.q, v=self.v, P=self.P, active=self.active, gaps=self.gaps,
                 energy=self.energy, V=self.V, h=self.h, impact_vel_tol=self.impact_vel_tol,
                 names=np.array(repr(self.names)), **extra)
        return path

    @classmethod
    def load(cls, path) -> "ContactTrajectory":
        """Read a file written by :meth:`save`."""
        import ast

        d = np.load(path, allow_pickle=False)
        stats = {}
        for k in d.files:
            if k.startswith("stats_"):
                val = d[k]
                stats[k[6:]] = val.item() if val.ndim == 0 else val
        return cls(d["t"], d["q"], d["v"], d["P"], d["active"], d["gaps"], d["energy"], d["V"], float(d["h"]),
                   ast.literal_eval(str(d["names"])), stats, float(d["impact_vel_tol"]))

    def plot(self, path=None, **kw):
        """Phase portrait, gaps, impulses, energy and V (see :mod:`invctl.plot.contact`)."""
        from ..plot.contact import plot_contact_trajectory

        return plot_contact_trajectory(self, path=path, **kw)


def _small_solve(A, B):
    """``A^{-1} B`` for symbolic ``A``: adjugate formula for n <= 3 (few
    operations, exploits structural zeros), symbolic QR beyond."""
    n = A.shape[0]
    if n == 1:
        return B / A[0, 0]
    if n == 2:
        det = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
        adj = ca.blockcat([[A[1, 1], -A[0, 1]], [-A[1, 0], A[0, 0]]])
        return ca.mtimes(adj, B) / det
    if n == 3:
        c = [[A[(i + 1) % 3, (j + 1) % 3] * A[(i + 2) % 3, (j + 2) % 3]
              - A[(i + 1) % 3, (j + 2) % 3] * A[(i + 2) % 3, (j + 1) % 3] for j in range(3)] for i in range(3)]
        det = A[0, 0] * c[0][0] + A[0, 1] * c[0][1] + A[0, 2] * c[0][2]
        adj = ca.blockcat([[c[j][i] for j in range(3)] for i in range(3)])
        return ca.mtimes(adj, B) / det
    return ca.solve(A, B)


def _cse(*exprs):
    """Common-subexpression elimination (CasADi >= 3.6), if available."""
    if hasattr(ca, "cse"):
        out = ca.cse(list(exprs))
        return tuple(out)
    return exprs


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
    chunk : int
        Steps per compiled call.
    substeps : int
        Steps inlined in one loop iteration (fewer VM dispatches).
    max_enum : int
        Contacts up to which the impulse LCP is solved by exact enumeration.
    """

    def __init__(self, model, law: FeedbackLaw | None = None, *, potential=None, projection: bool = False,
                 projection_iters: int = 8, backend: str = "auto", chunk: int = 8192, substeps: int = 4,
                 max_enum: int = 4,
                 verbose: bool = False):
        if backend not in ("auto", "vm", "c"):
            raise ParameterError(f"backend must be 'auto', 'vm' or 'c', got {backend!r}")
        self.model = model
        self.cs = ContactSystem(model)
        self.law = law or zero_input(potential)
        self.potential = potential
        self.projection = bool(projection)
        self.projection_iters = int(projection_iters)
        self.chunk = int(chunk)
        self.substeps = int(substeps)
        if self.substeps < 1 or self.chunk % self.substeps or self.chunk < 64:
            raise ParameterError(f"chunk ({chunk}) must be >= 64 and a multiple of substeps ({substeps})")
        self.max_enum = int(max_enum)
        self.verbose = verbose
        self._build()
        if backend == "auto":
            backend = "c" if c_compiler() else "vm"
        self.backend = backend
        self._loops: dict = {}

    # ----------------------------------------------------------------- build
    def _build(self):
        mdl, cs = self.model, self.cs
        n, mu = mdl.n, cs.m_u
        q, v, th = mdl.q, mdl.v, mdl.theta
        t = ca.SX.sym("t")
        u, V, kappa = self.law.symbolic(mdl, t)
        th_c = ca.SX.sym("theta_ctrl", th.shape[0])  # the controller's model parameters (nominal)
        u, V = ca.substitute([u, V], [th], [th_c])
        h = ca.SX.sym("h")
        thm = ca.SX.sym("theta_m")
        tol = ca.SX.sym("tol_act")
        self.n_theta, self.n_kappa = th.shape[0], kappa.shape[0]
        X = ca.vertcat(q, v, t, th, th_c, kappa, h, thm, tol)
        self.nx = X.shape[0]
        F = mdl.f + ca.mtimes(mdl.B, u)
        Kq = -ca.jacobian(F, q)
        Cv = -ca.jacobian(F, v)
        if ca.depends_on(F, t):
            Fth = thm * ca.substitute(F, t, t + h) + (1 - thm) * F
        else:
            Fth = F
        What = mdl.M + h * thm * Cv + (h * thm) ** 2 * Kq
        r = h * (Fth - h * thm * ca.mtimes(Kq, v))
        Wn = cs.W
        rhs = ca.horzcat(r, Wn)
        sol = _small_solve(What, rhs)
        if mdl.ell:
            G = mdl.G
            WiG = _small_solve(What, G.T)
            S = ca.mtimes(G, WiG)
            # velocity-level G v_{k+1} = 0 through the projected operator of 000 (8)
            corr = ca.mtimes(WiG, _small_solve(S, ca.mtimes(G, ca.horzcat(v, ca.SX.zeros(n, mu)) + sol)))
            sol = sol - corr
        dv_free, WiW = sol[:, 0], sol[:, 1:]
        v_free = v + dv_free
        U = ca.mtimes(Wn.T, v)
        gap = cs.gap
        act = ca.if_else(gap + 0.5 * h * U <= tol, 1, 0) if mu else ca.SX(0, 1)
        D = ca.mtimes(Wn.T, WiW)
        # Newton's law acts on approaching contacts only (000 (4): v_n(t-) <= 0)
        b = ca.mtimes(Wn.T, v_free) + cs.e * ca.fmin(U, 0)
        Dm = ca.SX(D)
        for i in range(mu):
            for j in range(mu):
                Dm[i, j] = act[i] * act[j] * D[i, j] + (1 - act[i] if i == j else 0)
        P = lcp_sx(Dm, act * b, max_enum=self.max_enum)
        v_next = v_free + ca.mtimes(WiW, P)
        q_next = q + h * (thm * v_next + (1 - thm) * v)
        if self.projection:
            for _ in range(self.projection_iters):
                gq = ca.substitute(gap, q, q_next)
                Wq = ca.substitute(Wn, q, q_next)
                Mq = ca.substitute(mdl.M, q, q_next)
                MiW = _small_solve(Mq, Wq)
                mu_p = lcp_sx(ca.mtimes(Wq.T, MiW), gq, max_enum=self.max_enum)
                q_next = q_next + ca.mtimes(MiW, mu_p)
        t_next = t + h
        E = 0.5 * ca.mtimes([v.T, mdl.M, v]) + (0 if self.potential is None else self.potential)
        Xn = ca.vertcat(q_next, v_next, t_next, th, th_c, kappa, h, thm, tol)
        # outputs refer to the step start (k): energy, V, gaps, normal velocity; and the step's P, active set
        Y = ca.vertcat(P, act)
        self.ny = Y.shape[0]
        Xn, Y = _cse(Xn, Y)
        self.step = ca.Function("mj_step", [X], [Xn, Y], ["x"], ["x_next", "y"])
        # energy, V, input, gaps, normal velocities: evaluated after the loop on the whole trajectory (map)
        self._post = ca.Function("mj_post", [X], [ca.vertcat(gap, U, E, V, u)], ["x"], ["z"])
        self.f_uV = ca.Function("uV", [q, v, t, th_c, kappa], [u, V])

    def _fused(self):
        """``substeps`` steps inlined in one Function (fewer VM calls); its second
        output stacks ``(q, v, t, P, active)`` after each substep."""
        X = ca.SX.sym("x", self.nx)
        xs, ys = X, []
        n = self.model.n
        for _ in range(self.substeps):
            xs, y = self.step(xs)
            ys.append(ca.vertcat(xs[:2 * n + 1], y))
        return ca.Function("mj_fused", [X], [xs, ca.vertcat(*ys)], ["x"], ["x_next", "y"])

    def _loop(self, backend: str, size: int):
        key = (backend, size)
        if key in self._loops:
            return self._loops[key]
        fused = self._fused()
        # a name unique to this loop's code: several compiled loops may live in one process
        tag = hashlib.sha256(fused.serialize().encode() + str(size).encode()).hexdigest()[:16]
        loop = fused.mapaccum(f"mj_{tag}", size // self.substeps)
        if backend == "c":
            try:
                loop = self._compile(loop)
            except (OSError, RuntimeError, subprocess.SubprocessError) as exc:
                print(f"invctl: generated-C backend unavailable ({exc}); using the CasADi VM", file=sys.stderr)
        self._loops[key] = loop
        return loop

    def _compile(self, fn: ca.Function) -> ca.Function:
        cc = c_compiler()
        if cc is None:
            return fn
        with tempfile.TemporaryDirectory() as tmp:
            src = Path(tmp) / f"{fn.name()}.c"
            cg = ca.CodeGenerator(src.name, {"with_header": False})
            cg.add(fn)
            cg.generate(str(tmp) + os.sep)
            code = src.read_text()
        key = hashlib.sha256(code.encode()).hexdigest()[:20]
        lib = _cache_dir() / f"mj_{key}.so"
        if not lib.exists():
            csrc = _cache_dir() / f"mj_{key}.{os.getpid()}.c"
            csrc.write_text(code)
            tmp_lib = lib.with_suffix(f".{os.getpid()}.tmp.so")
            cmd = [cc, "-O3", "-march=native", "-fPIC", "-shared", str(csrc), "-o", str(tmp_lib), "-lm"]
            if self.verbose:
                print("invctl: compiling time-stepping loop:", " ".join(cmd), file=sys.stderr)
            res = subprocess.run(cmd, capture_output=True, text=True)
            if res.returncode != 0:
                cmd.remove("-march=native")
                res = subprocess.run(cmd, capture_output=True, text=True)
                if res.returncode != 0:
                    print(f"invctl: C compilation failed, using the CasADi VM:\n{res.stderr[:500]}", file=sys.stderr)
                    return fn
            os.replace(tmp_lib, lib)
            csrc.unlink(missing_ok=True)
        return ca.external(fn.name(), str(lib))

    # ------------------------------------------------------------------- run
    def initial_state(self, q0, v0, t0=0.0, *, h, theta=0.5, params=None, gains=None,
                      activation_tol=DEFAULT_ACTIVATION_TOL, ctrl_params=None) -> np.ndarray:
        mdl = self.model
        th = mdl.theta_values if params is None else np.asarray(params, float)
        thc = th if ctrl_params is None else np.asarray(ctrl_params, float)
        if th.size != self.n_theta or thc.size != self.n_theta:
            raise ParameterError(f"params must have length {self.n_theta} ({mdl.params.names})")
        kap = np.asarray(self.law.kappa_values if gains is None else gains, float)
        if kap.size != self.n_kappa:
            raise ParameterError(f"gains has length {kap.size}, law {self.law.name!r} has {self.law.kappa_names}")
        if not (h > 0 and np.isfinite(h)):
            raise ParameterError(f"time step h must be positive and finite, got {h}")
        if not 0.0 <= theta <= 1.0:
            raise ParameterError(f"theta of the theta-method must lie in [0, 1], got {theta}")
        q0 = np.asarray(q0, float).ravel()
        v0 = np.asarray(v0, float).ravel()
        if q0.size != mdl.n or v0.size != mdl.n:
            raise ParameterError(f"q0, v0 must have length n = {mdl.n}, got {q0.size}, {v0.size}")
        return np.r_[q0, v0, t0, th, thc, kap, h, theta, activation_tol]

    def run(self, q0, v0, t_end: float, h: float, *, t0: float = 0.0, theta: float = 0.5, params=None,
            gains=None, activation_tol: float = DEFAULT_ACTIVATION_TOL, backend: str | None = None,
            ctrl_params=None,
            impact_vel_tol: float | None = None, progress: bool | None = None) -> ContactTrajectory:
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
        progress : bool, optional
            Report progress on stderr (default: only for runs of more than 5e6 steps).
        """
        x = self.initial_state(q0, v0, t0, h=h, theta=theta, params=params, gains=gains,
                               activation_tol=activation_tol, ctrl_params=ctrl_params)
        x_init = x.copy()
        N = int(np.ceil((t_end - t0) / h - 1e-9))
        if N <= 0:
            raise ParameterError(f"t_end = {t_end} must exceed t0 = {t0}")
        backend = backend or self.backend
        if progress is None:
            progress = N > 5_000_000
        # one compiled chunk size for C (compiled once, cached on disk); smaller VM loops for short runs
        size = self.chunk if (N >= self.chunk or backend == "c") else max(64, 1 << (N - 1).bit_length())
        size = max(size, self.substeps) // self.substeps * self.substeps
        loop = self._loop(backend, size)
        nchunks = -(-N // size)
        n, mu = self.model.n, self.cs.m_u
        nyf = 2 * n + 1 + 2 * mu
        Xacc = np.zeros((self.nx, size // self.substeps), order="F")
        Yall = np.zeros((nyf, nchunks * size), order="F")
        xin = np.array(x, float)
        buf, run_chunk = loop.buffer()
        buf.set_arg(0, memoryview(xin))
        buf.set_res(0, memoryview(Xacc.reshape(-1, order="F")))
        tic = time.perf_counter()
        for c in range(nchunks):
            buf.set_res(1, memoryview(Yall[:, c * size:(c + 1) * size].reshape(-1, order="F")))
            run_chunk()
            xin[:] = Xacc[:, -1]
            if progress and (c % 50 == 0):
                print(f"\rinvctl: moreau-jean {min(N, (c + 1) * size)}/{N} steps", end="", file=sys.stderr)
        wall = time.perf_counter() - tic
        if progress:
            print(file=sys.stderr)
        Y = Yall[:, :N]
        X = np.repeat(x_init.reshape(-1, 1), N, axis=1)
        X[:2 * n + 1] = Y[:2 * n + 1]
        Y = Y[2 * n + 1:]
        return self._package(x0=x_init,
                             X=X, Y=Y, h=h, wall=wall, backend=backend, N=N,
                             impact_vel_tol=impact_vel_tol)

    def _package(self, x0, X, Y, h, wall, backend, N, impact_vel_tol):
        n, mu = self.model.n, self.cs.m_u
        if not np.all(np.isfinite(X)):
            k = int(np.argmax(~np.all(np.isfinite(X), axis=0)))
            raise SimulationFailed(f"Moreau-Jean: non-finite state at step {k} (t = {x0[2 * n] + k * h:.6g}); "
                                   "reduce h or check the model/gains", diagnostics={"step": k})
        Xall = np.hstack([x0.reshape(-1, 1), X])
        Z = np.asarray(self._post.map(Xall.shape[1], "serial")(Xall))
        o = 0
        P = Y[o:o + mu].T; o += mu
        act = Y[o:o + mu].T > 0.5
        o = 0
        gaps = Z[o:o + mu].T; o += mu
        Un = Z[o:o + mu].T; o += mu
        E = Z[o]; V = Z[o + 1]; o += 2
        u = Z[o:o + self.model.m].T
        t = Xall[2 * n]
        vtol = impact_vel_tol if impact_vel_tol is not None else 1e-8
        stats = {"wall_s": wall, "steps": N, "steps_per_s": N / wall if wall > 0 else float("inf"),
                 "backend": backend, "Un": Un, "u": u, "theta_m": float(x0[-2]), "activation_tol": float(x0[-1]),
                 "projection": int(self.projection)}
        names = {"q": list(self.model.q_names), "gaps": list(self.cs.names), "u": list(self.model.u_names)}
        return ContactTrajectory(t, Xall[:n].T, Xall[n:2 * n].T, P, act, gaps, E, V, h, names, stats, vtol)
