"""Collocation schemes: a scheme is a class, and everything that differs between schemes is one of its methods.

``hermite-simpson``  :class:`HermiteSimpson`, compressed Hermite-Simpson (Lobatto IIIA, order 4):
                     states at the mesh points, cubic Hermite interpolant collocated at the midpoint;
``legendre<d>``      :class:`GaussLegendre`, collocation at ``d`` Gauss-Legendre points (order 2d);
``radau<d>``         :class:`RadauIIA`, collocation at ``d`` Radau IIA points (order 2d - 1).

A scheme answers the sizes and times of a transcription (collocation states, reference samples),
the polynomial the solution is between the nodes (values, derivative, coefficients) and builds the
scheme's part of the two transcriptions: the defect equations and their Jacobian blocks of
:class:`~invctl.inversion.collocation.Transcription` (``bvp_*``), the interval rows, their
derivatives and bound points of :class:`~invctl.inversion.ocp.OCPTranscription` (``ocp_*``,
``path_points``) and of its exact Hessian (``hessian_*``).
"""
from __future__ import annotations

import re
from typing import Any, Callable

import casadi as ca
import numpy as np

from .servo import NUMERIC_SOLVES_NX

SCHEME_RE = re.compile(r"^(hermite-simpson|hs|legendre(\d+)|radau(\d+))$")


class Scheme:
    """A collocation scheme: where ``F`` is evaluated on an interval, the polynomial the solution is
    between the nodes, and the defect equations (with their Jacobian blocks) of the transcription.

    ``name``, ``degree``, ``order``; ``tau``: the points in (0, 1] where ``F`` is evaluated
    besides the mesh; ``stages``: points per interval (memory estimates); ``poly_degree``: degree
    of the interpolating polynomial; ``interiors``: the interior bound rows of
    :class:`~invctl.inversion.ocp.OCPTranscription` it supports (the first is the default),
    ``tracking_interior`` the one for problems that cannot reshape around the points;
    ``rates_between_nodes``: whether rate bounds hold on the whole interval; ``buffered``: whether the
    Newton backend evaluates through CasADi buffers by default (:meth:`Transcription.evaluators`).
    """

    name: str
    block_name: str
    interval_name: str  # the name of :meth:`bvp_interval`'s function (its compiled form is looked up by it)
    degree: int
    order: int
    tau: np.ndarray
    stages: int
    poly_degree: int
    interiors: tuple
    tracking_interior: str | None
    rates_between_nodes: bool
    buffered: bool

    def __repr__(self):
        return f"{type(self).__name__}({self.name!r})"

    def mesh_slopes(self, X_mesh, slopes) -> np.ndarray:
        """``dX_mesh`` of an :class:`~invctl.inversion.result.Inverse` (``slopes()``: ``F`` at the mesh, called
        only by a scheme whose polynomial needs it)."""
        return np.zeros_like(X_mesh)

    # methods of the subclasses (see HermiteSimpson, Collocation): sizes and times
    n_col: Callable[[int], int]
    n_samples: Callable[[int], int]
    sample_times: Callable[..., np.ndarray]
    collocation_times: Callable[..., np.ndarray]
    interior_samples: Callable[[int], slice]
    # the polynomial between the nodes (values, derivative; coefficients in s = (t - t_k) / h)
    evaluate: Callable[..., np.ndarray]
    coefficients: Callable[..., np.ndarray]
    # the square transcription's pieces (collocation.py) and their parameter derivatives (sensitivity.py)
    bvp_interval: Callable[..., Any]
    bvp_defects: Callable[..., Any]
    bvp_blocks: Callable[..., Any]
    bvp_jacobian_values: Callable[..., list]
    bvp_pattern: Callable[..., tuple]
    bvp_residual: Callable[..., tuple]
    bvp_theta_function: Callable[..., Any]
    bvp_theta_jacobian: Callable[..., tuple]
    slope_sensitivities: Callable[..., np.ndarray]
    # the bounded problems' pieces (ocp.py, bounded.py)
    bound_points: Callable[..., tuple]
    path_points: Callable[..., Any]
    n_points: Callable[[int, int], int]
    default_fractions: Callable[[int, int], list]
    point_slots: Callable[[], int]
    rate_extrema: Callable[..., None]
    ocp_interval: Callable[..., tuple]
    ocp_graph: Callable[..., tuple]
    ocp_interval_rows: Callable[..., list]
    ocp_mesh_rates: Callable[..., tuple]
    hessian_interval: Callable[..., tuple]
    hessian_blocks: Callable[..., list]


