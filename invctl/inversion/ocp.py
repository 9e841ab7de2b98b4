"""The servo-constraint transcription as an optimal control problem: bounds, a relaxed servo
constraint, a free transition time.

The unknowns and collocation equations are those of :class:`~invctl.inversion.collocation.Transcription`
(the index-reduced inverse model ``X' = F(X, Y, theta)`` of 003 (35), ``X = (q, v, lam, mu, u)``);
three things are added.

Relaxed servo constraint
    The servo rows of the (Baumgarte-stabilized) jerk-level constraint get a right-hand side
    ``c s(t)`` (``s``: one *slack* per output, at every point where ``F`` is evaluated), so with
    ``e = h(q) - y_ref``::

        e''' + 3 w e'' + 3 w^2 e' + w^3 e = c s,     c = w^3   (c = 1/(tf - t0)^3 for "jerk")

    and ``z' = (lam, mu, u)'`` follows from ``A_z z' = -(...) + (0, 0, c s)``.  With ``s = 0``
    this is (35) (exact tracking); with ``s`` free, ``u`` is a free input, ``lam`` and ``mu`` stay
    the multipliers of the holonomic and non-holonomic constraints, and ``s`` is (at low
    frequencies) the output error it buys.
Bounds
    On entries of ``q``, ``v``, ``u`` and on ``u'`` of the interpolating polynomial of every
    interval (the trajectory the :class:`~invctl.inversion.result.Inverse` returns), not only at
    the mesh (and collocation) points, with interior rows of one of two kinds (``interior``):

    * ``"hull"``: a polynomial lies between its Bernstein (Bezier) coefficients, so bounding them
      (linear in the unknowns) guarantees the bound everywhere, conservatively by O(h^2).
      Hermite-Simpson: the control points ``X_k + h F_k / 3`` and ``X_{k+1} - h F_{k+1} / 3`` of the
      cubic, and for ``u'`` the middle coefficient ``2 F_m - (F_k + F_{k+1}) / 2`` of its quadratic
      derivative (equal to ``3 (X_{k+1} - X_k) / h - F_k - F_{k+1}`` where the defects vanish) besides
      ``u'`` at the mesh.  Legendre/Radau: the interior Bernstein coefficients of ``X``.
    * ``"points"``: the polynomial at interior points whose positions (fractions of the interval)
      are NLP parameters, for a caller that moves them to the interior extrema
      (:meth:`OCPTranscription.extremum_points`) and solves again: exact, not conservative, where
      the solution cannot reshape itself around the points (exact tracking, minimum time).

    Legendre/Radau without ``interior``: mesh and collocation points only; their ``u'`` bounds
    (the ``u`` rows of ``F``) hold at the collocation points only.
Free transition time
    A decision ``tau = tf - t0``: the mesh intervals of ``[t0, tf]`` scale with ``tau / tau_ref``,
    the reference samples of derivative ``k`` with ``(tau_ref / tau)^k`` (the shape is fixed);
    pre- and post-actuation keep their lengths.

Objective (weights are NLP parameters, so one solver serves all weights and bound values)::

    sum_i W_i int e_i^2 dt + rho int |s|^2 dt + w_E int |u|^2 dt + w_R int |u'|^2 dt + w_T tau

with the scheme's own quadrature (Simpson for Hermite-Simpson, the Gauss/Radau weights of the
collocation points otherwise).  The *elastic* variant moves every bound into the constraints with
one nonnegative relaxation per bound and minimizes the scaled relaxations: it answers "how far
must the bounds move to be feasible" when the bounded problem is infeasible.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

import casadi as ca
import numpy as np

from .schemes import Scheme


def _assembly(rows, cols, shape, *, summed: bool = False):
    """Sparsity of the triplets ``(rows, cols)`` and the sparse 0/1 matrix mapping values in
    triplet order to its nonzeros in CSC order (duplicates are added when ``summed``)."""
    rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
    key = cols * shape[0] + rows
    uniq = np.unique(key)
    if not summed and uniq.size != key.size:
        raise RuntimeError("duplicate entries in a Jacobian pattern")
    pos = np.searchsorted(uniq, key)
    ucols, urows = uniq // shape[0], uniq % shape[0]
    indptr = np.concatenate([[0], np.cumsum(np.bincount(ucols, minlength=shape[1]))])
    sparsity = ca.Sparsity(int(shape[0]), int(shape[1]), indptr.astype(np.int64).tolist(),
                           urows.astype(np.int64).tolist())
    S = ca.DM(ca.Sparsity.triplet(int(uniq.size), int(key.size), pos.tolist(), list(range(key.size))), 1.0)
    return sparsity, S


def _block_triplets(nrow: int, index: np.ndarray, row0: int):
    """Global (row, col) of the vec of a mapped dense block output ``(nrow x nz)`` per repetition
    (``index``: ``(count, nz)`` global columns; rows ``row0 + k nrow + i``), in vec order."""
    count, nz = index.shape
    k = np.repeat(np.arange(count), nz * nrow)
    j = np.tile(np.repeat(np.arange(nz), nrow), count)
    i = np.tile(np.arange(nrow), count * nz)
    return row0 + k * nrow + i, index[k, j]


def _all_cached(functions) -> bool:
    from .compiled import is_cached

    return all(is_cached(f) for f in functions)


def _compile(fn):
    from .compiled import compile_cached

    return compile_cached(fn)


def slack_scale(servo, duration: float) -> float:
    """``c`` of the relaxed servo rows (module doc): ``w^3`` (Baumgarte) so that a constant
    slack ``s`` holds the output error ``e = s``; ``1/duration^3`` without stabilization."""
    if servo.formulation == "baumgarte" and servo.omega > 0:
        return float(servo.omega) ** 3
    return 1.0 / float(duration) ** 3


def relaxed_rhs(servo) -> ca.Function:
    """``(X, Y, theta, s, c) -> F``: the index-reduced inverse model with the servo rows
    relaxed by ``c s`` (module doc); ``s = 0`` gives :attr:`ServoModel.rhs`."""
    fn = getattr(servo, "_relaxed_rhs", None)
    if fn is None:
        L = servo.layout
        X, Y = ca.SX.sym("X", L.nx), ca.SX.sym("Y", 4 * L.m)
        th, s, c = ca.SX.sym("theta", servo.model.theta.shape[0]), ca.SX.sym("s", L.m), ca.SX.sym("c")
        F = servo.rhs(X, Y, th)
        Az = servo.decoupling(X, Y, th)
        dz = ca.solve(Az, ca.vertcat(ca.SX.zeros(L.l + L.p), c * s))
        F = F + ca.vertcat(ca.SX.zeros(2 * L.n), dz)
        fn = ca.Function("servo_rhs_relaxed", [X, Y, th, s, c], [F], ["X", "Y", "theta", "s", "c"], ["F"])
        servo._relaxed_rhs = fn
    return fn


@dataclass(frozen=True)
class PathRow:
    """One bounded quantity of a transcription: ``kind`` ("X": an entry of ``X``; "rate": an
    entry of ``u'``), ``entry`` (index into ``X``, or into ``u`` for rates), ``where`` ("mesh",
    "mid", "col", "ext": at an interval fraction given as a parameter, see
    :meth:`OCPTranscription.extremum_points`) and ``point`` (its index among those points)."""

    kind: str
    entry: int
    where: str
    point: int


#: the names of OCPTranscription.__init__ the structured Hessian (structured_hessian) reads
_HESSIAN_CONTEXT = (
    "zeta", "pin", "G", "n_def", "n_ip", "npr", "n_el", "flat_pts", "pts_keys", "x", "p",
)


class OCPTranscription:
    """The NLP of one (servo model, selection, scheme, N, structure); see the module doc.

    Parameters
    ----------
    relaxed : bool
        Slack variables on the servo rows (least-squares tracking) or exact tracking.
    free_time : bool
        ``tau`` is a decision variable.
    bounded : tuple of int
        Entries of ``X`` that have bounds (with ``interior``, rows between the nodes are added to ``g``).
    rated : tuple of int
        Entries of ``u`` with rate bounds (their ``F`` rows are added to ``g``).
    elastic : bool
        Every bound as a relaxed constraint (module doc); needs ``relaxed``.
    interior : {"hull", "points", None}
        Interior rows of the bounded entries (module doc): Bezier control points ("hull"; the
        Hermite-Simpson default), points at parameter positions ("points") or none (Legendre/Radau
        default: mesh and collocation points only).

    Notes
    -----
    Decision vector ``[vec(X_mesh); vec(X_col); vec(S) (m x nS, relaxed); tau (free_time); r
    (elastic)]``; parameters ``[h; vec(Y); theta; E0; Ef; sqrt(W) (m); sqrt(rho, w_E, w_R); w_T;
    c; mask (N: 1 on the intervals of [t0, tf]); tau_ref; relaxation weights; eps; scale; interior
    points (n_points x N)]``;
    constraints ``[defects; boundary conditions; bounded quantities (:attr:`path_rows`)]``, the
    bounded quantities twice (upper, lower) in the elastic problem.

    Derivatives: every point (mesh, midpoint, collocation point) is one call of a mapped SX
    function returning ``G = (F, r)`` (right-hand side, objective residual) and its dense
    Jacobian; per interval a small SX function chains them (exactly, through the
    Hermite-Simpson midpoint) into the interval's rows of the constraint Jacobian and of the
    residual Jacobian ``J_R``.  The Hessian of the Lagrangian is the Gauss-Newton matrix
    ``2 J_R^T J_R`` of the least-squares objective ``|R|^2`` (constraint curvature dropped, as
    acados does by default): exact where the residual and the multipliers vanish (feasible
    tracking), a linearly convergent approximation elsewhere.  ``hessian="exact"`` in
    :meth:`ipopt` differentiates the whole graph instead (slow; for checks).
    """

    def __init__(self, servo, selection, scheme: Scheme, N: int, *, relaxed: bool, free_time: bool = False,
                 bounded: tuple = (), rated: tuple = (), elastic: bool = False, interior: str | None = "auto",
                 compiled: bool | str = False):
        t_build = time.perf_counter()
        if elastic and not relaxed:
            raise ValueError("the elastic problem relaxes the servo constraint (relaxed=True)")
        self.servo, self.selection, self.scheme, self.N = servo, selection, scheme, int(N)
        self.relaxed, self.free_time, self.elastic = bool(relaxed), bool(free_time), bool(elastic)
        if interior == "auto":
            interior = scheme.interiors[0]
        if interior not in scheme.interiors:
            raise ValueError(f"interior must be one of {scheme.interiors} for {scheme.name}, got {interior!r}")
        self.interior = interior
        self.bounded, self.rated = tuple(int(i) for i in bounded), tuple(int(i) for i in rated)
        L = servo.layout
        nx, m, m4 = L.nx, L.m, 4 * L.m
        nth = servo.model.theta.shape[0]
        self.nx, self.m, self.m4, self.ntheta = nx, m, m4, nth
        N = self.N
        self.n_col, self.nY = scheme.n_col(N), scheme.n_samples(N)
        self.nS = self.nY  # slacks where F is evaluated: nodes + midpoints (HS), collocation points
        ub = L.blocks["u"]
        u_idx = list(range(ub.start, ub.stop))
        rate_rows = [u_idx[i] for i in self.rated]
        bnd = list(self.bounded)
        # interior points per interval (module doc): positions are parameters
        self.n_points = scheme.n_points(len(bnd), len(rate_rows)) if interior == "points" else 0
        hull = interior == "hull"
        # ---------------------------------------------------------------- global layout
        self.nXs = nx * (N + 1) + nx * self.n_col
        self.nSv = m * self.nS if self.relaxed else 0
        self.i_tau = self.nXs + self.nSv  # where tau is in x (free_time only)
        self.i_r = self.nXs + self.nSv + (1 if self.free_time else 0)
        self.relax_labels = ([("X", i, side) for i in self.bounded for side in ("lower", "upper")]
                             + [("rate", j, side) for j in self.rated for side in ("lower", "upper")]
                             if self.elastic else [])
        self.nr = len(self.relax_labels)
        self.nX = self.i_r + self.nr
        sizes = [("h", N), ("Y", m4 * self.nY), ("theta", nth), ("E0", nx), ("Ef", nx), ("W", m), ("w", 3),
                 ("wT", 1), ("c", 1), ("mask", N), ("tau_ref", 1), ("relax_w", self.nr), ("eps", 1), ("fscale", 1),
                 ("points", self.n_points * N)]
        self._p_slices, o = {}, 0
        for name, k in sizes:
            self._p_slices[name] = slice(o, o + k)
            o += k
        self.np = o
        nz_pt = nx + (m if self.relaxed else 0)

        def cols(block, k):  # global indices of column k of X_mesh ("X"), X_col ("C") or S ("S")
            if block == "X":
                return k * nx + np.arange(nx)
            if block == "C":
                return nx * (N + 1) + k * nx + np.arange(nx)
            return self.nXs + k * m + np.arange(m)

        def point_cols(kx, ks, block="X"):
            return np.concatenate([cols(block, kx)] + ([cols("S", ks)] if self.relaxed else []))

        # ---------------------------------------------------------------- SX building blocks
        Frel = relaxed_rhs(servo)
        th, c, sW, sw = ca.SX.sym("theta", nth), ca.SX.sym("c"), ca.SX.sym("sqrtW", m), ca.SX.sym("sqrtw", 3)
        tau_ref, hr, mk = ca.SX.sym("tau_ref"), ca.SX.sym("h"), ca.SX.sym("mask")
        tau = ca.SX.sym("tau") if self.free_time else None
        T = [tau] if tau is not None else []
        ratio = tau / tau_ref if tau is not None else 1  # used only with tau

        # one point: G = (F, r) and its Jacobian in zeta = (X, s)
        zeta, Yraw = ca.SX.sym("zeta", nz_pt), ca.SX.sym("Y", m4)
        Y = Yraw if tau is None else Yraw * ca.vertcat(*[ca.repmat(ratio ** (-k), m, 1) for k in range(4)])
        X = zeta[:nx]
        s = zeta[nx:] if self.relaxed else ca.SX.zeros(m)
        F = Frel(X, Y, th, s, c)
        e = servo.output(X, Y, th) - Y[:m]
        r = ca.vertcat(*([sW * e] + ([sw[0] * s] if self.relaxed else []) + [sw[1] * X[u_idx], sw[2] * F[u_idx]]))
        G = ca.vertcat(F, r)
        self.nG, nrp = int(G.numel()), int(r.numel())
        pin = [zeta, Yraw] + T + [th, c, sW, sw, tau_ref]
        pt_val = ca.Function("ocp_point", pin, [G])
        jouts = [G, ca.densify(ca.jacobian(G, zeta))] + ([ca.densify(ca.jacobian(G, tau))] if tau is not None else [])
        pt_jac = ca.Function("ocp_point_jac", pin, jouts)
        # interval: values from the point outputs, and their Jacobian by the chain rule (linear in d)
        h = hr if tau is None else hr * (1 + mk * (ratio - 1))
        dh = 0 if tau is None else hr * mk / tau_ref  # dh/dtau
        sp = ca.SX.sym("points", self.n_points)
        ipars = [hr, mk] + T + [tau_ref, sp]
        nG = self.nG

        def lin(JG, Gt, dzeta, dt):  # first-order change of G at a point
            out = ca.mtimes(JG, dzeta)
            return out if tau is None else out + Gt * dt

        ctx = SimpleNamespace(nx=nx, m=m, nG=nG, nz_pt=nz_pt, N=N, h=h, dh=dh, tau=tau, sp=sp, ipars=ipars, bnd=bnd,
                            rate_rows=rate_rows, rated=self.rated, hull=hull, interior=interior, relaxed=self.relaxed,
                            lin=lin, cols=cols, point_cols=point_cols, i_tau=self.i_tau, block_triplets=_block_triplets)
        val, iv_val, iv_jac, iv_index, ctx.local = scheme.ocp_interval(ctx)
        n_def, n_res, n_ip = (int(v.numel()) for v in val)
        self._functions = {"point": pt_val, "point_jac": pt_jac, "interval": iv_val, "interval_jac": iv_jac}
        # compiled functions (never differentiated themselves: they feed the custom derivatives below);
        # "auto": only when already in the disk cache, the rest compiled in the background
        self._compile_request = compiled
        # the Gauss-Newton block J_k^T J_k of an interval's residual Jacobian on its structural nonzeros (upper triangle
        # when the interval's columns are in global order); compiled, cheaper than the sparse product of the assembled J_R
        Jk = ca.SX.sym("JR", ca.sparsify(iv_jac.call(iv_jac.sx_in())[1]).sparsity())
        JtJ_k = ca.mtimes(Jk.T, Jk)
        ordered = bool(np.all(np.diff(iv_index, axis=1) > 0))
        gn_blk = ca.Function("ocp_gn_block", [Jk], [ca.densify(ca.triu(JtJ_k) if ordered else JtJ_k)])
        # the values too: with compiled pieces IPOPT gets the objective gradient from them (grad_f), never by AD
        pieces = (pt_val, iv_val, pt_jac, iv_jac, gn_blk)
        self.compiled = self._compile_request is True or (self._compile_request == "auto" and _all_cached(pieces))
        self._pending: tuple = ()
        self._compile_started = False
        self._pending_hessian: tuple = ()
        self._hessian_compile_started = False
        if self.compiled:
            pt_val, iv_val, pt_jac, iv_jac, gn_blk = (_compile(f) for f in pieces)
        elif self._compile_request == "auto":  # compiled in the background once the first solve has returned
            from .collocation import DEFERRED
            from .compiled import is_cached

            self._pending = tuple(f for f in pieces if not is_cached(f))
            DEFERRED.append(self)
        # ---------------------------------------------------------------- the MX graph
        x, p = ca.MX.sym("x", self.nX), ca.MX.sym("p", self.np)
        P = {k: p[sl] for k, sl in self._p_slices.items()}
        Ymat = ca.reshape(P["Y"], m4, self.nY)
        Xmesh = ca.reshape(x[:nx * (N + 1)], nx, N + 1)
        Xcol = ca.reshape(x[nx * (N + 1):self.nXs], nx, self.n_col)  # nx x 0 for Hermite-Simpson
        S = ca.reshape(x[self.nXs:self.nXs + self.nSv], m, self.nS) if self.relaxed else ca.MX(m, 0)
        tau_x = [x[self.i_tau]] if self.free_time else []
        common = tau_x + [P["theta"], P["c"], P["W"], P["w"], P["tau_ref"]]
        ip = [P["h"].T, P["mask"].T] + tau_x + [P["tau_ref"], ca.reshape(P["points"], self.n_points, N)]

        def zeta_of(Xs, a, b):
            return ca.vertcat(Xs, S[:, a:b]) if self.relaxed else Xs

        ctx.__dict__.update(pt_val=pt_val, pt_jac=pt_jac, iv_val=iv_val, iv_jac=iv_jac, iv_index=iv_index, Xmesh=Xmesh,
                          Xcol=Xcol, Ymat=Ymat, common=common, ip=ip, zeta_of=zeta_of)
        (defect, resid, ipath), Gn = scheme.ocp_graph(ctx, False)
        (Jdef, JR_blk, Jip), pts = scheme.ocp_graph(ctx, True)
        s0, sf = list(selection.start), list(selection.end)
        bc = ca.vertcat(Xmesh[s0, 0] - P["E0"][s0], Xmesh[sf, N] - P["Ef"][sf])
        trip = []  # (rows, cols, values) of the Jacobian of g
        trip.append((*_block_triplets(n_def, iv_index, 0), ca.vec(Jdef)))
        o = N * n_def
        self.n_defect, self.n_bc = o, len(s0) + len(sf)
        bc_cols = np.concatenate([np.asarray(s0, np.int64), N * nx + np.asarray(sf, np.int64)])
        trip.append((o + np.arange(bc_cols.size), bc_cols, ca.DM.ones(bc_cols.size)))
        o += bc_cols.size
        parts, rows, pj, base = [], [], [], 0
        n_el = 0  # elastic state rows (mesh and collocation points) before the interval path rows
        if self.elastic and bnd:  # bounds on the mesh and collocation states become constraints
            parts.append(ca.vec(Xmesh[bnd, :]))
            rows += [PathRow("X", i, "mesh", k) for k in range(N + 1) for i in bnd]
            ccols = [k * nx + i for k in range(N + 1) for i in bnd]
            if self.n_col:
                parts.append(ca.vec(Xcol[bnd, :]))
                rows += [PathRow("X", i, "col", k) for k in range(self.n_col) for i in bnd]
                ccols += [nx * (N + 1) + k * nx + i for k in range(self.n_col) for i in bnd]
            pj.append((np.arange(len(ccols)), np.array(ccols, np.int64), ca.DM.ones(len(ccols))))
            base = n_el = len(ccols)
        if n_ip:
            parts.append(ca.vec(ipath))
            for k in range(N):  # in the order of the interval rows (Scheme.path_points)
                rows += [PathRow(*r) for r in scheme.ocp_interval_rows(k, bnd, self.rated, interior)]
            pj.append((*_block_triplets(n_ip, iv_index, base), ca.vec(Jip)))
            base += N * n_ip
        mparts, mrows, mpj = scheme.ocp_mesh_rates(ctx, Gn, pts, base)  # rates at the mesh points (Hermite-Simpson)
        parts += mparts
        rows += [PathRow(*r) for r in mrows]
        pj += mpj
        self.path_rows = tuple(rows)
        npr = len(rows)
        path = ca.vertcat(*parts) if parts else ca.MX(0, 1)
        if self.elastic:  # value - r_up <= ub (first copy), value + r_lo >= lb (second copy)
            index = {lab: k for k, lab in enumerate(self.relax_labels)}
            up = np.array([index[(q.kind, q.entry, "upper")] for q in rows], np.int64)
            lo = np.array([index[(q.kind, q.entry, "lower")] for q in rows], np.int64)
            rx = x[self.i_r:]
            path = ca.vertcat(path - rx[up.tolist()], path + rx[lo.tolist()])
            pj = pj + [(rr + npr, cc, vv) for rr, cc, vv in pj]
            pj += [(np.arange(npr), self.i_r + up, -ca.DM.ones(npr)),
                   (npr + np.arange(npr), self.i_r + lo, ca.DM.ones(npr))]
        trip += [(o + rr, cc, vv) for rr, cc, vv in pj]
        g = ca.vertcat(ca.vec(defect), bc, path)
        self.ng = int(g.shape[0])
        sp_g, S_g = _assembly(np.concatenate([t[0] for t in trip]), np.concatenate([t[1] for t in trip]),
                              (self.ng, self.nX))
        Jg = ca.MX(sp_g, ca.mtimes(S_g, ca.vertcat(*[t[2] for t in trip])))
        R = ca.vec(resid)
        self.nR = int(R.shape[0])
        rows_r, cols_r = _block_triplets(n_res, iv_index, 0)
        sp_r, S_r = _assembly(rows_r, cols_r, (self.nR, self.nX))
        JR = ca.MX(sp_r, ca.mtimes(S_r, ca.vec(JR_blk)))
        # g with its assembled Jacobian (IPOPT never differentiates the mapped graph by AD)
        xs, ps = ca.MX.sym("x", self.nX), ca.MX.sym("p", self.np)
        gs, Jgs, JRs = ca.substitute([g, Jg, JR], [x, p], [xs, ps])
        og = ca.MX.sym("out_g", self.ng)
        jac_g = ca.Function("jac_ocp_g", [xs, ps, og], [Jgs, ca.MX(self.ng, self.np)], ["x", "p", "out_g"],
                            ["jac_g_x", "jac_g_p"])
        self._gfun = ca.Function("ocp_g", [xs, ps], [gs], ["x", "p"], ["g"],
                                 {"custom_jacobian": jac_g, "jac_penalty": 0})
        self._jac_g = jac_g  # (x, p, g) -> (dg/dx, 0): the held re-solve's predictor (bounded.predicted_start)
        weight = P["eps"] if self.elastic else P["fscale"]
        f = weight * ca.sumsqr(R)
        if self.free_time:
            f = f + P["fscale"] * P["wT"] * x[self.i_tau]
        if self.elastic:
            f = f + ca.dot(P["relax_w"], x[self.i_r:])
        lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", self.ng)
        ws = ca.substitute(weight, p, ps)
        if self.compiled:  # the sum of the intervals' blocks, upper triangle
            count, nzl = iv_index.shape
            _r, cols_h = _block_triplets(nzl, iv_index, 0)
            rows_h = iv_index[np.repeat(np.arange(count), nzl * nzl), np.tile(np.arange(nzl), count * nzl)]
            keep = rows_h <= cols_h
            sp_h, S_h = _assembly(rows_h[keep], cols_h[keep], (self.nX, self.nX), summed=True)
            blocks = ca.substitute([ca.vec(gn_blk.map(N)(JR_blk))], [x, p], [xs, ps])[0]
            JtJ = ca.MX(sp_h, ca.mtimes(S_h, blocks[np.flatnonzero(keep).tolist()]))
        else:
            JtJ = ca.triu(ca.mtimes(JRs.T, JRs))
        self._hess_gn = ca.Function("gauss_newton_hess_lag", [xs, ps, lam_f, lam_g], [2 * lam_f * ws * JtJ],
                                    ["x", "p", "lam_f", "lam_g"], ["triu_hess_gamma_x_x"])
        # the gradient from the assembled residual Jacobian, for compiled pieces (HS N = 100: 3 against 13 ms by reverse AD)
        Rs, fs = ca.substitute([R, f], [x, p], [xs, ps])
        grad = 2 * ws * ca.mtimes(JRs.T, Rs)
        if self.free_time:
            grad[self.i_tau] += ps[self._p_slices["fscale"]] * ps[self._p_slices["wT"]]
        if self.elastic:
            grad[self.i_r:] += ps[self._p_slices["relax_w"]]
        self._grad_f = ca.Function("ocp_grad_f", [xs, ps], [fs, grad], ["x", "p"], ["f", "grad_f_x"])
        if self.compiled:  # compiled values have no derivatives: f's is the assembled one (as g's)
            of = ca.MX.sym("out_f")
            jac_f = ca.Function("jac_ocp_f", [xs, ps, of], [grad.T, ca.MX(1, self.np)], ["x", "p", "out_f"],
                                ["jac_f_x", "jac_f_p"])
            f = ca.Function("ocp_f", [xs, ps], [fs], ["x", "p"], ["f"],
                            {"custom_jacobian": jac_f, "jac_penalty": 0})(x, p)
        self._residual_fn = ca.Function("ocp_residual", [x, p], [R])

        # the point outputs the exact Hessian needs, as expressions of (x, p)
        pts_map = pts
        pts_keys, flat_pts = list(pts_map), list(pts_map.values())
        ctx.__dict__.update({k: v for k, v in locals().items() if k in _HESSIAN_CONTEXT})
        self._hx = ctx
        self._build_exact_hessian = lambda: structured_hessian(self)
        self.g = self._gfun(x, p)
        self.f = f
        self._plain_fg = None if self.compiled else (f, g)  # the same NLP without custom derivatives (hessian="ad")
        self._structure = dict(relaxed=relaxed, free_time=free_time, bounded=bounded, rated=rated, elastic=elastic,
                               interior=interior)
        self._x, self._p = x, p
        self._solvers: dict = {}
        self.build_s = time.perf_counter() - t_build

    @property
    def _plain(self):
        """``(f, g)`` of the NLP without custom derivatives, for AD of the whole graph (``hessian="ad"``, checks);
        with compiled pieces (no derivatives) built from the SX functions, on the same symbols."""
        if self._plain_fg is None:
            other = OCPTranscription(self.servo, self.selection, self.scheme, self.N, compiled=False, **self._structure)
            self._plain_fg = tuple(ca.substitute(list(other._plain), [other._x, other._p], [self._x, self._p]))
        return self._plain_fg

    def start_background_compile(self) -> None:
        """Start compiling the derivative pieces missing from the disk cache in the background (once per
        group: the first solve's pieces, then the exact Hessian's once it is asked for)."""
        from .compiled import compile_in_background

        if self._pending and not self._compile_started:
            self._compile_started = True
            compile_in_background(list(self._pending))
        if self._pending_hessian and not self._hessian_compile_started:
            self._hessian_compile_started = True
            compile_in_background(list(self._pending_hessian))

    def defer_hessian(self, fns) -> None:
        """Compile the exact Hessian's pieces ``fns`` missing from the disk cache in the background once the
        solve that asked for them has returned (a later transcription of this structure evaluates them in C)."""
        from .collocation import DEFERRED
        from .compiled import is_cached

        self._pending_hessian = tuple(f for f in fns if not is_cached(f))
        if self._pending_hessian:
            DEFERRED.append(self)

    def upgradable(self) -> bool:
        """Whether a group of pieces compiled in the background since this transcription was built (the first
        solve's, or the exact Hessian's) is now in the disk cache: a new transcription of the same structure
        would evaluate it in C."""
        from .compiled import is_cached

        return any(group and all(is_cached(f) for f in group) for group in (self._pending, self._pending_hessian))

    def residual(self, x, p) -> np.ndarray:
        """The objective residual ``R`` (``f = scale |R|^2 + ...``)."""
        return np.array(self._residual_fn(x, p)).ravel()

    def g_function(self):
        """``(x, p) -> g`` (with the assembled Jacobian)."""
        return self._gfun

    # ------------------------------------------------------------------ layout
    def sample_times(self, t_mesh) -> np.ndarray:
        """Times of the reference samples (order of ``Y`` and of the slacks): the scheme's."""
        return self.scheme.sample_times(t_mesh)

    def collocation_times(self, t_mesh) -> np.ndarray:
        """Times of ``X_col`` (empty for Hermite-Simpson)."""
        return self.scheme.collocation_times(t_mesh)

    def row_times(self, t_mesh) -> np.ndarray:
        """Time of every bounded quantity (:attr:`path_rows`; interior points: the midpoint)."""
        t_mesh = np.asarray(t_mesh, float)
        mid = 0.5 * (t_mesh[:-1] + t_mesh[1:])
        at = {"mesh": t_mesh, "mid": mid, "col": self.collocation_times(t_mesh), "ext": mid}
        return np.array([at[r.where][r.point] for r in self.path_rows])

    def parameters(self, t_mesh, Ysamples, theta, E0, Ef, *, W=1.0, rho=0.0, energy=0.0, rate=0.0,
                   time_weight=0.0, c=1.0, mask=None, tau_ref=1.0, relax_weights=None, eps=0.0,
                   scale=1.0, points=None) -> np.ndarray:
        """The parameter vector (class notes); ``W``, ``rho``, ``energy``, ``rate``, ``time_weight``
        are the objective weights (the square roots of the first four enter the residuals),
        ``scale`` multiplies the whole objective (IPOPT's objective scaling without a new solver;
        the elastic problem has ``eps`` on its least-squares part instead); ``points``: the positions
        of the interior points (:meth:`extremum_points`; default :meth:`default_points`)."""
        p = np.zeros(self.np)
        S = self._p_slices
        p[S["h"]] = np.diff(np.asarray(t_mesh, float))
        p[S["Y"]] = np.asarray(Ysamples, float).ravel(order="F")
        p[S["theta"]] = theta
        p[S["E0"]], p[S["Ef"]] = E0, Ef
        p[S["W"]] = np.sqrt(np.broadcast_to(np.asarray(W, float), (self.m,)))
        p[S["w"]] = np.sqrt([rho, energy, rate])
        p[S["wT"]] = time_weight
        p[S["c"]] = c
        p[S["mask"]] = 0.0 if mask is None else mask
        p[S["tau_ref"]] = tau_ref
        if self.nr:
            p[S["relax_w"]] = relax_weights
        p[S["eps"]] = eps
        p[S["fscale"]] = scale
        p[S["points"]] = (self.default_points() if points is None else np.asarray(points, float)).ravel(order="F")
        return p

    def default_points(self) -> np.ndarray:
        """Interior points spread over every interval: ``(n_points, N)`` fractions."""
        nb, nr = len(self.bounded), len(self.rated)
        col = self.scheme.default_fractions(nb, nr) if self.interior == "points" else []
        return np.zeros((len(col), self.N)) + np.array(col, float)[:, None]

    def extremum_points(self, inv) -> np.ndarray:
        """Where the polynomials of ``inv`` (on this transcription's mesh, or a retimed one) have their
        interior extrema: the positions for :meth:`parameters` that bound them exactly (a bound
        held at every interior extremum and at the nodes holds everywhere); free slots stay spread."""
        pts = self.default_points()
        if not self.n_points:
            return pts
        nb, N = len(self.bounded), self.N
        h = np.diff(inv.t_mesh)
        slots, sch = self.scheme.point_slots(), self.scheme
        deriv = []  # coefficients in s of d/ds of the polynomial of every bounded entry, (degree x N)
        for i in self.bounded:
            C = sch.coefficients(inv.X_mesh, inv.dX_mesh, inv.X_col, i, h)
            deriv.append(C[:-1] * np.arange(C.shape[0] - 1, 0, -1)[:, None])
        sch.rate_extrema(inv, self.servo.layout.blocks["u"].start, self.rated, pts, nb)
        for e, D in enumerate(deriv):
            for k in range(N):
                roots = [float(z.real) for z in np.roots(D[:, k]) if abs(z.imag) < 1e-12 and 0 < z.real < 1]
                spread = [q / (slots + 1) for q in range(1, slots + 1)]
                chosen = sorted(roots)[:slots]
                chosen += [s for s in spread if all(abs(s - c) > 0.05 for c in chosen)][:slots - len(chosen)]
                for q, sq in enumerate(chosen):
                    pts[q * nb + e, k] = sq
        return pts

    def pack(self, Xmesh, Xcol=None, S=None, tau=None, r=None) -> np.ndarray:
        """The decision vector from its parts (slacks and relaxations default to zero)."""
        parts: list[Any] = [np.asarray(Xmesh, float).ravel(order="F")]
        if self.n_col:
            parts.append(np.asarray(Xcol, float).ravel(order="F"))
        if self.relaxed:
            parts.append(np.zeros(self.nSv) if S is None else np.asarray(S, float).ravel(order="F"))
        if self.free_time:
            parts.append([float(tau)])
        if self.nr:
            parts.append(np.zeros(self.nr) if r is None else np.asarray(r, float))
        return np.concatenate(parts)

    def unpack(self, x):
        """``(X_mesh, X_col, S, tau, r)`` from a decision vector."""
        x = np.asarray(x, float).ravel()
        nx, N = self.nx, self.N
        Xmesh = x[:nx * (N + 1)].reshape(nx, N + 1, order="F")
        Xcol = x[nx * (N + 1):self.nXs].reshape(nx, self.n_col, order="F") if self.n_col else np.zeros((nx, 0))
        S = (x[self.nXs:self.nXs + self.nSv].reshape(self.m, self.nS, order="F") if self.relaxed
             else np.zeros((self.m, self.nS)))
        tau = float(x[self.i_tau]) if self.free_time else None
        return Xmesh, Xcol, S, tau, x[self.i_r:self.i_r + self.nr]

    @staticmethod
    def retimed_mesh(t_mesh_ref, mask, tau_ref, tau) -> np.ndarray:
        """The mesh for the transition length ``tau``: intervals with ``mask`` scaled by ``tau / tau_ref``."""
        h = np.diff(np.asarray(t_mesh_ref, float)) * (1 + np.asarray(mask, float) * (tau / tau_ref - 1))
        return np.concatenate([[t_mesh_ref[0]], t_mesh_ref[0] + np.cumsum(h)])

    # ------------------------------------------------------------------ solver
    def ipopt(self, options: dict, *, hessian: str = "gauss-newton") -> ca.Function:
        """The IPOPT solver for these options (built once per option set).

        ``hessian``: ``"gauss-newton"`` (default, class notes), ``"exact"`` (CasADi AD of the whole
        graph; slow) or ``"limited-memory"`` (IPOPT's quasi-Newton)."""
        if hessian not in ("gauss-newton", "exact", "limited-memory", "ad"):
            raise ValueError(f"hessian must be 'gauss-newton', 'exact', 'limited-memory' or 'ad', got {hessian!r}")
        key = repr((sorted((k, repr(v)) for k, v in options.items()), hessian))
        if key not in self._solvers:
            opts = dict(options)
            if hessian == "ad":
                f, g = self._plain
                nlp = {"x": self._x, "p": self._p, "f": f, "g": g}
            elif hessian == "exact":
                if getattr(self, "_hess_exact", None) is None:
                    self._hess_exact = self._build_exact_hessian()
                nlp = {"x": self._x, "p": self._p, "f": self.f, "g": self.g}
                opts["hess_lag"] = self._hess_exact
            else:
                nlp = {"x": self._x, "p": self._p, "f": self.f, "g": self.g}
                if hessian == "gauss-newton" and opts.get("ipopt.hessian_approximation", "exact") == "exact":
                    opts["hess_lag"] = self._hess_gn
                else:
                    opts["ipopt.hessian_approximation"] = "limited-memory"
            if hessian != "ad" and self.compiled:  # "ad" differentiates the plain graph (checks); in CasADi's
                opts["grad_f"] = self._grad_f  # virtual machine reverse AD is cheaper than the Jacobian chain
            self._solvers[key] = ca.nlpsol("servo_ocp", "ipopt", nlp, opts)
        return self._solvers[key]

    def point_values(self, zeta, Ysamples, theta, c, tau=None, tau_ref=1.0) -> np.ndarray:
        """``G = (F, r)`` at points ``zeta = (X, s)`` (columns), e.g. the slopes ``F`` at the mesh
        points for the Hermite-Simpson interpolant (``r`` with unit weights)."""
        k = zeta.shape[1]
        tau = tau_ref if tau is None else tau  # samples given for the actual duration: no retiming
        args = [zeta, Ysamples] + ([tau] if self.free_time else []) + [theta, c, np.ones(self.m), np.ones(3), tau_ref]
        return np.array(self.servo.maps.mapped(self._functions["point"], k)(*args))


