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

from .assembly import _all_cached, _assembly, _block_triplets, _compile


def structured_hessian(tr) -> ca.Function:
    """``(x, p, lam_f, lam_g) -> triu(Hessian of the Lagrangian)`` of ``tr`` (module doc)."""
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
