"""Direct collocation of ``X' = F(X, Y(t), theta)`` on a mesh of ``[T0, Tf]``: the square
boundary value problem of the exact inverse (:class:`Transcription`; the scheme's equations come from
its :class:`~invctl.inversion.schemes.Scheme`).

The transcription is built once per (servo model, selection, scheme, N): the
step sizes, the reference samples ``Y = (y, y', y'', y''')`` at every
collocation time, the model parameters and both equilibria are NLP
*parameters*, so other meshes with the same N, other references, parameters or
horizons reuse the same graph.  The graph is an unexpanded MX graph over two
``map``-ped SX functions (the right-hand side at all nodes and one interval),
so its size does not grow with N.
"""
from __future__ import annotations

import time
from functools import cached_property

import casadi as ca
import numpy as np
import scipy.sparse as sp

from .schemes import Scheme
from .servo import NUMERIC_SOLVES_NX, Buffered, dense_map


#: transcriptions whose missing pieces wait for :func:`start_deferred_compiles`
DEFERRED: list = []


def start_deferred_compiles() -> None:
    """Start the background compiles deferred by transcriptions built since the last call: a forked
    compile worker competes with the first solve for the CPU and its fork costs the caller ~20 ms, so
    it starts when that solve has returned."""
    while DEFERRED:
        DEFERRED.pop().start_background_compile()


