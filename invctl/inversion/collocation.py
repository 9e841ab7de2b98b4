"""Direct collocation of ``X' = F(X, Y(t), theta)`` on a mesh of ``[T0, Tf]``.

Schemes (a scheme is a coefficient table):

``hermite-simpson``  compressed Hermite-Simpson (Lobatto IIIA, order 4): states at
                     the mesh points, cubic Hermite interpolant collocated at the midpoint;
``legendre<d>``      Gauss-Legendre collocation with ``d`` points (order 2d);
``radau<d>``         Radau IIA collocation with ``d`` points (order 2d - 1).

The transcription is built once per (servo model, selection, scheme, N): the
step sizes, the reference samples ``Y = (y, y', y'', y''')`` at every
collocation time, the model parameters and both equilibria are NLP
*parameters*, so other meshes with the same N, other references, parameters or
horizons reuse the same graph.  The graph is an unexpanded MX graph over two
``map``-ped SX functions (the right-hand side at all nodes and one interval),
so its size does not grow with N.
"""
from __future__ import annotations

import re
import time
from dataclasses import dataclass

import casadi as ca
import numpy as np
import scipy.sparse as sp

from .servo import NUMERIC_SOLVES_NX

SCHEME_RE = re.compile(r"^(hermite-simpson|hs|legendre(\d+)|radau(\d+))$")



@dataclass(frozen=True)
class Scheme:
    """A collocation scheme: points ``tau`` in (0, 1], derivative matrix ``C``,
    continuity weights ``D`` and quadrature weights ``B`` (empty for Hermite-Simpson)."""

    name: str
    degree: int
    tau: np.ndarray
    C: np.ndarray
    D: np.ndarray
    B: np.ndarray
    order: int

    @property
    def is_hs(self) -> bool:
        return self.name == "hermite-simpson"