class HermiteSimpson(Scheme):
    """Compressed Hermite-Simpson: cubic Hermite pieces through the mesh values and slopes, the
    defect ``X_{k+1} - X_k - h (F_k + 4 F_m + F_{k+1}) / 6`` with the midpoint state
    ``X_m = (X_k + X_{k+1}) / 2 + h (F_k - F_{k+1}) / 8``."""

    name, degree, order, stages, poly_degree = "hermite-simpson", 3, 4, 2, 3
    block_name = "hs_blocks"  # the block function's name (its compiled form is looked up by it)
    interval_name = "hs_interval"
    tau = np.array([0.5, 1.0])
    interiors, tracking_interior, rates_between_nodes, buffered = ("hull", "points"), "points", True, True

    def n_col(self, N):
        return 0

    def n_samples(self, N):
        return 2 * N + 1

    def sample_times(self, t_mesh):
        t_mesh = np.asarray(t_mesh, float)
        return np.concatenate([t_mesh, t_mesh[:-1] + 0.5 * np.diff(t_mesh)])

    def collocation_times(self, t_mesh):
        return np.zeros(0)

    def interior_samples(self, N):
        return slice(N + 1, None)

    def mesh_slopes(self, X_mesh, slopes):
        return np.asarray(slopes(), float)

    def evaluate(self, X_mesh, dX_mesh, X_col, k, h, s, derivative=False):
        """The solution on the intervals ``k`` (lengths ``h``) at fractions ``s`` (time derivative with ``derivative``)."""
        if derivative:
            s2 = s * s
            return ((X_mesh[:, k + 1] - X_mesh[:, k]) * (6 * s - 6 * s2) / h
                    + dX_mesh[:, k] * (3 * s2 - 4 * s + 1) + dX_mesh[:, k + 1] * (3 * s2 - 2 * s))
        h00, h10, h01, h11 = self._hermite(s)
        return (X_mesh[:, k] * h00 + dX_mesh[:, k] * (h10 * h)
                + X_mesh[:, k + 1] * h01 + dX_mesh[:, k + 1] * (h11 * h))

    def coefficients(self, X_mesh, dX_mesh, X_col, row, h):
        y0, y1 = X_mesh[row, :-1], X_mesh[row, 1:]
        d0, d1 = h * dX_mesh[row, :-1], h * dX_mesh[row, 1:]
        return np.array([2 * y0 + d0 - 2 * y1 + d1, -3 * y0 - 2 * d0 + 3 * y1 - d1, d0, y0])

    # ------------------------------------------------------------ the transcription's pieces
    @staticmethod
    def _ends(A, w: int = 1):
        """``(A[:, :-w], A[:, w:])`` of an MX with ``N + 1`` column blocks of width ``w`` (the blocks at the
        start and at the end of every interval) by one split and two concatenations: a column slice
        builds an index of every nonzero (~5 ms for the right-hand side Jacobians of N = 200)."""
        n = A.shape[1]
        first, middle, last = ca.horzsplit(A, [0, w, n - w, n])
        return ca.horzcat(first, middle), ca.horzcat(middle, last)

    @staticmethod
    def _midpoint(Xa, Xb, Fa, Fb, h):
        return 0.5 * (Xa + Xb) + h / 8 * (Fa - Fb)

    def bvp_interval(self, tr, rhs, ub) -> ca.Function:
        """One interval's defect and energy (SX)."""
        nx, m4 = tr.nx, tr.m4
        Xa, Xb, Fa, Fb = (ca.SX.sym(s, nx) for s in ("Xa", "Xb", "Fa", "Fb"))
        Ym, th, hs = ca.SX.sym("Ym", m4), ca.SX.sym("theta", tr.ntheta), ca.SX.sym("h")
        Xm = self._midpoint(Xa, Xb, Fa, Fb, hs)
        Fm = rhs(Xm, Ym, th)
        defect = Xb - Xa - hs / 6 * (Fa + 4 * Fm + Fb)
        energy = hs / 6 * (ca.sumsqr(Xa[ub]) + 4 * ca.sumsqr(Xm[ub]) + ca.sumsqr(Xb[ub]))
        return ca.Function(self.interval_name, [Xa, Xb, Fa, Fb, hs, Ym, th], [defect, energy],
                           ["Xa", "Xb", "Fa", "Fb", "h", "Ym", "theta"], ["defect", "energy"])

    def bvp_defects(self, tr, interval, rhs, x, Xmesh, h, Y, theta):
        """Mapped ``(defect, energy)`` of all intervals (MX)."""
        N = tr.N
        Fn = rhs.map(N + 1)(Xmesh, Y[:, :N + 1], theta)
        return interval.map(N)(*self._ends(Xmesh), *self._ends(Fn), h, Y[:, N + 1:], theta)

    def bvp_blocks(self, tr) -> ca.Function:
        """SX function of the Jacobian blocks ``(Da^T, Db^T)`` of one interval."""
        nx, m4 = tr.nx, tr.m4
        Xa, Xb, Fa, Fb = (ca.SX.sym(s, nx) for s in ("Xa", "Xb", "Fa", "Fb"))
        Ja, Jb = ca.SX.sym("Ja", nx, nx), ca.SX.sym("Jb", nx, nx)
        hs, Ym, th = ca.SX.sym("h"), ca.SX.sym("Ym", m4), ca.SX.sym("th", tr.ntheta)
        _Fm, Jm = tr.servo.rhs_jac(self._midpoint(Xa, Xb, Fa, Fb, hs), Ym, th)
        return ca.Function(self.block_name, [Xa, Xb, Fa, Fb, Ja, Jb, hs, Ym, th], list(self._block_pair(Ja, Jb, Jm, hs)))

    @staticmethod
    def _block_pair(Ja, Jb, Jm, h):
        I = ca.DM.eye(Ja.shape[0])  # noqa: E741
        Da = -I - h / 6 * (Ja + 4 * ca.mtimes(Jm, 0.5 * I + h / 8 * Ja))
        Db = I - h / 6 * (Jb + 4 * ca.mtimes(Jm, 0.5 * I - h / 8 * Jb))
        return Da.T, Db.T

    def bvp_jacobian_values(self, tr, x, Xmesh, h, Y, theta, rj):
        """The nonzeros of the defect rows of ``dg/dx`` (MX), in the block order of :meth:`bvp_pattern`."""
        nx, N = tr.nx, tr.N
        if not tr.compiled and nx > NUMERIC_SOLVES_NX:
            # large blocks: the right-hand side Jacobian with numeric solves by M (ServoModel.rhs_jac_numeric),
            # at the midpoints by the mapped function, and the two nx^3 products of every interval as MX
            # matrix products (compiled C loops), not as nx^3 SX instructions per interval
            rjn = tr.servo.rhs_jac_numeric
            F, JF = rjn.map(N + 1)(Xmesh, Y[:, :N + 1], theta)
            Fa, Fb = F[:, :N], F[:, 1:]
            Xm = 0.5 * (Xmesh[:, :N] + Xmesh[:, 1:]) + ca.repmat(h / 8, nx, 1) * (Fa - Fb)
            _Fm, JFm = rjn.map(N)(Xm, Y[:, N + 1:], theta)
            Ja, Jb, Jm = (ca.MX.sym(k, nx, nx) for k in ("Ja", "Jb", "Jm"))
            hs = ca.MX.sym("h")
            prod = ca.Function("hs_block_products", [Ja, Jb, Jm, hs], list(self._block_pair(Ja, Jb, Jm, hs)))
            DaT, DbT = prod.map(N)(JF[:, :nx * N], JF[:, nx:], JFm, h)
        else:
            blk = tr.piece(self.block_name, tr.block_function)
            F, JF = rj.map(N + 1)(Xmesh, Y[:, :N + 1], theta)
            DaT, DbT = blk.map(N)(*self._ends(Xmesh), *self._ends(F), *self._ends(JF, nx), h, Y[:, N + 1:], theta)
        return [ca.vec(DaT), ca.vec(DbT)]

    def bvp_pattern(self, tr):
        """Rows and columns of the dense defect blocks, and the number of defect rows."""
        nx, N = tr.nx, tr.N
        r, k = np.arange(nx), np.arange(N)
        rows, cols = [], []
        for off in (0, 1):  # d defect_k / d X_{k+off}
            rows.append((k[:, None, None] * nx + r[None, :, None]).repeat(nx, 2))
            cols.append(((k + off)[:, None, None] * nx + r[None, None, :]).repeat(nx, 1))
        return rows, cols, N * nx

    def bvp_residual(self, tr, Xmesh, Xcol, h, Y, theta, jacobian: bool):
        """The defects (numpy) and, with ``jacobian``, the values of their blocks."""
        N, nx = tr.N, tr.nx
        if not jacobian:
            rm = tr._rhs_map
            F = np.array(rm(N + 1)(Xmesh, Y[:, :N + 1], theta))
            Fm = np.array(rm(N)(self._midpoint(Xmesh[:, :-1], Xmesh[:, 1:], F[:, :-1], F[:, 1:], h),
                                Y[:, N + 1:], theta))
            return (Xmesh[:, 1:] - Xmesh[:, :-1] - h / 6 * (F[:, :-1] + 4 * Fm + F[:, 1:])).ravel(order="F"), None
        I = np.eye(nx)  # noqa: E741
        F, JF = tr._rhs_jac_map(N + 1)(Xmesh, Y[:, :N + 1], theta)
        F = np.array(F)
        JF = np.array(JF).reshape(nx, N + 1, nx).transpose(1, 0, 2)
        Fa, Fb, JFa, JFb = F[:, :-1], F[:, 1:], JF[:-1], JF[1:]
        Xm = self._midpoint(Xmesh[:, :-1], Xmesh[:, 1:], Fa, Fb, h)
        Fm, JFm = tr._rhs_jac_map(N)(Xm, Y[:, N + 1:], theta)
        Fm = np.array(Fm)
        JFm = np.array(JFm).reshape(nx, N, nx).transpose(1, 0, 2)
        defect = Xmesh[:, 1:] - Xmesh[:, :-1] - h / 6 * (Fa + 4 * Fm + Fb)
        hh = h[:, None, None]
        Da = -I - hh / 6 * (JFa + 4 * np.einsum("kij,kjl->kil", JFm, 0.5 * I + hh / 8 * JFa))
        Db = I - hh / 6 * (JFb + 4 * np.einsum("kij,kjl->kil", JFm, 0.5 * I - hh / 8 * JFb))
        return defect.ravel(order="F"), [Da.ravel(), Db.ravel()]

    def bvp_theta_function(self, iv, ins, defect, D, nx, nth):
        """``d(defect)/dtheta`` of one interval, also through the node slopes ``F_a, F_b``
        (``+ d/dF_a F_theta(a) + d/dF_b F_theta(b)``; inputs Xa, Xb, Fa, Fb, Fta, Ftb, h, Ym, theta)."""
        Fta, Ftb = ca.SX.sym("Fta", nx, nth), ca.SX.sym("Ftb", nx, nth)
        D = D + ca.mtimes(ca.jacobian(defect, ins[2]), Fta) + ca.mtimes(ca.jacobian(defect, ins[3]), Ftb)
        return ca.Function("interval_dtheta", ins[:4] + [Fta, Ftb] + ins[4:], [ca.densify(D)])

    def bvp_theta_jacobian(self, fn, rhs, dF, Xm, Xc, h, Y, th):
        """The mapped :meth:`bvp_theta_function` and ``F_theta`` at the mesh (``None`` if not needed)."""
        N, nth = Xm.shape[1] - 1, th.size
        F = np.array(rhs.map(N + 1)(Xm, Y[:, :N + 1], th))
        Ft = np.array(dF.map(N + 1)(Xm, Y[:, :N + 1], th))
        D = fn.map(N)(Xm[:, :N], Xm[:, 1:], F[:, :N], F[:, 1:], Ft[:, :nth * N], Ft[:, nth:], h[None, :],
                      Y[:, N + 1:], th)
        return np.array(D), Ft

    def slope_sensitivities(self, rhs_jac, Xm, Y, th, dXm, Ft):
        """``d dX_mesh / dtheta`` from ``dX_mesh/dtheta``: ``dF = F_X dX + F_theta`` (``y_ref`` fixed)."""
        nx, N = Xm.shape[0], Xm.shape[1] - 1
        _F, JF = rhs_jac.map(N + 1)(Xm, Y[:, :N + 1], th)
        JF = np.array(JF).reshape(nx, N + 1, nx).transpose(1, 0, 2)
        return np.einsum("kij,pjk->pik", JF, dXm) + Ft.reshape(nx, N + 1, th.size).transpose(2, 0, 1)

    def bound_points(self, inv, rhs, samples, theta, ub):
        """States and rates where a bounded transcription imposes its bounds: ``(t_states, X, t_rates, U')``
        (mesh points and midpoints; ``samples(t)``: the reference samples)."""
        tm = inv.t_mesh
        tmid = 0.5 * (tm[:-1] + tm[1:])
        Xm = inv.X(tmid)  # the Hermite interpolant at the midpoint is the HS midpoint state
        Fm = np.array(rhs.map(tmid.size)(Xm, samples(tmid), theta))
        return (np.concatenate([tm, tmid]), np.hstack([inv.X_mesh, Xm]), np.concatenate([tm, tmid]),
                np.hstack([inv.dX_mesh[ub], Fm[ub]]))

    # ------------------------------------------------------------ the OCP's pieces (ocp.py)
    @staticmethod
    def _hermite(s):
        """The cubic Hermite basis ``h00, h10, h01, h11`` at ``s`` (numbers, arrays or SX)."""
        s2, s3 = s * s, s * s * s
        return 2 * s3 - 3 * s2 + 1, s3 - 2 * s2 + s, -2 * s3 + 3 * s2, s3 - s2

    def path_points(self, Xa, Xb, Fa, Fb, Fm, h, sp, bnd, rate_rows, hull: bool):
        """The interval's bound rows (:mod:`~invctl.inversion.ocp` module doc): Bezier control points (``hull``)
        or the cubics at the fractions ``sp[:nb]``, ``sp[nb:2 nb]`` and their derivatives at ``sp[2 nb:]``."""
        nb, out = len(bnd), []
        fa, fb, b1 = Fa[rate_rows], Fb[rate_rows], 2 * Fm[rate_rows] - (Fa[rate_rows] + Fb[rate_rows]) / 2
        if hull:
            return ca.vertcat(Xa[bnd] + h / 3 * Fa[bnd], Xb[bnd] - h / 3 * Fb[bnd], b1)
        for q in range(2 if nb else 0):
            h00, h10, h01, h11 = self._hermite(sp[q * nb:(q + 1) * nb])
            out.append(Xa[bnd] * h00 + h * Fa[bnd] * h10 + Xb[bnd] * h01 + h * Fb[bnd] * h11)
        if len(rate_rows):
            r = sp[2 * nb:]
            out.append(fa * (1 - r) ** 2 + 2 * b1 * r * (1 - r) + fb * r ** 2)
        return ca.vertcat(*out) if out else ca.SX(0, 1)

    def n_points(self, nb: int, nr: int) -> int:
        """Interior points per interval of ``interior="points"`` for ``nb`` bounded entries and ``nr`` rates."""
        return 2 * nb + nr

    def default_fractions(self, nb: int, nr: int) -> list:
        """Positions of the interior points spread over an interval."""
        return [1 / 3] * nb + [2 / 3] * nb + [0.5] * nr

    def point_slots(self) -> int:
        """Interior points per bounded entry."""
        return 2

    def rate_extrema(self, inv, ub: int, rated, pts, nb: int):
        """Move the rate points of ``pts`` to the interior extrema of ``u'`` (its quadratic pieces)."""
        h = np.diff(inv.t_mesh)
        for r, j in enumerate(rated):
            fa, fb = inv.dX_mesh[ub + j, :-1], inv.dX_mesh[ub + j, 1:]
            b1 = 3 * (inv.X_mesh[ub + j, 1:] - inv.X_mesh[ub + j, :-1]) / h - fa - fb
            den = fa - 2 * b1 + fb
            with np.errstate(divide="ignore", invalid="ignore"):
                s = np.where(np.abs(den) > 1e-300, (fa - b1) / den, 0.5)
            pts[2 * nb + r] = np.where((s > 0) & (s < 1), s, 0.5)

    def ocp_interval(self, c):
        """One interval of :class:`~invctl.inversion.ocp.OCPTranscription` (``c``: its building blocks): the rows
        ``(defect, residual, path)``, their function and Jacobian, the columns of its variables, a local function."""
        nx, nG, nz_pt, h, dh, tau, sp = c.nx, c.nG, c.nz_pt, c.h, c.dh, c.tau, c.sp
        bnd, rate_rows, hull, lin, cols, N = c.bnd, c.rate_rows, c.hull, c.lin, c.cols, c.N
        Xa, Xb, Xm = ca.SX.sym("Xa", nx), ca.SX.sym("Xb", nx), ca.SX.sym("Xm", nx)
        Ga, Gb, Gm = ca.SX.sym("Ga", nG), ca.SX.sym("Gb", nG), ca.SX.sym("Gm", nG)
        mid_state = ca.Function("ocp_hs_mid", [Xa, Xb, Ga, Gb] + c.ipars,
                                [0.5 * (Xa + Xb) + h / 8 * (Ga[:nx] - Gb[:nx])])
        Fa, Fb, Fm = Ga[:nx], Gb[:nx], Gm[:nx]
        val = (Xb - Xa - h / 6 * (Fa + 4 * Fm + Fb),
               ca.vertcat(ca.sqrt(h / 6) * Ga[nx:], ca.sqrt(2 * h / 3) * Gm[nx:], ca.sqrt(h / 6) * Gb[nx:]),
               self.path_points(Xa, Xb, Fa, Fb, Fm, h, sp, bnd, rate_rows, hull))
        iv_val = ca.Function("ocp_hs_interval", [Xa, Xb, Xm, Ga, Gb, Gm] + c.ipars, list(val))
        # chain rule: local variables z = (Xa, Xb, sa, sb, sm, tau)
        JGa, JGb, JGm = (ca.SX.sym(k, nG, nz_pt) for k in ("JGa", "JGb", "JGm"))
        Gta, Gtb, Gtm = (ca.SX.sym(k, nG) for k in ("Gta", "Gtb", "Gtm"))
        dXa, dXb = ca.SX.sym("dXa", nx), ca.SX.sym("dXb", nx)
        dsa, dsb, dsm = (ca.SX.sym(k, c.m) if c.relaxed else ca.SX(0, 1) for k in ("dsa", "dsb", "dsm"))
        dt = ca.SX.sym("dt") if tau is not None else ca.SX(0)
        dGa = lin(JGa, Gta, ca.vertcat(dXa, dsa), dt)
        dGb = lin(JGb, Gtb, ca.vertcat(dXb, dsb), dt)
        dXm = 0.5 * (dXa + dXb) + h / 8 * (dGa[:nx] - dGb[:nx]) + dh * dt / 8 * (Fa - Fb)
        dGm = lin(JGm, Gtm, ca.vertcat(dXm, dsm), dt)
        ddef = dXb - dXa - h / 6 * (dGa[:nx] + 4 * dGm[:nx] + dGb[:nx]) - dh * dt / 6 * (Fa + 4 * Fm + Fb)
        sq = [ca.sqrt(h / 6), ca.sqrt(2 * h / 3), ca.sqrt(h / 6)]
        dsq = [dh * dt / (2 * q) * k for q, k in zip(sq, (1 / 6, 2 / 3, 1 / 6))]
        dR = ca.vertcat(*[sq[i] * dG[nx:] + dsq[i] * G_[nx:]
                          for i, (dG, G_) in enumerate(((dGa, Ga), (dGm, Gm), (dGb, Gb)))])
        Z = ca.SX.zeros(nx)
        pp = self.path_points
        dpath = (pp(dXa, dXb, dGa[:nx], dGb[:nx], dGm[:nx], h, sp, bnd, rate_rows, hull)
                 + dh * dt * (pp(Z, Z, Fa, Fb, Fm, 1, sp, bnd, rate_rows, hull)
                              - pp(Z, Z, Fa, Fb, Fm, 0, sp, bnd, rate_rows, hull)))
        z = ca.vertcat(dXa, dXb, dsa, dsb, dsm, *([dt] if tau is not None else []))
        jins = [Ga, Gb, Gm, JGa, JGb, JGm] + ([Gta, Gtb, Gtm] if tau is not None else []) + c.ipars
        iv_jac = ca.Function("ocp_hs_interval_jac", jins, [ca.densify(ca.jacobian(q, z)) for q in (ddef, dR, dpath)])
        iv_index = np.stack([np.concatenate([cols("X", k), cols("X", k + 1)]
                                            + ([cols("S", k), cols("S", k + 1), cols("S", N + 1 + k)]
                                               if c.relaxed else [])
                                            + ([[c.i_tau]] if tau is not None else [])) for k in range(N)])
        return val, iv_val, iv_jac, iv_index, mid_state

    def ocp_graph(self, c, jac: bool):
        """The mapped interval values ``((defect, R, path), G at the mesh)``, or their Jacobian blocks and the point
        outputs, of :class:`~invctl.inversion.ocp.OCPTranscription` (MX)."""
        N, nz_pt, Xmesh, Ymat, common, ip, zeta_of = c.N, c.nz_pt, c.Xmesh, c.Ymat, c.common, c.ip, c.zeta_of
        pt = c.pt_jac if jac else c.pt_val
        out_n = pt.map(N + 1)(zeta_of(Xmesh, 0, N + 1), Ymat[:, :N + 1], *common)
        Gn = out_n[0] if jac else out_n
        Xm = c.local.map(N)(Xmesh[:, :N], Xmesh[:, 1:], Gn[:, :N], Gn[:, 1:], *ip)
        out_m = pt.map(N)(zeta_of(Xm, N + 1, 2 * N + 1), Ymat[:, N + 1:], *common)
        if not jac:
            return c.iv_val.map(N)(Xmesh[:, :N], Xmesh[:, 1:], Xm, Gn[:, :N], Gn[:, 1:], out_m, *ip), Gn
        JGn, Gm, JGm = out_n[1], out_m[0], out_m[1]
        tin = [out_n[2][:, :N], out_n[2][:, 1:], out_m[2]] if c.tau is not None else []
        blocks = c.iv_jac.map(N)(Gn[:, :N], Gn[:, 1:], Gm, JGn[:, :nz_pt * N], JGn[:, nz_pt:], JGm, *tin, *ip)
        pts = {"Gn": out_n[0], "JGn": out_n[1], "Gm": out_m[0], "JGm": out_m[1], "zn": zeta_of(Xmesh, 0, N + 1),
               "Yn": Ymat[:, :N + 1], "zm": zeta_of(Xm, N + 1, 2 * N + 1), "Ym": Ymat[:, N + 1:]}
        if c.tau is not None:
            pts.update({"Gtn": out_n[2], "Gtm": out_m[2]})
        return blocks, pts

    def ocp_interval_rows(self, k: int, bnd, rated, interior):
        """``(kind, entry, where, point)`` of the path rows of interval ``k``, in the order of :meth:`path_points`."""
        return ([("X", i, "ext", k) for _q in range(2 if interior else 0) for i in bnd]
                + [("rate", j, "ext", k) for j in rated])

    def ocp_mesh_rates(self, c, Gn, pts, base):
        """The rate rows at the mesh points: ``(values, rows, Jacobian triplets)``."""
        N, rate_rows, rated = c.N, c.rate_rows, c.rated
        if not rated:
            return [], [], []
        nidx = np.stack([c.point_cols(k, k) for k in range(N + 1)])
        pj = [(*c.block_triplets(len(rate_rows), nidx, base), ca.vec(pts["JGn"][rate_rows, :]))]
        if c.tau is not None:
            pj.append((base + np.arange((N + 1) * len(rate_rows)), np.full((N + 1) * len(rate_rows), c.i_tau),
                       ca.vec(pts["Gtn"][rate_rows, :])))
        return ([ca.vec(Gn[rate_rows, :])], [("rate", j, "mesh", k) for k in range(N + 1) for j in rated], pj)

    def hessian_interval(self, c, lam_s, mu_s, fs, hd_sym, h_d, npv):
        """``(weights, Hessian)`` functions of one interval for :func:`~invctl.inversion.ocp.structured_hessian`."""
        nx, nG, nz_pt, h, tau, lin, ipars = c.nx, c.nG, c.nz_pt, c.h, c.tau, c.lin, c.ipars

        def hull(Xa, Xb, Fa, Fb, Fm, hh):  # the interval's path rows
            return self.path_points(Xa, Xb, Fa, Fb, Fm, hh, c.sp, c.bnd, c.rate_rows, c.hull)

        Ga_, Gb_, Gm_ = (ca.SX.sym(k, nG) for k in ("Ga", "Gb", "Gm"))
        JGa_, JGb_, JGm_ = (ca.SX.sym(k, nG, nz_pt) for k in ("JGa", "JGb", "JGm"))
        Gta_, Gtb_, Gtm_ = (ca.SX.sym(k, nG) for k in ("Gta", "Gtb", "Gtm"))
        Hm_ = ca.SX.sym("Hm", npv, npv)
        # total adjoint weights of Ga, Gb, Gm (first-order models, gradient at 0)
        dGa, dGb, dGm = (ca.SX.sym(k, nG) for k in ("dGa", "dGb", "dGm"))
        Fa_, Fb_ = Ga_[:nx] + dGa[:nx], Gb_[:nx] + dGb[:nx]
        dXm = h / 8 * (dGa[:nx] - dGb[:nx])
        Gm_l = Gm_ + dGm + ca.mtimes(JGm_[:, :nx], dXm)
        PHI = (ca.dot(lam_s, -h / 6 * (Fa_ + 4 * Gm_l[:nx] + Fb_))
               + fs * (h / 6 * ca.sumsqr(Ga_[nx:] + dGa[nx:]) + 2 * h / 3 * ca.sumsqr(Gm_l[nx:])
                       + h / 6 * ca.sumsqr(Gb_[nx:] + dGb[nx:]))
               + ca.dot(mu_s, hull(ca.SX.zeros(nx), ca.SX.zeros(nx), Fa_, Fb_, Gm_l[:nx], h)))
        dall = ca.vertcat(dGa, dGb, dGm)
        wa, wb, wm = (ca.substitute(ca.gradient(PHI, v), dall, ca.DM.zeros(3 * nG)) for v in (dGa, dGb, dGm))
        iv_w = ca.Function("ocp_hs_weights", [Ga_, Gb_, Gm_, JGm_, lam_s, mu_s, fs] + ipars, [wa, wb, wm])
        # second-order expansion in the local variables d
        dXa_, dXb_ = ca.SX.sym("dXa", nx), ca.SX.sym("dXb", nx)
        dsa_, dsb_, dsm_ = (ca.SX.sym(k, c.m) if c.relaxed else ca.SX(0, 1) for k in ("dsa", "dsb", "dsm"))
        dt_ = hd_sym
        dGa2 = lin(JGa_, Gta_, ca.vertcat(dXa_, dsa_), dt_)
        dGb2 = lin(JGb_, Gtb_, ca.vertcat(dXb_, dsb_), dt_)
        Fa2, Fb2 = Ga_[:nx] + dGa2[:nx], Gb_[:nx] + dGb2[:nx]
        dXm2 = 0.5 * (dXa_ + dXb_) + h_d / 8 * (Fa2 - Fb2) - h / 8 * (Ga_[:nx] - Gb_[:nx])
        dzm = ca.vertcat(dXm2, dsm_)
        Gm2 = Gm_ + ca.mtimes(JGm_, dzm) + (Gtm_ * dt_ if tau is not None else 0)
        R2 = ca.vertcat(ca.sqrt(h_d / 6) * (Ga_[nx:] + dGa2[nx:]), ca.sqrt(2 * h_d / 3) * Gm2[nx:],
                        ca.sqrt(h_d / 6) * (Gb_[nx:] + dGb2[nx:]))
        PHI2 = (ca.dot(lam_s, dXb_ - dXa_ - h_d / 6 * (Fa2 + 4 * Gm2[:nx] + Fb2)) + fs * ca.sumsqr(R2)
                + ca.dot(mu_s, hull(dXa_, dXb_, Fa2, Fb2, Gm2[:nx], h_d)))
        zl = ca.vertcat(dXa_, dXb_, dsa_, dsb_, dsm_, *([dt_] if tau is not None else []))
        Jm = ca.jacobian(ca.vertcat(dzm, *([dt_] if tau is not None else [])), zl)
        H2 = ca.hessian(PHI2, zl)[0] + ca.mtimes([Jm.T, Hm_, Jm])
        H2 = ca.substitute(H2, zl, ca.DM.zeros(zl.numel()))
        tins = [Gta_, Gtb_, Gtm_] if tau is not None else []
        iv_h = ca.Function("ocp_hs_hess", [Ga_, Gb_, Gm_, JGa_, JGb_, JGm_] + tins + [lam_s, mu_s, fs, Hm_]
                           + ipars, [ca.densify(H2)])
        return iv_w, iv_h

    def hessian_blocks(self, c, outs, iv_w, iv_h, pt_hess, lam_def, mu_ip, fsv, ip2, com2, path_mult, i_tau):
        """``[(global columns, dense blocks)]`` of the Hessian: per point and per interval (MX)."""
        N, nG, nz_pt, tau, rate_rows = c.N, c.nG, c.nz_pt, c.tau, c.rate_rows
        Gn_, JGn_, Gm_v, JGm_v = outs["Gn"], outs["JGn"], outs["Gm"], outs["JGm"]
        wa, wb, wm = iv_w.map(N)(Gn_[:, :N], Gn_[:, 1:], Gm_v, JGm_v, lam_def, mu_ip, fsv, *ip2)
        Wn = ca.horzcat(wa, ca.MX.zeros(nG, 1)) + ca.horzcat(ca.MX.zeros(nG, 1), wb)
        if c.rated:
            mu_n = ca.reshape(path_mult(c.n_el + N * c.n_ip, (N + 1) * len(rate_rows)), len(rate_rows), N + 1)
            E = ca.DM(ca.Sparsity.triplet(nG, len(rate_rows), rate_rows, list(range(len(rate_rows)))), 1.0)
            Wn = Wn + ca.mtimes(E, mu_n)
        Hn = pt_hess.map(N + 1)(outs["zn"], outs["Yn"], *com2, Wn)
        Hm = pt_hess.map(N)(outs["zm"], outs["Ym"], *com2, wm)
        tins = [outs["Gtn"][:, :N], outs["Gtn"][:, 1:], outs["Gtm"]] if tau is not None else []
        Hb = iv_h.map(N)(Gn_[:, :N], Gn_[:, 1:], Gm_v, JGn_[:, :nz_pt * N], JGn_[:, nz_pt:], JGm_v, *tins,
                         lam_def, mu_ip, fsv, Hm, *ip2)
        pidx = np.stack([np.concatenate([c.point_cols(k, k)] + ([[i_tau]] if tau is not None else []))
                         for k in range(N + 1)])
        return [(pidx, Hn), (c.iv_index, Hb)]