class Transcription:
    """The NLP of one (servo model, selection, scheme, N); see module doc.

    Decision vector ``x = [vec(X_mesh) (nx x N+1); vec(X_col) (nx x dN)]``;
    constraints ``[defects; boundary conditions]``; parameters
    ``[h (N); vec(Y at the scheme's sample times); theta; E0 (nx); Ef (nx)]``.
    """

    def __init__(self, servo, selection, scheme: Scheme, N: int, *, objective: float = 0.0,
                 compiled: bool = False, cache_key: str | None = None):
        t_build = time.perf_counter()
        if compiled is True and objective:
            raise ValueError("compiled evaluation has no derivatives: use it for square systems (no objective)")
        self.compiled = False
        self._compile_request = compiled if not objective else False
        self.servo, self.selection, self.scheme, self.N = servo, selection, scheme, int(N)
        L = servo.layout
        nx, m4 = L.nx, 4 * L.m
        ntheta = servo.model.theta.shape[0]
        self.nx, self.m4, self.ntheta = nx, m4, ntheta
        N = self.N
        self.n_col, self.nY = scheme.n_col(N), scheme.n_samples(N)
        if self._compile_request == "auto" and nx > NUMERIC_SOLVES_NX:
            self._compile_request = False  # large models: numeric solves, nothing to look up in the cache
        self.compiled_pieces: tuple = ()
        self._pending: tuple = ()
        self._compile_started = False
        self._have: set = set()
        self._pieces: dict = {}
        self._key = cache_key
        if self._compile_request:
            # the pieces by name: one found in the disk cache is loaded without building its SX function
            makers = {"servo_rhs": lambda: servo.rhs, scheme.interval_name: lambda: self.interval_sx,
                      "servo_rhs_jac": lambda: servo.rhs_jac, scheme.block_name: self.block_function,
                      "servo_residuals": lambda: servo.residuals, "servo_Az": lambda: servo.decoupling,
                      "servo_constraint_jac": lambda: servo.constraint_jacobian}
            for name in makers:
                found = servo.disk_piece(name, cache_key) if cache_key is not None else None
                if found is not None:
                    self._pieces[name] = found
            if self._compile_request is True:
                have = set(makers)
            else:  # "auto": what the disk cache has now; the rest compiles in the background
                have = set(self._pieces)
                missing = [make() for name, make in makers.items() if name not in have]
                if missing:  # compiled in the background once the first solve has returned
                    self._pending = tuple((f, cache_key) for f in missing)
                    DEFERRED.append(self)
            self._have = have
            self._makers = makers
            self.compiled = len(have) == len(makers)
            # the plan's and the dichotomy check's linearizations, the quasi-static path's checks too
            servo.use_compiled(*(self.piece(nm) if nm in have else None
                                 for nm in ("servo_rhs_jac", "servo_residuals", "servo_Az", "servo_constraint_jac")))
            self.compiled_pieces = tuple(name for name in makers if name in have)
        # compiled pieces found on disk are loaded by name: no SX function of the model is built for them
        self.interval = interval = self.piece(scheme.interval_name, lambda: self.interval_sx)
        rhs = self.piece("servo_rhs", lambda: servo.rhs)
        self.nX = nx * (N + 1) + nx * self.n_col
        self.np = N + m4 * self.nY + ntheta + 2 * nx
        x = ca.MX.sym("x", self.nX)
        p = ca.MX.sym("p", self.np)
        Xmesh = ca.reshape(x[:nx * (N + 1)], nx, N + 1)
        h, Y, theta, E0, Ef = self._split_p(p)
        defect, energy = scheme.bvp_defects(self, interval, rhs, x, Xmesh, h, Y, theta)
        s0, sf = list(selection.start), list(selection.end)
        bc = ca.vertcat(Xmesh[s0, 0] - E0[s0], Xmesh[sf, N] - Ef[sf])
        self.g = ca.vertcat(ca.vec(defect), bc)
        self.ng = self.g.shape[0]
        self.square = self.ng == self.nX
        self.objective = float(objective)
        self.f = self.objective * ca.sum2(energy) if self.objective else ca.MX(0)
        self._x, self._p = x, p
        self._solvers: dict = {}
        self.build_s = time.perf_counter() - t_build

    @cached_property
    def interval_sx(self) -> ca.Function:
        """One interval's defect and energy, the SX form (the parameter derivatives of sensitivity.py)."""
        return self.scheme.bvp_interval(self, self.servo.rhs, self.servo.layout.blocks["u"])

    def piece(self, name: str, make=None) -> ca.Function:
        """The piece called ``name`` (``servo_rhs``, ``servo_rhs_jac``, ``servo_residuals``, the interval or the
        block function): compiled when this transcription evaluates it in C (loaded once), else the SX function
        ``make()`` (built only then)."""
        hit = self._pieces.get(name)
        if hit is not None:
            return hit
        make = make or self.__dict__.get("_makers", {})[name]
        if name in self._have:
            from .compiled import compile_cached

            hit = self._pieces[name] = compile_cached(make(), key=self._key)
            return hit
        return make()

    def start_background_compile(self) -> None:
        """Start compiling the pieces missing from the disk cache in the background (once)."""
        if self._pending and not self._compile_started:
            from .compiled import compile_in_background

            self._compile_started = True
            compile_in_background([f for f, _ in self._pending], key=self._pending[0][1])

    def upgradable(self) -> bool:
        """Whether pieces compiled in the background since this transcription was built are now in
        the disk cache (a new transcription of the same problem would evaluate them in C)."""
        if not self._pending:
            return False
        from .compiled import is_cached

        return any(is_cached(f, key=key) for f, key in self._pending)

    # ------------------------------------------------------------ layout
    def _split_p(self, p):
        """``(h (1 x N), Y (4m x nY), theta, E0, Ef)`` from the symbolic parameter vector ``p``."""
        N, nx, m4 = self.N, self.nx, self.m4
        o = N + m4 * self.nY
        return (p[:N].T, ca.reshape(p[N:o], m4, self.nY), p[o:o + self.ntheta],
                p[o + self.ntheta:o + self.ntheta + nx], p[o + self.ntheta + nx:o + self.ntheta + 2 * nx])

    def sample_times(self, t_mesh: np.ndarray) -> np.ndarray:
        """Times at which the reference is sampled (order of ``Y`` in ``p``)."""
        return self.scheme.sample_times(t_mesh)

    def collocation_times(self, t_mesh: np.ndarray) -> np.ndarray:
        """Times of the collocation states ``X_col``."""
        return self.scheme.collocation_times(t_mesh)

    def parameters(self, t_mesh, Ysamples, theta, E0, Ef) -> np.ndarray:
        return np.concatenate([np.diff(t_mesh), np.asarray(Ysamples, float).ravel(order="F"),
                               np.asarray(theta, float), np.asarray(E0, float), np.asarray(Ef, float)])

    def pack(self, Xmesh, Xcol=None) -> np.ndarray:
        parts = [np.asarray(Xmesh, float).ravel(order="F")]
        if self.n_col:
            parts.append(np.asarray(Xcol, float).ravel(order="F"))
        return np.concatenate(parts)

    def unpack(self, x):
        x = np.asarray(x, float).ravel()
        nx, N = self.nx, self.N
        Xmesh = x[:nx * (N + 1)].reshape(nx, N + 1, order="F")
        Xcol = x[nx * (N + 1):].reshape(nx, self.n_col, order="F") if self.n_col else np.zeros((nx, 0))
        return Xmesh, Xcol

    # ------------------------------------------------------------ solvers
    def block_function(self) -> ca.Function:
        """SX function of the Jacobian blocks of one interval or collocation point (the scheme's)."""
        if getattr(self, "_blk", None) is None:
            self._blk = self.scheme.bvp_blocks(self)
        return self._blk

    def _jacobian_mx(self, x, p):
        """The Jacobian of ``g`` as a sparse MX built from mapped per-node/per-interval
        SX functions (the same blocks as :meth:`residual_and_jacobian`)."""
        indices, indptr = self._pattern()[:2]
        spars = ca.Sparsity(self.ng, self.nX, np.asarray(indptr, np.int64).tolist(),
                            np.asarray(indices, np.int64).tolist())
        return ca.MX(spars, self._jacobian_nz(x, p))

    def _jacobian_nz(self, x, p, csc: bool = True):
        """The nonzeros of the Jacobian of ``g`` in CSC order of :meth:`_pattern` (MX column; ``csc=False``:
        in block order, ``[perm]`` puts them in CSC order)."""
        nx, N = self.nx, self.N
        indices, indptr, perm, s0, sf = self._pattern()
        Xmesh = ca.reshape(x[:nx * (N + 1)], nx, N + 1)
        h, Y, theta, _E0, _Ef = self._split_p(p)
        vals = self.scheme.bvp_jacobian_values(self, x, Xmesh, h, Y, theta,
                                               self.piece("servo_rhs_jac", lambda: self.servo.rhs_jac))
        vals.append(ca.DM.ones(s0.size + sf.size))
        return ca.vertcat(*vals)[np.asarray(perm, np.int64).tolist()] if csc else ca.vertcat(*vals)

    def _jacobian_function(self) -> ca.Function:
        """``(x, p) -> dg/dx`` (the assembled sparse Jacobian), built once."""
        if getattr(self, "_jfun", None) is None:
            x, p = ca.MX.sym("x", self.nX), ca.MX.sym("p", self.np)
            self._jfun = ca.Function("servo_jac_g_x", [x, p], [self._jacobian_mx(x, p)], ["x", "p"], ["jac_g_x"])
        return self._jfun

    def _g_function(self) -> ca.Function:
        """``(x, p) -> g`` with the assembled Jacobian as its custom Jacobian, so that
        IPOPT does not differentiate the mapped graph by AD.  The parameter Jacobian
        of the custom function is not needed by any solver and is declared empty."""
        if getattr(self, "_gfun", None) is None:
            x, p = ca.MX.sym("x", self.nX), ca.MX.sym("p", self.np)
            gexpr = ca.substitute([self.g], [self._x, self._p], [x, p])[0]
            og = ca.MX.sym("out_g", self.ng)
            jac = ca.Function("jac_servo_g", [x, p, og], [self._jacobian_function()(x, p), ca.MX(self.ng, self.np)],
                              ["x", "p", "out_g"], ["jac_g_x", "jac_g_p"])
            self._gfun = ca.Function("servo_g", [x, p], [gexpr], ["x", "p"], ["g"],
                                     {"custom_jacobian": jac, "jac_penalty": 0})
        return self._gfun

    def ipopt(self, options: dict, *, assembled_jacobian: bool = True, zero_hessian: bool = False) -> ca.Function:
        """The IPOPT solver for these options (built once per option set).

        ``zero_hessian`` (square systems): hand IPOPT an exact, constant, structurally
        empty Hessian of the Lagrangian.  The primal step of a square system solves
        ``J dx = -g`` whatever the Hessian, and the KKT matrix ``[0 J^T; J 0]`` has the
        inertia IPOPT wants when ``J`` is nonsingular, so this is Newton's method with
        none of the limited-memory machinery (one sparse factorization per iteration).
        """
        key = repr((sorted((k, repr(v)) for k, v in options.items()), assembled_jacobian, zero_hessian))
        if key not in self._solvers:
            opts = dict(options)
            assembled = assembled_jacobian and self.square
            g = self._g_function()(self._x, self._p) if assembled else self.g
            if assembled and "jac_g" not in opts:
                # the assembled Jacobian once per call: derived from the custom Jacobian of g by AD,
                # CasADi would evaluate it once per 64 seed directions of the banded coloring
                # (3 times for nx = 65)
                opts["jac_g"] = ca.Function("servo_jac_g", [self._x, self._p],
                                            [self.g, self._jacobian_function()(self._x, self._p)],
                                            ["x", "p"], ["g", "jac_g_x"])
            nlp = {"x": self._x, "p": self._p, "f": self.f, "g": g}
            if zero_hessian:
                lf, lg = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", self.ng)
                opts["hess_lag"] = ca.Function("zero_hess_lag", [self._x, self._p, lf, lg],
                                               [ca.MX(self.nX, self.nX)], ["x", "p", "lam_f", "lam_g"],
                                               ["triu_hess_gamma_x_x"])
                opts["ipopt.hessian_constant"] = "yes"
            self._solvers[key] = ca.nlpsol("servo_bvp", "ipopt", nlp, opts)
        return self._solvers[key]

    # ------------------------------------------------ assembled residual and Jacobian
    def _pattern(self):
        """Row/column indices of the dense blocks of the Jacobian, and the permutation
        that puts their values in CSC order (built once)."""
        if getattr(self, "_pat", None) is not None:
            return self._pat
        nx, N = self.nx, self.N
        rows, cols, nrow_int = self.scheme.bvp_pattern(self)
        s0, sf = np.array(self.selection.start, int), np.array(self.selection.end, int)
        bc_rows = nrow_int + np.arange(s0.size + sf.size)
        bc_cols = np.concatenate([s0, N * nx + sf])
        rows = np.concatenate([a.ravel() for a in rows] + [bc_rows])
        cols = np.concatenate([a.ravel() for a in cols] + [bc_cols])
        A = sp.csc_matrix((np.arange(1, rows.size + 1, dtype=float), (rows, cols)), shape=(self.ng, self.nX))
        A.sort_indices()  # CasADi needs sorted rows per column; scipy 1.13 leaves them in COO order
        if A.nnz != rows.size:
            raise AssertionError("collocation Jacobian pattern has duplicate entries")
        perm = A.data.astype(np.int64) - 1
        self._pat = (A.indices.copy(), A.indptr.copy(), perm, s0, sf)
        return self._pat

    def evaluators(self, buffered: bool | None = None):
        """Fast ``(x, p) -> g`` and ``(x, p) -> (g, dg/dx)`` for the Newton backend.

        ``buffered``: the same mapped (and, if compiled, C) functions as the IPOPT callbacks,
        called through CasADi's zero-copy buffers: ~0.15 ms for ``g`` and ~0.7 ms for ``g`` and
        the Jacobian at HS N = 100 compiled, against ~0.8 and ~3.5 ms for the numpy assembly of
        :meth:`residual` / :meth:`residual_and_jacobian` (which stays as the independent
        reference in tests).  The buffers are shared, so calls are serialized by a lock.
        ``None`` (default): buffered for compiled functions or as the scheme says (Hermite-Simpson); otherwise the
        numpy assembly, as fast in CasADi's VM for Legendre/Radau and without the memory of a
        second expression graph per cached transcription.
        """
        if buffered is None:
            buffered = self.compiled or self.scheme.buffered
        if not buffered:
            return self.residual, self.residual_and_jacobian
        if getattr(self, "_evals", None) is None:
            import threading

            indices, indptr, perm = self._pattern()[:3]
            x, p = self._x, self._p
            fg = ca.Function("servo_g_only", [x, p], [self.g])
            # the nonzeros in block order, put in CSC order by numpy (an MX index of every nonzero costs more
            # to build than the permutation costs in all the calls)
            fgj = ca.Function("servo_g_jac", [x, p], [self.g, self._jacobian_nz(x, p, csc=False)])
            xin, pin = np.zeros(self.nX), np.zeros(self.np)
            g1, g2, jnz = np.zeros(self.ng), np.zeros(self.ng), np.zeros(indices.size)
            lock = threading.Lock()
            keep = []

            def bind(f, outs):
                buf, run = f.buffer()
                buf.set_arg(0, memoryview(xin))
                buf.set_arg(1, memoryview(pin))
                for i, o in enumerate(outs):
                    buf.set_res(i, memoryview(o))
                keep.append(buf)
                return run

            run_g, run_gj = bind(fg, [g1]), bind(fgj, [g2, jnz])
            shape = (self.ng, self.nX)

            def residual(xv, pv):
                with lock:
                    np.copyto(xin, np.ravel(xv))
                    np.copyto(pin, np.ravel(pv))
                    run_g()
                    return g1.copy()

            def residual_and_jacobian(xv, pv):
                with lock:
                    np.copyto(xin, np.ravel(xv))
                    np.copyto(pin, np.ravel(pv))
                    run_gj()
                    return g2.copy(), sp.csc_matrix((jnz[perm], indices, indptr), shape=shape)

            self._evals = (residual, residual_and_jacobian, keep)
        return self._evals[:2]

    def banded_pattern(self):
        """The :class:`~invctl.inversion.banded.BandedPattern` of the Jacobian, unknowns in time
        order (``X_0, X_col(interval 0), X_1, ...``); built once."""
        if getattr(self, "_band", None) is None:
            from .banded import BandedPattern

            nx, N, nc = self.nx, self.N, self.n_col
            if nc:
                d = nc // N
                mesh = np.arange(nx * (N + 1)).reshape(N + 1, nx)
                col = nx * (N + 1) + np.arange(nx * nc).reshape(N, d * nx)
                order = np.concatenate([np.concatenate([mesh[k], col[k]]) for k in range(N)] + [mesh[N]])
            else:
                order = np.arange(self.nX)
            indices, indptr = self._pattern()[:2]
            self._band = BandedPattern(indices, indptr, self.nX, order)
        return self._band

    def residual(self, x, p) -> np.ndarray:
        """The constraint vector ``g`` alone (mapped right-hand side, numpy)."""
        return self.residual_and_jacobian(x, p, jacobian=False)[0]

    def residual_and_jacobian(self, x, p, jacobian: bool = True):
        """The constraint vector ``g`` and its sparse Jacobian (scipy CSC), assembled from
        the mapped right-hand side and its Jacobian at the nodes (numpy, no loops over nodes)."""
        nx, N = self.nx, self.N
        indices, indptr, perm, s0, sf = self._pattern()
        x = np.asarray(x, float).ravel()
        p = np.asarray(p, float).ravel()
        Xmesh, Xcol = self.unpack(x)
        o = 0
        h = p[o:o + N]
        o += N
        Y = p[o:o + self.m4 * self.nY].reshape(self.m4, self.nY, order="F")
        o += self.m4 * self.nY
        theta = p[o:o + self.ntheta]
        o += self.ntheta
        E0, Ef = p[o:o + nx], p[o + nx:o + 2 * nx]
        g_int, vals = self.scheme.bvp_residual(self, Xmesh, Xcol, h, Y, theta, jacobian)
        if not jacobian:
            return np.concatenate([g_int, Xmesh[s0, 0] - E0[s0], Xmesh[sf, N] - Ef[sf]]), None
        g = np.concatenate([g_int, Xmesh[s0, 0] - E0[s0], Xmesh[sf, N] - Ef[sf]])
        data = np.concatenate(vals + [np.ones(s0.size + sf.size)])[perm]
        J = sp.csc_matrix((data, indices, indptr), shape=(self.ng, self.nX))
        return g, J

    def _rhs_map(self, k: int) -> ca.Function:
        cache = self.__dict__.setdefault("_rm", {})
        if k not in cache:
            cache[k] = self.piece("servo_rhs", lambda: self.servo.rhs).map(k)
        return cache[k]

    def mapped_call(self, name: str, k: int) -> "Buffered":
        """``servo.<name>`` (``rhs``, ``rhs_jac`` or ``residuals``) at ``k`` points ``(X, Y, theta)``, compiled when the
        transcription is, called through buffers (:class:`Buffered`); built once per ``k``: the slopes
        of a solution and its checks at the mesh and between the nodes."""
        cache = self.__dict__.setdefault("_calls", {})
        if (name, k) not in cache:
            fn = self.piece(f"servo_{name}", lambda: getattr(self.servo, name))
            cache[name, k] = Buffered(dense_map(fn, k, (2,)))
        return cache[name, k]

    def _rhs_jac_map(self, k: int) -> ca.Function:
        cache = self.__dict__.setdefault("_rjm", {})
        if k not in cache:
            cache[k] = self.piece("servo_rhs_jac", lambda: self.servo.rhs_jac).map(k)
        return cache[k]
