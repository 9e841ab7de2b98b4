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

from .assembly import _all_cached, _assembly, _block_triplets, _compile, quadrature_weights  # noqa: F401
from .collocation import Scheme


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


def _hermite(s):
    """The cubic Hermite basis ``h00, h10, h01, h11`` at ``s`` (numbers, arrays or SX)."""
    s2, s3 = s * s, s * s * s
    return 2 * s3 - 3 * s2 + 1, s3 - 2 * s2 + s, -2 * s3 + 3 * s2, s3 - s2


def hs_points(Xa, Xb, Fa, Fb, Fm, h, sp, bnd, rate_rows, hull: bool):
    """Hermite-Simpson interval rows (module doc).  ``hull``: the interior Bezier control points of
    the interpolating cubics of ``X[bnd]`` (``X_k + h F_k / 3``, ``X_{k+1} - h F_{k+1} / 3``) and the
    middle Bernstein coefficient ``2 F_m - (F_k + F_{k+1}) / 2`` of the quadratic derivatives of
    ``X[rate_rows]``; otherwise the cubics at the interval fractions ``sp[:nb]`` and ``sp[nb:2 nb]``
    and the derivatives at ``sp[2 nb:]``."""
    nb, out = len(bnd), []
    fa, fb, b1 = Fa[rate_rows], Fb[rate_rows], 2 * Fm[rate_rows] - (Fa[rate_rows] + Fb[rate_rows]) / 2
    if hull:
        return ca.vertcat(Xa[bnd] + h / 3 * Fa[bnd], Xb[bnd] - h / 3 * Fb[bnd], b1)
    for q in range(2 if nb else 0):
        h00, h10, h01, h11 = _hermite(sp[q * nb:(q + 1) * nb])
        out.append(Xa[bnd] * h00 + h * Fa[bnd] * h10 + Xb[bnd] * h01 + h * Fb[bnd] * h11)
    if len(rate_rows):
        r = sp[2 * nb:]
        out.append(fa * (1 - r) ** 2 + 2 * b1 * r * (1 - r) + fb * r ** 2)
    return ca.vertcat(*out) if out else ca.SX(0, 1)


def lagrange_basis(scheme: Scheme) -> list:
    """Coefficients (highest power first) of the Lagrange polynomials through ``0`` and the
    collocation points (the interpolant of :class:`~invctl.inversion.result.Inverse`)."""
    allt = np.concatenate([[0.0], scheme.tau])
    out = []
    for j in range(allt.size):
        c = np.poly1d([1.0])
        for r in range(allt.size):
            if r != j:
                c *= np.poly1d([1.0, -allt[r]]) / (allt[j] - allt[r])
        out.append(c.coeffs)
    return out


def bernstein_interior(scheme: Scheme) -> np.ndarray:
    """``(d+1, d-1)``: the values of a degree-``d`` polynomial at ``0`` and the collocation points
    (a row) times it give its interior Bernstein coefficients on ``[0, 1]``."""
    from math import comb

    d = scheme.degree
    s = np.concatenate([[0.0], scheme.tau])[:, None]
    i = np.arange(d + 1)[None, :]
    A = np.array([[comb(d, k) for k in range(d + 1)]]) * s ** i * (1 - s) ** (d - i)
    return np.linalg.inv(A).T[:, 1:d]


def coll_points(Xall, sp, bnd, basis, hull=None):
    """Legendre/Radau interval rows: ``X[bnd]`` of the interval's polynomial (values ``Xall`` at 0
    and the collocation points) at the fractions ``sp[q nb:(q + 1) nb]``, ``q < d - 1``, or with
    ``hull`` (:func:`bernstein_interior`) its interior Bernstein coefficients."""
    if hull is not None:
        return ca.vec(ca.mtimes(Xall[bnd, :], ca.DM(hull)))
    nb, out = len(bnd), []
    for q in range(len(basis) - 2):
        s = sp[q * nb:(q + 1) * nb]
        val = 0
        for j, coeffs in enumerate(basis):
            lj = 0
            for a in coeffs:  # Horner
                lj = lj * s + float(a)
            val = val + Xall[bnd, j] * lj
        out.append(val)
    return ca.vertcat(*out) if out else ca.SX(0, 1)


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