class Collocation(Scheme):
    """Collocation at ``d`` points ``tau`` (derivative matrix ``C``, continuity weights ``D``, quadrature
    weights ``B``): the Lagrange polynomial through ``X_k`` and the ``d`` collocation states of
    the interval."""

    kind = ""
    block_name = "coll_block"
    interval_name = "coll_interval"
    interiors, tracking_interior, rates_between_nodes, buffered = (None, "hull", "points"), None, False, False

    def __init__(self, d: int):
        self.degree = self.poly_degree = int(d)
        self.stages = d + 1
        self.name = f"{self.kind}{d}"
        self.tau = tau = np.array(ca.collocation_points(d, self.kind))
        allt = np.concatenate([[0.0], tau])
        self.C, self.D, self.B = np.zeros((d + 1, d)), np.zeros(d + 1), np.zeros(d + 1)
        self.basis = []
        for j in range(d + 1):
            coeff = np.poly1d([1.0])
            for r in range(d + 1):
                if r != j:
                    coeff *= np.poly1d([1.0, -allt[r]]) / (allt[j] - allt[r])
            self.basis.append(coeff)
            self.D[j] = coeff(1.0)
            self.C[j, :] = np.polyder(coeff)(tau)
            self.B[j] = np.polyint(coeff)(1.0)

    def n_col(self, N):
        return self.degree * N

    def n_samples(self, N):
        return self.degree * N

    def sample_times(self, t_mesh):
        t_mesh = np.asarray(t_mesh, float)
        return (t_mesh[:-1, None] + np.diff(t_mesh)[:, None] * self.tau[None, :]).ravel()

    collocation_times = sample_times

    def interior_samples(self, N):
        return slice(None)

    def evaluate(self, X_mesh, dX_mesh, X_col, k, h, s, derivative=False):
        d = self.degree
        b = [np.polyder(c) for c in self.basis] if derivative else self.basis
        out = X_mesh[:, k] * b[0](s)
        for j in range(1, d + 1):
            out = out + X_col[:, k * d + j - 1] * b[j](s)
        return out / h if derivative else out

    def coefficients(self, X_mesh, dX_mesh, X_col, row, h):
        d = self.degree
        vals = np.vstack([X_mesh[row, :-1]] + [X_col[row, q::d] for q in range(d)])
        return np.sum([np.outer(b.coeffs, vals[j]) for j, b in enumerate(self.basis)], axis=0)

    # ------------------------------------------------------------ the transcription's pieces
    def bvp_interval(self, tr, rhs, ub):
        nx, m4, d = tr.nx, tr.m4, self.degree
        th, hs = ca.SX.sym("theta", tr.ntheta), ca.SX.sym("h")
        Xk, Xk1 = ca.SX.sym("Xk", nx), ca.SX.sym("Xk1", nx)
        Xc, Yc = ca.SX.sym("Xc", nx, d), ca.SX.sym("Yc", m4, d)
        Xall = ca.horzcat(Xk, Xc)
        Fc = ca.horzcat(*[rhs(Xc[:, r], Yc[:, r], th) for r in range(d)])
        res = ca.mtimes(Xall, ca.DM(self.C)) - hs * Fc
        cont = Xk1 - ca.mtimes(Xall, ca.DM(self.D))
        energy = hs * sum(self.B[r + 1] * ca.sumsqr(Xc[ub, r]) for r in range(d))
        return ca.Function(self.interval_name, [Xk, Xc, Xk1, hs, Yc, th], [ca.vertcat(ca.vec(res), cont), energy],
                           ["Xk", "Xc", "Xk1", "h", "Yc", "theta"], ["defect", "energy"])

    def bvp_defects(self, tr, interval, rhs, x, Xmesh, h, Y, theta):
        nx, N = tr.nx, tr.N
        Xcol = ca.reshape(x[nx * (N + 1):], nx, tr.n_col)
        return interval.map(N)(Xmesh[:, :N], Xcol, Xmesh[:, 1:], h, Y, theta)

    def bvp_blocks(self, tr):
        """SX function of the Jacobian block ``c I - h J`` of one collocation point."""
        nx = tr.nx
        Js, hs, cs = ca.SX.sym("J", nx, nx), ca.SX.sym("h"), ca.SX.sym("c")
        return ca.Function(self.block_name, [Js, hs, cs], [(cs * ca.DM.eye(nx) - hs * Js).T])

    def _blocks(self):
        """``(i, j, c)`` of the dense blocks ``c I`` (``- h J`` on the diagonal ``j = i + 1``) of one interval: row
        block ``i`` (``d``: continuity), column block ``j`` (0: ``X_k``, 1..d: ``X_col``, d+1: ``X_{k+1}``)."""
        d, C, D = self.degree, self.C, self.D
        return [(i, j, C[j, i] if i < d else 1.0 if j == d + 1 else -D[j])
                for i in range(d + 1) for j in range(d + 2) if not (j == d + 1 and i < d)]

    def bvp_jacobian_values(self, tr, x, Xmesh, h, Y, theta, rj):
        nx, N, d, C = tr.nx, tr.N, self.degree, self.C
        Xcol = ca.reshape(x[nx * (N + 1):], nx, tr.n_col)
        _F, JF = rj.map(d * N)(Xcol, Y, theta)
        blk = tr.piece(self.block_name, tr.block_function)
        hrep = ca.reshape(ca.repmat(h, d, 1), 1, d * N)
        crep = ca.DM(np.tile([C[i + 1, i] for i in range(d)], N)).T
        Bt = blk.map(d * N)(JF, hrep, crep)
        vals = []
        for i, j, c in self._blocks():
            if i < d and j - 1 == i:
                vals.append(ca.vec(Bt[:, [q for k in range(N) for q in range((k * d + i) * nx, (k * d + i + 1) * nx)]]))
            else:
                vals.append(ca.DM(np.tile((c * np.eye(nx)).ravel(), N)))
        return vals

    def bvp_pattern(self, tr):
        nx, N, d = tr.nx, tr.N, self.degree
        r, k = np.arange(nx), np.arange(N)
        base = k * nx * (d + 1)
        col0 = nx * (N + 1)
        rows, cols = [], []
        for i, j, _c in self._blocks():
            rb = base[:, None, None] + i * nx + r[None, :, None]
            if j == 0:
                cb = k[:, None, None] * nx + r[None, None, :]
            elif j <= d:
                cb = col0 + (k * d + j - 1)[:, None, None] * nx + r[None, None, :]
            else:
                cb = (k + 1)[:, None, None] * nx + r[None, None, :]
            rows.append(rb.repeat(nx, 2))
            cols.append(cb.repeat(nx, 1))
        return rows, cols, N * nx * (d + 1)

    def bvp_residual(self, tr, Xmesh, Xcol, h, Y, theta, jacobian):
        nx, N, d, C, D = tr.nx, tr.N, self.degree, self.C, self.D
        if jacobian:
            F, JF = tr._rhs_jac_map(d * N)(Xcol, Y, theta)
            JF = np.array(JF).reshape(nx, N, d, nx).transpose(1, 2, 0, 3)  # k, i, row, col
        else:
            F = tr._rhs_map(d * N)(Xcol, Y, theta)
        F = np.array(F).reshape(nx, N, d)
        Xall = np.concatenate([Xmesh[:, :-1, None], Xcol.reshape(nx, N, d)], axis=2)  # nx, N, d+1
        res = np.einsum("rkj,ji->rki", Xall, C) - h[None, :, None] * F
        cont = Xmesh[:, 1:] - np.einsum("rkj,j->rk", Xall, D)
        g_int = np.concatenate([res.transpose(0, 2, 1).reshape(nx * d, N, order="F"), cont], axis=0).ravel(order="F")
        if not jacobian:
            return g_int, None
        I, hh, vals = np.eye(nx), h[:, None, None], []  # noqa: E741
        for i, j, c in self._blocks():
            blk = c * I - (hh * JF[:, i] if i < d and j - 1 == i else 0.0)
            vals.append(np.ascontiguousarray(np.broadcast_to(blk, (N, nx, nx))).ravel())
        return g_int, vals

    def bvp_theta_function(self, iv, ins, defect, D, nx, nth):
        return ca.Function("interval_dtheta", ins, [ca.densify(D)])

    def bvp_theta_jacobian(self, fn, rhs, dF, Xm, Xc, h, Y, th):
        return np.array(fn.map(Xm.shape[1] - 1)(Xm[:, :-1], Xc, Xm[:, 1:], h[None, :], Y, th)), None

    def slope_sensitivities(self, rhs_jac, Xm, Y, th, dXm, Ft):
        return np.zeros_like(dXm)

    def bound_points(self, inv, rhs, samples, theta, ub):
        tm, tc = inv.t_mesh, self.collocation_times(inv.t_mesh)
        Fc = np.array(rhs.map(tc.size)(inv.X_col, samples(tc), theta))
        return np.concatenate([tm, tc]), np.hstack([inv.X_mesh, inv.X_col]), tc, Fc[ub]

    # ------------------------------------------------------------ the OCP's pieces (ocp.py)
    def quadrature_weights(self) -> np.ndarray:
        """Weights of the collocation points alone, ``int_0^1 l_r(s) ds`` for the Lagrange basis on ``tau``: the
        interpolatory rule, exact for ``s^k``, ``k < d`` (Gauss-Legendre: to degree ``2d - 1``; Radau IIA: ``2d - 2``)."""
        d = self.degree
        return np.linalg.solve(np.vander(self.tau, d, increasing=True).T, 1.0 / np.arange(1, d + 1))

    def bernstein_interior(self) -> np.ndarray:
        """``(d+1, d-1)``: the values of a degree-``d`` polynomial at ``0`` and the collocation points
        (a row) times it give its interior Bernstein coefficients on ``[0, 1]``."""
        from math import comb

        d = self.degree
        s = np.concatenate([[0.0], self.tau])[:, None]
        i = np.arange(d + 1)[None, :]
        A = np.array([[comb(d, k) for k in range(d + 1)]]) * s ** i * (1 - s) ** (d - i)
        return np.linalg.inv(A).T[:, 1:d]

    def path_points(self, Xall, sp, bnd, interior):
        """The interval's bound rows: ``X[bnd]`` of its polynomial (values ``Xall`` at 0 and ``tau``) at the fractions
        ``sp[q nb:(q + 1) nb]``, ``q < d - 1`` ("points"), its interior Bernstein coefficients ("hull"), or none."""
        if interior == "hull":
            return ca.vec(ca.mtimes(Xall[bnd, :], ca.DM(self.bernstein_interior())))
        nb, out = len(bnd), []
        for q in range(self.degree - 1 if interior == "points" else 0):
            s = sp[q * nb:(q + 1) * nb]
            val = 0
            for j, b in enumerate(self.basis):
                lj = 0
                for a in b.coeffs:  # Horner
                    lj = lj * s + float(a)
                val = val + Xall[bnd, j] * lj
            out.append(val)
        return ca.vertcat(*out) if out else ca.SX(0, 1)

    def n_points(self, nb, nr):
        return (self.degree - 1) * nb

    def default_fractions(self, nb, nr):
        return [q / self.degree for q in range(1, self.degree) for _ in range(nb)]

    def point_slots(self):
        return self.degree - 1

    def rate_extrema(self, inv, ub, rated, pts, nb):
        """Rates are bounded at the collocation points only: no rate points."""

    def _rows(self, c, Xk_, Xk1_, Xc_, Fc_, rc, h_):
        d, wq = self.degree, self.quadrature_weights()
        Xall = ca.horzcat(Xk_, Xc_)
        return (ca.vertcat(ca.vec(ca.mtimes(Xall, ca.DM(self.C)) - h_ * Fc_), Xk1_ - ca.mtimes(Xall, ca.DM(self.D))),
                ca.vertcat(*[ca.sqrt(h_ * float(wq[q])) * rc[:, q] for q in range(d)]),
                ca.vertcat(*[Fc_[c.rate_rows, q] for q in range(d)], self.path_points(Xall, c.sp, c.bnd, c.interior)))

    def ocp_interval(self, c):
        nx, nG, nz_pt, h, dh, tau, lin, cols, N, d = c.nx, c.nG, c.nz_pt, c.h, c.dh, c.tau, c.lin, c.cols, c.N, self.degree
        Xk, Xk1, Xc, Gc = ca.SX.sym("Xk", nx), ca.SX.sym("Xk1", nx), ca.SX.sym("Xc", nx, d), ca.SX.sym("Gc", nG, d)
        wq = self.quadrature_weights()
        val = self._rows(c, Xk, Xk1, Xc, Gc[:nx, :], Gc[nx:, :], h)
        iv_val = ca.Function("ocp_coll_interval", [Xk, Xk1, Xc, Gc] + c.ipars, list(val))
        JGc, Gtc = ca.SX.sym("JGc", nG, nz_pt * d), ca.SX.sym("Gtc", nG, d)
        dXk, dXk1, dXc = ca.SX.sym("dXk", nx), ca.SX.sym("dXk1", nx), ca.SX.sym("dXc", nx, d)
        dSc = ca.SX.sym("dSc", c.m, d) if c.relaxed else ca.SX(0, d)
        dt = ca.SX.sym("dt") if tau is not None else ca.SX(0)
        dGc = ca.horzcat(*[lin(JGc[:, q * nz_pt:(q + 1) * nz_pt], Gtc[:, q], ca.vertcat(dXc[:, q], dSc[:, q]), dt)
                           for q in range(d)])
        dall = ca.horzcat(dXk, dXc)
        ddef = ca.vertcat(ca.vec(ca.mtimes(dall, ca.DM(self.C)) - h * dGc[:nx, :] - dh * dt * Gc[:nx, :]),
                          dXk1 - ca.mtimes(dall, ca.DM(self.D)))
        sq = [ca.sqrt(h * float(wq[q])) for q in range(d)]
        dR = ca.vertcat(*[sq[q] * dGc[nx:, q] + dh * dt * float(wq[q]) / (2 * sq[q]) * Gc[nx:, q] for q in range(d)])
        dpath = ca.vertcat(*[dGc[c.rate_rows, q] for q in range(d)], self.path_points(dall, c.sp, c.bnd, c.interior))
        z = ca.vertcat(dXk, dXk1, ca.vec(dXc), ca.vec(dSc), *([dt] if tau is not None else []))
        jins = [Gc, JGc] + ([Gtc] if tau is not None else []) + c.ipars
        iv_jac = ca.Function("ocp_coll_interval_jac", jins,
                             [ca.densify(ca.jacobian(q, z)) for q in (ddef, dR, dpath)])
        iv_index = np.stack([np.concatenate([cols("X", k), cols("X", k + 1)]
                                            + [cols("C", k * d + q) for q in range(d)]
                                            + ([cols("S", k * d + q) for q in range(d)] if c.relaxed else [])
                                            + ([[c.i_tau]] if tau is not None else [])) for k in range(N)])
        return val, iv_val, iv_jac, iv_index, None

    def ocp_graph(self, c, jac):
        N, d = c.N, self.degree
        out_c = (c.pt_jac if jac else c.pt_val).map(N * d)(c.zeta_of(c.Xcol, 0, N * d), c.Ymat, *c.common)
        if not jac:
            return c.iv_val.map(N)(c.Xmesh[:, :N], c.Xmesh[:, 1:], c.Xcol, out_c, *c.ip), None
        tin = [out_c[2]] if c.tau is not None else []
        pts = {"Gc": out_c[0], "JGc": out_c[1], "zc": c.zeta_of(c.Xcol, 0, N * d), "Yc": c.Ymat}
        if c.tau is not None:
            pts["Gtc"] = out_c[2]
        return c.iv_jac.map(N)(out_c[0], out_c[1], *tin, *c.ip), pts

    def ocp_interval_rows(self, k, bnd, rated, interior):
        d = self.degree
        return ([("rate", j, "col", k * d + q) for q in range(d) for j in rated]
                + [("X", i, "ext", k) for _q in range(d - 1 if interior else 0) for i in bnd])

    def ocp_mesh_rates(self, c, Gn, pts, base):
        """Rates are bounded at the collocation points only (the interval rows)."""
        return [], [], []

    def hessian_interval(self, c, lam_s, mu_s, fs, hd_sym, h_d, npv):
        nx, nG, nz_pt, h, tau, d = c.nx, c.nG, c.nz_pt, c.h, c.tau, self.degree
        Gc_, JGc_, Gtc_ = ca.SX.sym("Gc", nG, d), ca.SX.sym("JGc", nG, nz_pt * d), ca.SX.sym("Gtc", nG, d)
        dGc = ca.SX.sym("dGc", nG, d)

        wq = self.quadrature_weights()

        def coll_phi(Gc_d, hh, dall, dXk1):
            rows = self._rows(c, dall[:, 0], dXk1, dall[:, 1:], Gc_d[:nx, :], Gc_d[nx:, :], hh)
            return (ca.dot(lam_s, rows[0]) + fs * sum(hh * float(wq[q]) * ca.sumsqr(Gc_d[nx:, q]) for q in range(d))
                    + ca.dot(mu_s, rows[2]))

        PHI = coll_phi(Gc_ + dGc, h, ca.SX.zeros(nx, d + 1), ca.SX.zeros(nx))
        wc = ca.substitute(ca.gradient(PHI, ca.vec(dGc)), ca.vec(dGc), ca.DM.zeros(nG * d))
        iv_w = ca.Function("ocp_coll_weights", [Gc_, lam_s, mu_s, fs] + c.ipars, [ca.reshape(wc, nG, d)])
        dXk_, dXk1_, dXc_ = ca.SX.sym("dXk", nx), ca.SX.sym("dXk1", nx), ca.SX.sym("dXc", nx, d)
        dSc_ = ca.SX.sym("dSc", c.m, d) if c.relaxed else ca.SX(0, d)
        dt_ = hd_sym
        dG2 = ca.horzcat(*[c.lin(JGc_[:, q * nz_pt:(q + 1) * nz_pt], Gtc_[:, q], ca.vertcat(dXc_[:, q], dSc_[:, q]),
                                 dt_) for q in range(d)])
        PHI2 = coll_phi(Gc_ + dG2, h_d, ca.horzcat(dXk_, dXc_), dXk1_)
        zl = ca.vertcat(dXk_, dXk1_, ca.vec(dXc_), ca.vec(dSc_), *([dt_] if tau is not None else []))
        H2 = ca.substitute(ca.hessian(PHI2, zl)[0], zl, ca.DM.zeros(zl.numel()))
        tins = [Gtc_] if tau is not None else []
        iv_h = ca.Function("ocp_coll_hess", [Gc_, JGc_] + tins + [lam_s, mu_s, fs] + c.ipars, [ca.densify(H2)])
        return iv_w, iv_h

    def hessian_blocks(self, c, outs, iv_w, iv_h, pt_hess, lam_def, mu_ip, fsv, ip2, com2, path_mult, i_tau):
        N, d, tau = c.N, self.degree, c.tau
        Gc_v, JGc_v = outs["Gc"], outs["JGc"]
        wc = iv_w.map(N)(Gc_v, lam_def, mu_ip, fsv, *ip2)
        Hc = pt_hess.map(N * d)(outs["zc"], outs["Yc"], *com2, wc)
        tins = [outs["Gtc"]] if tau is not None else []
        Hb = iv_h.map(N)(Gc_v, JGc_v, *tins, lam_def, mu_ip, fsv, *ip2)
        pidx = np.stack([np.concatenate([c.point_cols(j, j, "C")] + ([[i_tau]] if tau is not None else []))
                         for j in range(N * d)])
        return [(pidx, Hc), (c.iv_index, Hb)]

class GaussLegendre(Collocation):
    """Gauss-Legendre collocation (order ``2d``)."""

    kind = "legendre"

    def __init__(self, d: int):
        super().__init__(d)
        self.order = 2 * d


class RadauIIA(Collocation):
    """Radau IIA collocation (order ``2d - 1``)."""

    kind = "radau"

    def __init__(self, d: int):
        super().__init__(d)
        self.order = 2 * d - 1


def get_scheme(name: str) -> Scheme:
    """Parse ``hermite-simpson``, ``legendre<d>`` or ``radau<d>`` (d = 1..9)."""
    key = str(name).strip().lower()
    mt = SCHEME_RE.match(key)
    if not mt:
        raise ValueError(f"unknown collocation scheme {name!r}; use 'hermite-simpson', 'legendre<d>' or "
                         "'radau<d>' (e.g. legendre3, radau3)")
    if key in ("hermite-simpson", "hs"):
        return HermiteSimpson()
    d = int(mt.group(2) or mt.group(3))
    if not 1 <= d <= 9:
        raise ValueError(f"collocation degree must be 1..9, got {d}")
    return (GaussLegendre if key.startswith("legendre") else RadauIIA)(d)