# ---------------------------------------------------------------- the exact Hessian, structured
def structured_hessian(tr) -> ca.Function:
    """``(x, p, lam_f, lam_g) -> triu(Hessian of the Lagrangian)`` of ``tr`` (``hessian="exact"``).

    Every point (mesh point, midpoint, collocation point) contributes ``G = (F, r)``; per interval the
    constraint rows and residuals are low-degree formulas in the point outputs, the local states and
    ``h(tau)``.  The Hessian is the sum of, per point, the Hessian of ``w . G`` in ``(zeta, tau)`` with ``w``
    the *total* adjoint weight of the point's outputs (through the Hermite-Simpson midpoint state too), and,
    per interval, the exact second-order expansion of the interval formulas with the point outputs replaced
    by their first-order models (``G + J dzeta + G_tau dtau``) plus the midpoint's point Hessian pulled back
    through ``dzeta_m / dz`` (:meth:`~invctl.inversion.schemes.Scheme.hessian_interval`).  Checked against
    CasADi's AD of the whole graph in ``tests/test_ocp.py`` (relative 1e-12)."""
    c = tr._hx
    nG, zeta, tau, G, n_def, n_ip, h, dh, N = c.nG, c.zeta, c.tau, c.G, c.n_def, c.n_ip, c.h, c.dh, c.N
    npr, n_el, x, p, ip, common, scheme = c.npr, c.n_el, c.x, c.p, c.ip, c.common, tr.scheme
    wv = ca.SX.sym("w", nG)
    pvars = ca.vertcat(zeta, tau) if tau is not None else zeta
    npv = int(pvars.numel())
    pt_hess = ca.Function("ocp_point_hess", c.pin + [wv], [ca.densify(ca.hessian(ca.dot(wv, G), pvars)[0])])
    lam_s, mu_s, fs = ca.SX.sym("lam", n_def), ca.SX.sym("mu", n_ip), ca.SX.sym("fs")
    hd_sym = ca.SX.sym("dt") if tau is not None else ca.SX(0)
    h_d = h + (dh * hd_sym if tau is not None else 0)
    iv_w, iv_h = scheme.hessian_interval(c, lam_s, mu_s, fs, hd_sym, h_d, npv)
    hfuns = [pt_hess, iv_w, iv_h]
    if tr._compile_request is True or (tr._compile_request == "auto" and _all_cached(hfuns)):
        pt_hess, iv_w, iv_h = (_compile(fn) for fn in hfuns)
    elif tr._compile_request == "auto":  # in the virtual machine now, compiled in the background after the solve
        tr.defer_hessian(hfuns)
    # ---- MX assembly
    xs2, ps2 = ca.MX.sym("x", tr.nX), ca.MX.sym("p", tr.np)
    lf, lg = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", tr.ng)
    Pm = {k: ps2[sl] for k, sl in tr._p_slices.items()}
    fsv = lf * (Pm["eps"] if tr.elastic else Pm["fscale"])
    base_p = tr.n_defect + tr.n_bc
    lam_def = ca.reshape(lg[:N * n_def], n_def, N)

    def path_mult(a, n_):  # multipliers of path rows a..a+n_ (both copies when elastic)
        out = lg[base_p + a:base_p + a + n_]
        return out + lg[base_p + npr + a:base_p + npr + a + n_] if tr.elastic else out

    mu_ip = ca.reshape(path_mult(n_el, N * n_ip), n_ip, N) if n_ip else ca.MX(0, N)
    outs = dict(zip(c.pts_keys, ca.substitute(c.flat_pts, [x, p], [xs2, ps2])))
    ip2 = ca.substitute(ip, [p, x], [ps2, xs2]) if ip else []
    com2 = ca.substitute(common, [p, x], [ps2, xs2])
    trip_h = scheme.hessian_blocks(c, outs, iv_w, iv_h, pt_hess, lam_def, mu_ip, fsv, ip2, com2, path_mult, tr.i_tau)
    rr, cc, vv = [], [], []
    for index, blk in trip_h:
        count, nzl = index.shape
        r_, c_ = _block_triplets(nzl, index, 0)  # rows here are local: recompute global rows
        k = np.repeat(np.arange(count), nzl * nzl)
        i_loc = np.tile(np.arange(nzl), count * nzl)
        grow = index[k, i_loc]
        keep = grow <= c_
        rr.append(grow[keep])
        cc.append(c_[keep])
        vv.append(ca.vec(blk)[np.flatnonzero(keep).tolist()])
    sp_h, S_h = _assembly(np.concatenate(rr), np.concatenate(cc), (tr.nX, tr.nX), summed=True)
    H = ca.MX(sp_h, ca.mtimes(S_h, ca.vertcat(*vv)))
    return ca.Function("structured_hess_lag", [xs2, ps2, lf, lg], [H], ["x", "p", "lam_f", "lam_g"],
                       ["triu_hess_gamma_x_x"])