#: the names of OCPTranscription.__init__ the structured Hessian (ocp_hessian.py) reads
_HESSIAN_CONTEXT = (
    "nG", "zeta", "tau", "pin", "G", "n_def", "n_ip", "h", "dh", "hs", "nx", "m", "nz_pt", "lin",
    "bnd", "rate_rows", "ipars", "scheme", "d", "N", "npr", "n_el", "flat_pts", "pts_keys", "x",
    "p", "ip", "common", "iv_index", "point_cols", "basis", "hull", "bern",
)


def _structured_hessian(tr):
    from .ocp_hessian import structured_hessian

    return structured_hessian(tr)


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
            interior = "hull" if scheme.is_hs else None
        if interior not in ("hull", "points", None) or (interior is None and scheme.is_hs):
            raise ValueError(f"interior must be 'hull', 'points' (or None for Legendre/Radau), got {interior!r}")
        self.interior = interior
        self.bounded, self.rated = tuple(int(i) for i in bounded), tuple(int(i) for i in rated)
        L = servo.layout
        nx, m, m4 = L.nx, L.m, 4 * L.m
        nth = servo.model.theta.shape[0]
        self.nx, self.m, self.m4, self.ntheta = nx, m, m4, nth
        N = self.N
        hs = scheme.is_hs
        d = 1 if hs else scheme.degree
        self.n_col = 0 if hs else d * N
        self.nY = 2 * N + 1 if hs else d * N
        self.nS = self.nY  # slacks where F is evaluated: nodes + midpoints (HS), collocation points
        ub = L.blocks["u"]
        u_idx = list(range(ub.start, ub.stop))
        rate_rows = [u_idx[i] for i in self.rated]
        bnd = list(self.bounded)
        # interior points per interval (module doc): positions are parameters
        self.n_points = ((2 * len(bnd) + len(rate_rows)) if hs else (d - 1) * len(bnd)) if interior == "points" else 0
        hull = interior == "hull"
        # ---------------------------------------------------------------- global layout
        self.nXs = nx * (N + 1) + nx * self.n_col
        self.nSv = m * self.nS if self.relaxed else 0
        self.i_tau = self.nXs + self.nSv if self.free_time else None
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
        ratio = tau / tau_ref if tau is not None else None

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

        if hs:
            Xa, Xb, Xm = ca.SX.sym("Xa", nx), ca.SX.sym("Xb", nx), ca.SX.sym("Xm", nx)
            Ga, Gb, Gm = ca.SX.sym("Ga", nG), ca.SX.sym("Gb", nG), ca.SX.sym("Gm", nG)
            mid_state = ca.Function("ocp_hs_mid", [Xa, Xb, Ga, Gb] + ipars,
                                    [0.5 * (Xa + Xb) + h / 8 * (Ga[:nx] - Gb[:nx])])
            Fa, Fb, Fm = Ga[:nx], Gb[:nx], Gm[:nx]

            def hs_rows(Xa_, Xb_, Xm_, Fa_, Fb_, Fm_, ra, rm, rb, h_):
                return (Xb_ - Xa_ - h_ / 6 * (Fa_ + 4 * Fm_ + Fb_),
                        ca.vertcat(ca.sqrt(h_ / 6) * ra, ca.sqrt(2 * h_ / 3) * rm, ca.sqrt(h_ / 6) * rb),
                        hs_points(Xa_, Xb_, Fa_, Fb_, Fm_, h_, sp, bnd, rate_rows, hull))

            val = hs_rows(Xa, Xb, Xm, Fa, Fb, Fm, Ga[nx:], Gm[nx:], Gb[nx:], h)
            iv_val = ca.Function("ocp_hs_interval", [Xa, Xb, Xm, Ga, Gb, Gm] + ipars, list(val))
            # chain rule: local variables z = (Xa, Xb, sa, sb, sm, tau)
            JGa, JGb, JGm = (ca.SX.sym(k, nG, nz_pt) for k in ("JGa", "JGb", "JGm"))
            Gta, Gtb, Gtm = (ca.SX.sym(k, nG) for k in ("Gta", "Gtb", "Gtm"))
            dXa, dXb = ca.SX.sym("dXa", nx), ca.SX.sym("dXb", nx)
            dsa, dsb, dsm = (ca.SX.sym(k, m) if self.relaxed else ca.SX(0, 1) for k in ("dsa", "dsb", "dsm"))
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
            dpath = (hs_points(dXa, dXb, dGa[:nx], dGb[:nx], dGm[:nx], h, sp, bnd, rate_rows, hull)
                     + dh * dt * (hs_points(Z, Z, Fa, Fb, Fm, 1, sp, bnd, rate_rows, hull)
                                  - hs_points(Z, Z, Fa, Fb, Fm, 0, sp, bnd, rate_rows, hull)))
            z = ca.vertcat(dXa, dXb, dsa, dsb, dsm, *([dt] if tau is not None else []))
            jins = [Ga, Gb, Gm, JGa, JGb, JGm] + ([Gta, Gtb, Gtm] if tau is not None else []) + ipars
            iv_jac = ca.Function("ocp_hs_interval_jac", jins,
                                 [ca.densify(ca.jacobian(q, z)) for q in (ddef, dR, dpath)])
            ks = np.arange(N)
            iv_index = np.stack([np.concatenate([cols("X", k), cols("X", k + 1)]
                                                + ([cols("S", k), cols("S", k + 1), cols("S", N + 1 + k)]
                                                   if self.relaxed else [])
                                                + ([[self.i_tau]] if tau is not None else [])) for k in ks])
        else:
            Xk, Xk1, Xc, Gc = ca.SX.sym("Xk", nx), ca.SX.sym("Xk1", nx), ca.SX.sym("Xc", nx, d), ca.SX.sym("Gc", nG, d)
            wq = quadrature_weights(scheme)
            Cm, Dm = ca.DM(scheme.C), ca.DM(scheme.D)
            basis = lagrange_basis(scheme) if interior else lagrange_basis(scheme)[:1]
            bern = bernstein_interior(scheme) if hull else None

            def coll_rows(Xk_, Xk1_, Xc_, Fc_, rc, h_):
                Xall = ca.horzcat(Xk_, Xc_)
                return (ca.vertcat(ca.vec(ca.mtimes(Xall, Cm) - h_ * Fc_), Xk1_ - ca.mtimes(Xall, Dm)),
                        ca.vertcat(*[ca.sqrt(h_ * float(wq[q])) * rc[:, q] for q in range(d)]),
                        ca.vertcat(*[Fc_[rate_rows, q] for q in range(d)], coll_points(Xall, sp, bnd, basis, bern)))

            val = coll_rows(Xk, Xk1, Xc, Gc[:nx, :], Gc[nx:, :], h)
            iv_val = ca.Function("ocp_coll_interval", [Xk, Xk1, Xc, Gc] + ipars, list(val))
            JGc, Gtc = ca.SX.sym("JGc", nG, nz_pt * d), ca.SX.sym("Gtc", nG, d)
            dXk, dXk1, dXc = ca.SX.sym("dXk", nx), ca.SX.sym("dXk1", nx), ca.SX.sym("dXc", nx, d)
            dSc = ca.SX.sym("dSc", m, d) if self.relaxed else ca.SX(0, d)
            dt = ca.SX.sym("dt") if tau is not None else ca.SX(0)
            dGc = ca.horzcat(*[lin(JGc[:, q * nz_pt:(q + 1) * nz_pt], Gtc[:, q], ca.vertcat(dXc[:, q], dSc[:, q]), dt)
                               for q in range(d)])
            dall = ca.horzcat(dXk, dXc)
            ddef = ca.vertcat(ca.vec(ca.mtimes(dall, Cm) - h * dGc[:nx, :] - dh * dt * Gc[:nx, :]),
                              dXk1 - ca.mtimes(dall, Dm))
            sq = [ca.sqrt(h * float(wq[q])) for q in range(d)]
            dR = ca.vertcat(*[sq[q] * dGc[nx:, q] + dh * dt * float(wq[q]) / (2 * sq[q]) * Gc[nx:, q]
                              for q in range(d)])
            dpath = ca.vertcat(*[dGc[rate_rows, q] for q in range(d)], coll_points(dall, sp, bnd, basis, bern))
            z = ca.vertcat(dXk, dXk1, ca.vec(dXc), ca.vec(dSc), *([dt] if tau is not None else []))
            jins = [Gc, JGc] + ([Gtc] if tau is not None else []) + ipars
            iv_jac = ca.Function("ocp_coll_interval_jac", jins,
                                 [ca.densify(ca.jacobian(q, z)) for q in (ddef, dR, dpath)])
            ks = np.arange(N)
            iv_index = np.stack([np.concatenate([cols("X", k), cols("X", k + 1)]
                                                + [cols("C", k * d + q) for q in range(d)]
                                                + ([cols("S", k * d + q) for q in range(d)] if self.relaxed else [])
                                                + ([[self.i_tau]] if tau is not None else [])) for k in ks])
        n_def, n_res, n_ip = (int(v.numel()) for v in val)
        self._functions = {"point": pt_val, "point_jac": pt_jac, "interval": iv_val, "interval_jac": iv_jac}
        # compiled derivative functions (never differentiated themselves: they feed the custom
        # Jacobian and Hessians); "auto": only when already in the disk cache
        self._compile_request = compiled
        self.compiled = self._compile_request is True or (
            self._compile_request == "auto" and _all_cached([pt_jac, iv_jac]))
        if self.compiled:
            pt_jac, iv_jac = _compile(pt_jac), _compile(iv_jac)
        # ---------------------------------------------------------------- the MX graph
        x, p = ca.MX.sym("x", self.nX), ca.MX.sym("p", self.np)
        P = {k: p[sl] for k, sl in self._p_slices.items()}
        Ymat = ca.reshape(P["Y"], m4, self.nY)
        Xmesh = ca.reshape(x[:nx * (N + 1)], nx, N + 1)
        Xcol = ca.reshape(x[nx * (N + 1):self.nXs], nx, self.n_col) if self.n_col else None
        S = ca.reshape(x[self.nXs:self.nXs + self.nSv], m, self.nS) if self.relaxed else None
        tau_x = [x[self.i_tau]] if self.free_time else []
        common = tau_x + [P["theta"], P["c"], P["W"], P["w"], P["tau_ref"]]
        ip = [P["h"].T, P["mask"].T] + tau_x + [P["tau_ref"], ca.reshape(P["points"], self.n_points, N)]

        def zeta_of(Xs, a, b):
            return ca.vertcat(Xs, S[:, a:b]) if self.relaxed else Xs

        def graph(jac: bool):
            """(defect, R, interval path, node path) values, or their Jacobian blocks."""
            pt = (pt_jac if jac else pt_val)
            if hs:
                out_n = pt.map(N + 1)(zeta_of(Xmesh, 0, N + 1), Ymat[:, :N + 1], *common)
                Gn = out_n[0] if jac else out_n
                Xm = mid_state.map(N)(Xmesh[:, :N], Xmesh[:, 1:], Gn[:, :N], Gn[:, 1:], *ip)
                out_m = pt.map(N)(zeta_of(Xm, N + 1, 2 * N + 1), Ymat[:, N + 1:], *common)
                if not jac:
                    return iv_val.map(N)(Xmesh[:, :N], Xmesh[:, 1:], Xm, Gn[:, :N], Gn[:, 1:], out_m, *ip), Gn
                JGn, Gm, JGm = out_n[1], out_m[0], out_m[1]
                tin = [out_n[2][:, :N], out_n[2][:, 1:], out_m[2]] if tau is not None else []
                blocks = iv_jac.map(N)(Gn[:, :N], Gn[:, 1:], Gm, JGn[:, :nz_pt * N], JGn[:, nz_pt:], JGm, *tin, *ip)
                return blocks, {"node": out_n, "mid": out_m, "Xm": Xm}
            out_c = pt.map(N * d)(zeta_of(Xcol, 0, N * d), Ymat, *common)
            if not jac:
                return iv_val.map(N)(Xmesh[:, :N], Xmesh[:, 1:], Xcol, out_c, *ip), None
            tin = [out_c[2]] if tau is not None else []
            return iv_jac.map(N)(out_c[0], out_c[1], *tin, *ip), {"col": out_c}

        (defect, resid, ipath), Gn = graph(False)
        (Jdef, JR_blk, Jip), pts = graph(True)
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
            for k in range(N):  # in the order of the interval rows (hs_points, coll_points)
                if not hs:
                    rows += [PathRow("rate", j, "col", k * d + q) for q in range(d) for j in self.rated]
                rows += [PathRow("X", i, "ext", k) for _q in range((2 if hs else d - 1) if interior else 0)
                         for i in bnd]
                if hs:
                    rows += [PathRow("rate", j, "ext", k) for j in self.rated]
            pj.append((*_block_triplets(n_ip, iv_index, base), ca.vec(Jip)))
            base += N * n_ip
        if hs and self.rated:  # rates at the mesh points
            parts.append(ca.vec(Gn[rate_rows, :]))
            rows += [PathRow("rate", j, "mesh", k) for k in range(N + 1) for j in self.rated]
            nidx = np.stack([point_cols(k, k) for k in range(N + 1)])
            pj.append((*_block_triplets(len(rate_rows), nidx, base), ca.vec(pts["node"][1][rate_rows, :])))
            if tau is not None:
                pj.append((base + np.arange((N + 1) * len(rate_rows)), np.full((N + 1) * len(rate_rows), self.i_tau),
                           ca.vec(pts["node"][2][rate_rows, :])))
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
        weight = P["eps"] if self.elastic else P["fscale"]
        f = weight * ca.sumsqr(R)
        if self.free_time:
            f = f + P["fscale"] * P["wT"] * x[self.i_tau]
        if self.elastic:
            f = f + ca.dot(P["relax_w"], x[self.i_r:])
        lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", self.ng)
        ws = ca.substitute(weight, p, ps)
        self._hess_gn = ca.Function("gauss_newton_hess_lag", [xs, ps, lam_f, lam_g],
                                    [ca.triu(2 * lam_f * ws * ca.mtimes(JRs.T, JRs))],
                                    ["x", "p", "lam_f", "lam_g"], ["triu_hess_gamma_x_x"])
        self._residual_fn = ca.Function("ocp_residual", [x, p], [R])

        # the point outputs the exact Hessian needs, as expressions of (x, p)
        if hs:
            on, om = pts["node"], pts["mid"]
            pts_map = {"Gn": on[0], "JGn": on[1], "Gm": om[0], "JGm": om[1], "zn": zeta_of(Xmesh, 0, N + 1),
                       "Yn": Ymat[:, :N + 1], "zm": zeta_of(pts["Xm"], N + 1, 2 * N + 1), "Ym": Ymat[:, N + 1:]}
            if tau is not None:
                pts_map.update({"Gtn": on[2], "Gtm": om[2]})
        else:
            oc = pts["col"]
            pts_map = {"Gc": oc[0], "JGc": oc[1], "zc": zeta_of(Xcol, 0, N * d), "Yc": Ymat}
            if tau is not None:
                pts_map["Gtc"] = oc[2]
        pts_keys, flat_pts = list(pts_map), list(pts_map.values())
        self._hx = SimpleNamespace(**{k: v for k, v in locals().items() if k in _HESSIAN_CONTEXT})
        self._build_exact_hessian = lambda: _structured_hessian(self)
        self.g = self._gfun(x, p)
        self.f = f
        self._plain = (f, g)  # the same NLP without custom derivatives (hessian="exact")
        self._x, self._p = x, p
        self._solvers: dict = {}
        self.build_s = time.perf_counter() - t_build

    def residual(self, x, p) -> np.ndarray:
        """The objective residual ``R`` (``f = scale |R|^2 + ...``)."""
        return np.array(self._residual_fn(x, p)).ravel()

    def g_function(self):
        """``(x, p) -> g`` (with the assembled Jacobian)."""
        return self._gfun

    # ------------------------------------------------------------------ layout
    def sample_times(self, t_mesh) -> np.ndarray:
        """Times of the reference samples (order of ``Y`` and of the slacks): the mesh points,
        then the midpoints (Hermite-Simpson), or the collocation points."""
        t_mesh = np.asarray(t_mesh, float)
        h = np.diff(t_mesh)
        if self.scheme.is_hs:
            return np.concatenate([t_mesh, t_mesh[:-1] + 0.5 * h])
        return (t_mesh[:-1, None] + h[:, None] * self.scheme.tau[None, :]).ravel()

    def collocation_times(self, t_mesh) -> np.ndarray:
        """Times of ``X_col`` (empty for Hermite-Simpson)."""
        return np.zeros(0) if self.scheme.is_hs else self.sample_times(t_mesh)

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
        nb, nr, d = len(self.bounded), len(self.rated), self.scheme.degree
        if self.interior != "points":
            col = []
        elif self.scheme.is_hs:
            col = [1 / 3] * nb + [2 / 3] * nb + [0.5] * nr
        else:
            col = [q / d for q in range(1, d) for _ in range(nb)]
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
        slots = 2 if self.scheme.is_hs else self.scheme.degree - 1
        deriv: list[Any] = []
        if self.scheme.is_hs:
            # coefficients of d/ds of the cubic, per entry: (3 c3, 2 c2, c1) x N
            for i in self.bounded:
                y0, y1 = inv.X_mesh[i, :-1], inv.X_mesh[i, 1:]
                d0, d1 = h * inv.dX_mesh[i, :-1], h * inv.dX_mesh[i, 1:]
                deriv.append(np.array([3 * (2 * y0 + d0 - 2 * y1 + d1), 2 * (-3 * y0 - 2 * d0 + 3 * y1 - d1), d0]))
            ub = self.servo.layout.blocks["u"].start
            for r, j in enumerate(self.rated):
                fa, fb = inv.dX_mesh[ub + j, :-1], inv.dX_mesh[ub + j, 1:]
                b1 = 3 * (inv.X_mesh[ub + j, 1:] - inv.X_mesh[ub + j, :-1]) / h - fa - fb
                den = fa - 2 * b1 + fb
                with np.errstate(divide="ignore", invalid="ignore"):
                    s = np.where(np.abs(den) > 1e-300, (fa - b1) / den, 0.5)
                pts[2 * nb + r] = np.where((s > 0) & (s < 1), s, 0.5)
        else:
            basis = [np.polyder(np.poly1d(c)) for c in lagrange_basis(self.scheme)]
            d = self.scheme.degree
            for i in self.bounded:
                vals = np.vstack([inv.X_mesh[i, :-1]] + [inv.X_col[i, q::d] for q in range(d)])  # (d+1) x N
                coeffs = np.sum([np.outer(np.pad(b.coeffs, (d - 1 - b.order, 0)), vals[j]) for j, b in enumerate(basis)],
                                axis=0)
                deriv.append(coeffs)
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
            self._solvers[key] = ca.nlpsol("servo_ocp", "ipopt", nlp, opts)
        return self._solvers[key]

    def point_values(self, zeta, Ysamples, theta, c, tau=None, tau_ref=1.0) -> np.ndarray:
        """``G = (F, r)`` at points ``zeta = (X, s)`` (columns), e.g. the slopes ``F`` at the mesh
        points for the Hermite-Simpson interpolant (``r`` with unit weights)."""
        k = zeta.shape[1]
        tau = tau_ref if tau is None else tau  # samples given for the actual duration: no retiming
        args = [zeta, Ysamples] + ([tau] if self.free_time else []) + [theta, c, np.ones(self.m), np.ones(3), tau_ref]
        return np.array(self._functions["point"].map(k)(*args))