def get_scheme(name: str) -> Scheme:
    """Parse ``hermite-simpson``, ``legendre<d>`` or ``radau<d>`` (d = 1..9)."""
    key = str(name).strip().lower()
    mt = SCHEME_RE.match(key)
    if not mt:
        raise ValueError(f"unknown collocation scheme {name!r}; use 'hermite-simpson', 'legendre<d>' or "
                         "'radau<d>' (e.g. legendre3, radau3)")
    if key in ("hermite-simpson", "hs"):
        return Scheme("hermite-simpson", 3, np.array([0.5, 1.0]), np.zeros((0, 0)), np.zeros(0), np.zeros(0), 4)
    kind = "legendre" if key.startswith("legendre") else "radau"
    d = int(mt.group(2) or mt.group(3))
    if not 1 <= d <= 9:
        raise ValueError(f"collocation degree must be 1..9, got {d}")
    tau = np.array(ca.collocation_points(d, kind))
    allt = np.concatenate([[0.0], tau])
    C = np.zeros((d + 1, d))
    D = np.zeros(d + 1)
    B = np.zeros(d + 1)
    for j in range(d + 1):
        coeff = np.poly1d([1.0])
        for r in range(d + 1):
            if r != j:
                coeff *= np.poly1d([1.0, -allt[r]]) / (allt[j] - allt[r])
        D[j] = coeff(1.0)
        dcoeff = np.polyder(coeff)
        C[j, :] = dcoeff(tau)
        B[j] = np.polyint(coeff)(1.0)
    return Scheme(f"{kind}{d}", d, tau, C, D, B, 2 * d if kind == "legendre" else 2 * d - 1)


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
        self._c = lambda f: f  # noqa: E731
        self.compiled = False
        self._compile_request = compiled if not objective else False
        self.servo, self.selection, self.scheme, self.N = servo, selection, scheme, int(N)
        L = servo.layout
        nx, m4 = L.nx, 4 * L.m
        ntheta = servo.model.theta.shape[0]
        self.nx, self.m4, self.ntheta = nx, m4, ntheta
        N = self.N
        rhs = servo.rhs
        th = ca.SX.sym("theta", ntheta)
        hs = ca.SX.sym("h")
        ub = L.blocks["u"]
        if scheme.is_hs:
            Xa, Xb, Fa, Fb, Ym = (ca.SX.sym(s, nx) if s != "Ym" else ca.SX.sym(s, m4)
                                  for s in ("Xa", "Xb", "Fa", "Fb", "Ym"))
            Xm = 0.5 * (Xa + Xb) + hs / 8 * (Fa - Fb)
            Fm = rhs(Xm, Ym, th)
            defect = Xb - Xa - hs / 6 * (Fa + 4 * Fm + Fb)
            energy = hs / 6 * (ca.sumsqr(Xa[ub]) + 4 * ca.sumsqr(Xm[ub]) + ca.sumsqr(Xb[ub]))
            interval = ca.Function("hs_interval", [Xa, Xb, Fa, Fb, hs, Ym, th], [defect, energy],
                                   ["Xa", "Xb", "Fa", "Fb", "h", "Ym", "theta"], ["defect", "energy"])
            self.n_col, self.nY = 0, 2 * N + 1
        else:
            d = scheme.degree
            Xk, Xk1 = ca.SX.sym("Xk", nx), ca.SX.sym("Xk1", nx)
            Xc, Yc = ca.SX.sym("Xc", nx, d), ca.SX.sym("Yc", m4, d)
            Xall = ca.horzcat(Xk, Xc)
            Fc = ca.horzcat(*[rhs(Xc[:, r], Yc[:, r], th) for r in range(d)])
            res = ca.mtimes(Xall, ca.DM(scheme.C)) - hs * Fc
            cont = Xk1 - ca.mtimes(Xall, ca.DM(scheme.D))
            energy = hs * sum(scheme.B[r + 1] * ca.sumsqr(Xc[ub, r]) for r in range(d))
            interval = ca.Function("coll_interval", [Xk, Xc, Xk1, hs, Yc, th],
                                   [ca.vertcat(ca.vec(res), cont), energy],
                                   ["Xk", "Xc", "Xk1", "h", "Yc", "theta"], ["defect", "energy"])
            self.n_col, self.nY = d * N, d * N
        if self._compile_request == "auto" and nx > NUMERIC_SOLVES_NX:
            self._compile_request = False  # large models: numeric solves, nothing to look up in the cache
        self.compiled_pieces: tuple = ()
        self._pending: tuple = ()
        if self._compile_request:
            from .compiled import compile_cached, compile_in_background, is_cached

            wanted = [rhs, interval, servo.rhs_jac, self._block_function()]
            if self._compile_request is True:
                have = {f.name() for f in wanted}
            else:  # "auto": what the disk cache has now; the rest compiles in the background
                have = {f.name() for f in wanted if is_cached(f, key=cache_key)}
                missing = [f for f in wanted if f.name() not in have]
                if missing:
                    self._pending = tuple((f, cache_key) for f in missing)
                    compile_in_background(missing, key=cache_key)
            self._c = lambda f: compile_cached(f, key=cache_key) if f.name() in have else f  # noqa: E731
            self.compiled = len(have) == len(wanted)
            self.compiled_pieces = tuple(f.name() for f in wanted if f.name() in have)
        self.interval = interval = self._c(interval)
        rhs = self._c(rhs)
        self.nX = nx * (N + 1) + nx * self.n_col
        self.np = N + m4 * self.nY + ntheta + 2 * nx
        x = ca.MX.sym("x", self.nX)
        p = ca.MX.sym("p", self.np)
        Xmesh = ca.reshape(x[:nx * (N + 1)], nx, N + 1)
        h, Y, theta, E0, Ef = self._split_p(p)
        if scheme.is_hs:
            Fn = rhs.map(N + 1)(Xmesh, Y[:, :N + 1], theta)
            defect, energy = interval.map(N)(Xmesh[:, :N], Xmesh[:, 1:], Fn[:, :N], Fn[:, 1:], h, Y[:, N + 1:], theta)
        else:
            Xcol = ca.reshape(x[nx * (N + 1):], nx, self.n_col)
            defect, energy = interval.map(N)(Xmesh[:, :N], Xcol, Xmesh[:, 1:], h, Y, theta)
        s0, sf = list(selection.start), list(selection.end)
        bc = ca.vertcat(Xmesh[s0, 0] - E0[s0], Xmesh[sf, N] - Ef[sf])
        self.g = ca.vertcat(ca.vec(defect), bc)
        self.ng = self.g.shape[0]
        self.square = self.ng == self.nX
        self.objective = float(objective)
        self.f = self.objective * ca.sum2(energy) if self.objective else ca.MX(0)
        self._x, self._p = x, p
        self._solvers: dict = {}
        self._newton = None
        self.build_s = time.perf_counter() - t_build

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
        h = np.diff(t_mesh)
        if self.scheme.is_hs:
            return np.concatenate([t_mesh, t_mesh[:-1] + 0.5 * h])
        return (t_mesh[:-1, None] + h[:, None] * self.scheme.tau[None, :]).ravel()

    def collocation_times(self, t_mesh: np.ndarray) -> np.ndarray:
        """Times of the collocation states ``X_col`` (empty for Hermite-Simpson)."""
        if self.scheme.is_hs:
            return np.zeros(0)
        h = np.diff(t_mesh)
        return (t_mesh[:-1, None] + h[:, None] * self.scheme.tau[None, :]).ravel()

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
    def _block_function(self) -> ca.Function:
        """SX function of the Jacobian blocks of one interval (HS) or one collocation point."""
        if getattr(self, "_blk", None) is None:
            nx, m4 = self.nx, self.m4
            I = ca.DM.eye(nx)  # noqa: E741
            if self.scheme.is_hs:
                Xa, Xb, Fa, Fb = (ca.SX.sym(s, nx) for s in ("Xa", "Xb", "Fa", "Fb"))
                Ja, Jb = ca.SX.sym("Ja", nx, nx), ca.SX.sym("Jb", nx, nx)
                hs, Ym, th = ca.SX.sym("h"), ca.SX.sym("Ym", m4), ca.SX.sym("th", self.ntheta)
                Xm = 0.5 * (Xa + Xb) + hs / 8 * (Fa - Fb)
                _Fm, Jm = self.servo.rhs_jac(Xm, Ym, th)
                Da = -I - hs / 6 * (Ja + 4 * ca.mtimes(Jm, 0.5 * I + hs / 8 * Ja))
                Db = I - hs / 6 * (Jb + 4 * ca.mtimes(Jm, 0.5 * I - hs / 8 * Jb))
                self._blk = ca.Function("hs_blocks", [Xa, Xb, Fa, Fb, Ja, Jb, hs, Ym, th], [Da.T, Db.T])
            else:
                Js, hs, cs = ca.SX.sym("J", nx, nx), ca.SX.sym("h"), ca.SX.sym("c")
                self._blk = ca.Function("coll_block", [Js, hs, cs], [(cs * I - hs * Js).T])
        return self._blk

    def _product_function(self) -> ca.Function:
        """MX ``(Ja, Jb, Jm, h) -> (Da^T, Db^T)``: the Hermite-Simpson blocks from the right-hand side
        Jacobians at both ends and the midpoint (the same formulas as :meth:`_block_function`)."""
        if getattr(self, "_prod", None) is None:
            nx = self.nx
            I = ca.DM.eye(nx)  # noqa: E741
            Ja, Jb, Jm, hs = ca.MX.sym("Ja", nx, nx), ca.MX.sym("Jb", nx, nx), ca.MX.sym("Jm", nx, nx), ca.MX.sym("h")
            Da = -I - hs / 6 * (Ja + 4 * ca.mtimes(Jm, 0.5 * I + hs / 8 * Ja))
            Db = I - hs / 6 * (Jb + 4 * ca.mtimes(Jm, 0.5 * I - hs / 8 * Jb))
            self._prod = ca.Function("hs_block_products", [Ja, Jb, Jm, hs], [Da.T, Db.T])
        return self._prod

    def _jacobian_mx(self, x, p):
        """The Jacobian of ``g`` as a sparse MX built from mapped per-node/per-interval
        SX functions (the same blocks as :meth:`residual_and_jacobian`)."""
        indices, indptr = self._pattern()[:2]
        spars = ca.Sparsity(self.ng, self.nX, np.asarray(indptr, np.int64).tolist(),
                            np.asarray(indices, np.int64).tolist())
        return ca.MX(spars, self._jacobian_nz(x, p))

    def _jacobian_nz(self, x, p):
        """The nonzeros of the Jacobian of ``g`` in CSC order of :meth:`_pattern` (MX column)."""
        nx, N = self.nx, self.N
        indices, indptr, perm, s0, sf = self._pattern()
        Xmesh = ca.reshape(x[:nx * (N + 1)], nx, N + 1)
        h, Y, theta, _E0, _Ef = self._split_p(p)
        rj_sx = self.servo.rhs_jac
        rj = self._c(rj_sx)
        vals = []
        if self.scheme.is_hs and not self.compiled and nx > NUMERIC_SOLVES_NX:
            # large blocks: the right-hand side Jacobian with numeric solves by M (ServoModel.rhs_jac_numeric),
            # at the midpoints by the mapped function, and the two nx^3 products of every interval as MX
            # matrix products (compiled C loops), not as nx^3 SX instructions per interval
            rjn = self.servo.rhs_jac_numeric
            F, JF = rjn.map(N + 1)(Xmesh, Y[:, :N + 1], theta)
            Fa, Fb = F[:, :N], F[:, 1:]
            Xm = 0.5 * (Xmesh[:, :N] + Xmesh[:, 1:]) + ca.repmat(h / 8, nx, 1) * (Fa - Fb)
            _Fm, JFm = rjn.map(N)(Xm, Y[:, N + 1:], theta)
            DaT, DbT = self._product_function().map(N)(JF[:, :nx * N], JF[:, nx:], JFm, h)
            vals = [ca.vec(DaT), ca.vec(DbT)]
        elif self.scheme.is_hs:
            blk = self._c(self._block_function())
            F, JF = rj.map(N + 1)(Xmesh, Y[:, :N + 1], theta)
            DaT, DbT = blk.map(N)(Xmesh[:, :N], Xmesh[:, 1:], F[:, :N], F[:, 1:], JF[:, :nx * N], JF[:, nx:],
                                  h, Y[:, N + 1:], theta)
            vals = [ca.vec(DaT), ca.vec(DbT)]
        else:
            d = self.scheme.degree
            C, D = self.scheme.C, self.scheme.D
            Xcol = ca.reshape(x[nx * (N + 1):], nx, self.n_col)
            _F, JF = rj.map(d * N)(Xcol, Y, theta)
            blk = self._c(self._block_function())
            hrep = ca.repmat(h, d, 1)
            hrep = ca.reshape(hrep, 1, d * N)
            crep = ca.DM(np.tile([C[i + 1, i] for i in range(d)], N)).T
            Bt = blk.map(d * N)(JF, hrep, crep)
            for i in range(d + 1):
                for j in range(d + 2):
                    if j == d + 1 and i < d:
                        continue
                    if i < d and j - 1 == i:
                        cols = [c for k in range(N) for c in range((k * d + i) * nx, (k * d + i + 1) * nx)]
                        vals.append(ca.vec(Bt[:, cols]))
                        continue
                    if i < d:
                        M = C[0, i] * np.eye(nx) if j == 0 else C[j, i] * np.eye(nx)
                    else:
                        M = np.eye(nx) if j == d + 1 else -D[j] * np.eye(nx)
                    vals.append(ca.DM(np.tile(M.ravel(), N)))
        vals.append(ca.DM.ones(s0.size + sf.size))
        return ca.vertcat(*vals)[np.asarray(perm, np.int64).tolist()]

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
        r = np.arange(nx)
        rows, cols = [], []
        if self.scheme.is_hs:
            k = np.arange(N)
            for off in (0, 1):  # d defect_k / d X_{k+off}
                rows.append((k[:, None, None] * nx + r[None, :, None]).repeat(nx, 2))
                cols.append(((k + off)[:, None, None] * nx + r[None, None, :]).repeat(nx, 1))
            nrow_int = N * nx
        else:
            d = self.scheme.degree
            k = np.arange(N)
            base = k * nx * (d + 1)
            col0 = nx * (N + 1)
            for i in range(d + 1):  # row block i (d = continuity)
                rb = base[:, None, None] + i * nx + r[None, :, None]
                for j in range(d + 2):  # column block: 0 = X_k, 1..d = X_c, d+1 = X_{k+1}
                    if j == d + 1 and i < d:
                        continue
                    if j == 0:
                        cb = k[:, None, None] * nx + r[None, None, :]
                    elif j <= d:
                        cb = col0 + (k * d + j - 1)[:, None, None] * nx + r[None, None, :]
                    else:
                        cb = (k + 1)[:, None, None] * nx + r[None, None, :]
                    rows.append(rb.repeat(nx, 2))
                    cols.append(cb.repeat(nx, 1))
            nrow_int = N * nx * (d + 1)
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
        ``None`` (default): buffered for Hermite-Simpson or compiled functions; otherwise the
        numpy assembly, as fast in CasADi's VM for Legendre/Radau and without the memory of a
        second expression graph per cached transcription.
        """
        if buffered is None:
            buffered = self.compiled or self.scheme.is_hs
        if not buffered:
            return self.residual, self.residual_and_jacobian
        if getattr(self, "_evals", None) is None:
            import threading

            indices, indptr = self._pattern()[:2]
            x, p = self._x, self._p
            fg = ca.Function("servo_g_only", [x, p], [self.g])
            fgj = ca.Function("servo_g_jac", [x, p], [self.g, self._jacobian_nz(x, p)])
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
                    return g2.copy(), sp.csc_matrix((jnz.copy(), indices, indptr), shape=shape)

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
        I = np.eye(nx)  # noqa: E741
        if not jacobian:
            rm = self._rhs_map
            if self.scheme.is_hs:
                F = np.array(rm(N + 1)(Xmesh, Y[:, :N + 1], theta))
                Xm = 0.5 * (Xmesh[:, :-1] + Xmesh[:, 1:]) + h / 8 * (F[:, :-1] - F[:, 1:])
                Fm = np.array(rm(N)(Xm, Y[:, N + 1:], theta))
                g_int = (Xmesh[:, 1:] - Xmesh[:, :-1] - h / 6 * (F[:, :-1] + 4 * Fm + F[:, 1:])).ravel(order="F")
            else:
                d = self.scheme.degree
                F = np.array(rm(d * N)(Xcol, Y, theta)).reshape(nx, N, d)
                Xall = np.concatenate([Xmesh[:, :-1, None], Xcol.reshape(nx, N, d)], axis=2)
                res = np.einsum("rkj,ji->rki", Xall, self.scheme.C) - h[None, :, None] * F
                cont = Xmesh[:, 1:] - np.einsum("rkj,j->rk", Xall, self.scheme.D)
                g_int = np.concatenate([res.transpose(0, 2, 1).reshape(nx * d, N, order="F"), cont],
                                       axis=0).ravel(order="F")
            return np.concatenate([g_int, Xmesh[s0, 0] - E0[s0], Xmesh[sf, N] - Ef[sf]]), None
        if self.scheme.is_hs:
            F, JF = self._rhs_jac_map(N + 1)(Xmesh, Y[:, :N + 1], theta)
            F = np.array(F)
            JF = np.array(JF).reshape(nx, N + 1, nx).transpose(1, 0, 2)
            Fa, Fb, JFa, JFb = F[:, :-1], F[:, 1:], JF[:-1], JF[1:]
            Xm = 0.5 * (Xmesh[:, :-1] + Xmesh[:, 1:]) + h / 8 * (Fa - Fb)
            Fm, JFm = self._rhs_jac_map(N)(Xm, Y[:, N + 1:], theta)
            Fm = np.array(Fm)
            JFm = np.array(JFm).reshape(nx, N, nx).transpose(1, 0, 2)
            defect = Xmesh[:, 1:] - Xmesh[:, :-1] - h / 6 * (Fa + 4 * Fm + Fb)
            hh = h[:, None, None]
            dXa = 0.5 * I + hh / 8 * JFa
            dXb = 0.5 * I - hh / 8 * JFb
            Da = -I - hh / 6 * (JFa + 4 * np.einsum("kij,kjl->kil", JFm, dXa))
            Db = I - hh / 6 * (JFb + 4 * np.einsum("kij,kjl->kil", JFm, dXb))
            vals = [Da.ravel(), Db.ravel()]
            g_int = defect.ravel(order="F")
        else:
            d = self.scheme.degree
            C, D = self.scheme.C, self.scheme.D
            F, JF = self._rhs_jac_map(d * N)(Xcol, Y, theta)
            F = np.array(F).reshape(nx, N, d)
            JF = np.array(JF).reshape(nx, N, d, nx).transpose(1, 2, 0, 3)  # k, i, row, col
            Xc = Xcol.reshape(nx, N, d)
            Xall = np.concatenate([Xmesh[:, :-1, None], Xc], axis=2)  # nx, N, d+1
            res = np.einsum("rkj,ji->rki", Xall, C) - h[None, :, None] * F
            cont = Xmesh[:, 1:] - np.einsum("rkj,j->rk", Xall, D)
            g_int = np.concatenate([res.transpose(0, 2, 1).reshape(nx * d, N, order="F"), cont], axis=0)
            g_int = g_int.ravel(order="F")
            vals = []
            hh = h[:, None, None]
            for i in range(d + 1):
                for j in range(d + 2):
                    if j == d + 1 and i < d:
                        continue
                    if i < d:
                        if j == 0:
                            blk = np.broadcast_to(C[0, i] * I, (N, nx, nx))
                        else:
                            blk = C[j, i] * I - (hh * JF[:, i] if j - 1 == i else 0.0)
                            blk = np.broadcast_to(blk, (N, nx, nx))
                    else:
                        blk = np.broadcast_to(I if j == d + 1 else -D[j] * I, (N, nx, nx))
                    vals.append(np.ascontiguousarray(blk).ravel())
        g = np.concatenate([g_int, Xmesh[s0, 0] - E0[s0], Xmesh[sf, N] - Ef[sf]])
        data = np.concatenate(vals + [np.ones(s0.size + sf.size)])[perm]
        J = sp.csc_matrix((data, indices, indptr), shape=(self.ng, self.nX))
        return g, J

    def _rhs_map(self, k: int) -> ca.Function:
        cache = self.__dict__.setdefault("_rm", {})
        if k not in cache:
            cache[k] = self._c(self.servo.rhs).map(k)
        return cache[k]

    def _rhs_jac_map(self, k: int) -> ca.Function:
        cache = self.__dict__.setdefault("_rjm", {})
        if k not in cache:
            cache[k] = self._c(self.servo.rhs_jac).map(k)
        return cache[k]

    def newton_functions(self):
        """``(x, p) -> g`` and ``(x, p) -> dg/dx`` (sparse), for the Newton backend."""
        if self._newton is None:
            if not self.square:
                raise ValueError("the Newton backend needs a square system (as many conditions as unknowns)")
            gfun = ca.Function("servo_g", [self._x, self._p], [self.g])
            jfun = ca.Function("servo_jac", [self._x, self._p], [ca.jacobian(self.g, self._x)])
            self._newton = (gfun, jfun)
        return self._newton
