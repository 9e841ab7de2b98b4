"""The exact Hessian of the Lagrangian of :class:`~invctl.inversion.ocp.OCPTranscription`, structured.

Every point (mesh point, midpoint, collocation point) contributes ``G = (F, r)``; per interval the
constraint rows and residuals are low-degree formulas in the point outputs, the local states and
``h(tau)``.  The Hessian is then the sum of

* per point, the Hessian of ``w . G`` in ``(zeta, tau)`` with ``w`` the *total* adjoint weight of the
  point's outputs (defect and path multipliers, objective residual, and, through the
  Hermite-Simpson midpoint state ``X_m = (X_a + X_b)/2 + h (F_a - F_b)/8``, the midpoint's weights);
* per interval, the exact second-order expansion of the interval formulas with the point outputs
  replaced by their first-order models (``G + J dzeta + G_tau dtau``), plus the midpoint's point
  Hessian pulled back through ``dzeta_m / dz``.

Checked against CasADi's AD of the whole graph in ``tests/test_ocp.py`` (relative 1e-12).
"""
from __future__ import annotations

import casadi as ca
import numpy as np
from typing import Any

from .assembly import _all_cached, _assembly, _block_triplets, _compile, quadrature_weights
from .ocp import coll_points, hs_points


def structured_hessian(tr) -> ca.Function:
    """``(x, p, lam_f, lam_g) -> triu(Hessian of the Lagrangian)`` of ``tr`` (module doc)."""
    c = tr._hx
    nG = c.nG
    zeta = c.zeta
    tau = c.tau
    pin = c.pin
    G = c.G
    n_def = c.n_def
    n_ip = c.n_ip
    h = c.h
    dh = c.dh
    hs = c.hs
    nx = c.nx
    m = c.m
    nz_pt = c.nz_pt
    lin = c.lin
    bnd = c.bnd
    rate_rows = c.rate_rows
    ipars = c.ipars
    sp = ipars[-1]  # the positions of the interior points
    scheme = c.scheme
    d = c.d
    N = c.N
    npr = c.npr
    n_el = c.n_el
    flat_pts = c.flat_pts
    pts_keys = c.pts_keys
    x = c.x
    p = c.p
    ip = c.ip
    common = c.common
    iv_index = c.iv_index
    point_cols = c.point_cols
    wv = ca.SX.sym("w", nG)
    pvars = ca.vertcat(zeta, tau) if tau is not None else zeta
    npv = int(pvars.numel())
    pt_hess = ca.Function("ocp_point_hess", pin + [wv], [ca.densify(ca.hessian(ca.dot(wv, G), pvars)[0])])
    lam_s, mu_s, fs = ca.SX.sym("lam", n_def), ca.SX.sym("mu", n_ip), ca.SX.sym("fs")
    hd_sym = ca.SX.sym("dt") if tau is not None else ca.SX(0)
    h_d = h + (dh * hd_sym if tau is not None else 0)
    if hs:
        def hull(Xa, Xb, Fa, Fb, Fm, hh):  # the interval's path rows
            return hs_points(Xa, Xb, Fa, Fb, Fm, hh, sp, bnd, rate_rows, c.hull)

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
        wa: Any
        wb: Any
        wm: Any
        wa, wb, wm = (ca.substitute(ca.gradient(PHI, v), dall, ca.DM.zeros(3 * nG)) for v in (dGa, dGb, dGm))
        iv_w = ca.Function("ocp_hs_weights", [Ga_, Gb_, Gm_, JGm_, lam_s, mu_s, fs] + ipars, [wa, wb, wm])
        # second-order expansion in the local variables d
        dXa_, dXb_ = ca.SX.sym("dXa", nx), ca.SX.sym("dXb", nx)
        dsa_, dsb_, dsm_ = (ca.SX.sym(k, m) if tr.relaxed else ca.SX(0, 1) for k in ("dsa", "dsb", "dsm"))
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
        tins: list[Any] = [Gta_, Gtb_, Gtm_] if tau is not None else []
        iv_h = ca.Function("ocp_hs_hess", [Ga_, Gb_, Gm_, JGa_, JGb_, JGm_] + tins + [lam_s, mu_s, fs, Hm_]
                           + ipars, [ca.densify(H2)])
    else:
        Gc_, JGc_, Gtc_ = ca.SX.sym("Gc", nG, d), ca.SX.sym("JGc", nG, nz_pt * d), ca.SX.sym("Gtc", nG, d)
        wq = quadrature_weights(scheme)
        Cm, Dm = ca.DM(scheme.C), ca.DM(scheme.D)
        dGc = ca.SX.sym("dGc", nG, d)

        def coll_phi(Gc_d, hh, dall, dXk1):
            res = ca.mtimes(dall, Cm) - hh * Gc_d[:nx, :]
            PHI = ca.dot(lam_s, ca.vertcat(ca.vec(res), dXk1 - ca.mtimes(dall, Dm)))
            PHI += fs * sum(hh * float(wq[q]) * ca.sumsqr(Gc_d[nx:, q]) for q in range(d))
            return PHI + ca.dot(mu_s, ca.vertcat(*[Gc_d[rate_rows, q] for q in range(d)],
                                                 coll_points(dall, sp, bnd, c.basis, c.bern)))

        PHI = coll_phi(Gc_ + dGc, h, ca.SX.zeros(nx, d + 1), ca.SX.zeros(nx))
        wc = ca.substitute(ca.gradient(PHI, ca.vec(dGc)), ca.vec(dGc), ca.DM.zeros(nG * d))
        iv_w = ca.Function("ocp_coll_weights", [Gc_, lam_s, mu_s, fs] + ipars, [ca.reshape(wc, nG, d)])
        dXk_, dXk1_, dXc_ = ca.SX.sym("dXk", nx), ca.SX.sym("dXk1", nx), ca.SX.sym("dXc", nx, d)
        dSc_ = ca.SX.sym("dSc", m, d) if tr.relaxed else ca.SX(0, d)
        dt_ = hd_sym
        dG2 = ca.horzcat(*[lin(JGc_[:, q * nz_pt:(q + 1) * nz_pt], Gtc_[:, q], ca.vertcat(dXc_[:, q], dSc_[:, q]),
                               dt_) for q in range(d)])
        PHI2 = coll_phi(Gc_ + dG2, h_d, ca.horzcat(dXk_, dXc_), dXk1_)
        zl = ca.vertcat(dXk_, dXk1_, ca.vec(dXc_), ca.vec(dSc_), *([dt_] if tau is not None else []))
        H2 = ca.substitute(ca.hessian(PHI2, zl)[0], zl, ca.DM.zeros(zl.numel()))
        tins = [Gtc_] if tau is not None else []
        iv_h = ca.Function("ocp_coll_hess", [Gc_, JGc_] + tins + [lam_s, mu_s, fs] + ipars, [ca.densify(H2)])
    hfuns = [pt_hess, iv_w, iv_h]
    if tr._compile_request is True or (tr._compile_request == "auto" and _all_cached(hfuns)):
        pt_hess, iv_w, iv_h = (_compile(fn) for fn in hfuns)
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
    sub = ca.substitute([pts_expr for pts_expr in flat_pts], [x, p], [xs2, ps2])
    outs = dict(zip(pts_keys, sub))
    ip2 = ca.substitute(ip, [p, x], [ps2, xs2]) if ip else []
    com2 = ca.substitute(common, [p, x], [ps2, xs2])
    trip_h = []
    if hs:
        Gn_, JGn_, Gm_v, JGm_v = outs["Gn"], outs["JGn"], outs["Gm"], outs["JGm"]
        wa, wb, wm = iv_w.map(N)(Gn_[:, :N], Gn_[:, 1:], Gm_v, JGm_v, lam_def, mu_ip, fsv, *ip2)
        Wn = ca.horzcat(wa, ca.MX.zeros(nG, 1)) + ca.horzcat(ca.MX.zeros(nG, 1), wb)
        if tr.rated:
            mu_n = ca.reshape(path_mult(n_el + N * n_ip, (N + 1) * len(rate_rows)), len(rate_rows), N + 1)
            E = ca.DM(ca.Sparsity.triplet(nG, len(rate_rows), rate_rows, list(range(len(rate_rows)))), 1.0)
            Wn = Wn + ca.mtimes(E, mu_n)
        Hn = pt_hess.map(N + 1)(outs["zn"], outs["Yn"], *com2, Wn)
        Hm: Any = pt_hess.map(N)(outs["zm"], outs["Ym"], *com2, wm)
        tins = [outs["Gtn"][:, :N], outs["Gtn"][:, 1:], outs["Gtm"]] if tau is not None else []
        Hb = iv_h.map(N)(Gn_[:, :N], Gn_[:, 1:], Gm_v, JGn_[:, :nz_pt * N], JGn_[:, nz_pt:], JGm_v, *tins,
                         lam_def, mu_ip, fsv, Hm, *ip2)
        pidx = np.stack([np.concatenate([point_cols(k, k)] + ([[tr.i_tau]] if tau is not None else []))
                         for k in range(N + 1)])
        trip_h += [(pidx, Hn), (iv_index, Hb)]
    else:
        Gc_v, JGc_v = outs["Gc"], outs["JGc"]
        wc = iv_w.map(N)(Gc_v, lam_def, mu_ip, fsv, *ip2)
        Hc = pt_hess.map(N * d)(outs["zc"], outs["Yc"], *com2, wc)
        tins = [outs["Gtc"]] if tau is not None else []
        Hb = iv_h.map(N)(Gc_v, JGc_v, *tins, lam_def, mu_ip, fsv, *ip2)
        pidx = np.stack([np.concatenate([point_cols(j, j, "C")] + ([[tr.i_tau]] if tau is not None else []))
                         for j in range(N * d)])
        trip_h += [(pidx, Hc), (iv_index, Hb)]
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
