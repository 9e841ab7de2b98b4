"""Stable inversion through the normal form (003 Sect. 2, (10)-(19)), for any uniform relative degree.

The second, independent route to the inverse of 003 (1) (the first is the servo-constraint DAE
(35) of :mod:`invctl.inversion.solver`, which needs the vector relative degree (2, ..., 2)).

Method
------
In the Byrnes-Isidori coordinates (11) of the auxiliary ODE (10),
``Phi(x) = (O1, O2, L_F O2, O3, ..., L_F^(r_hat-1) O3, phi(x)) = (xi, eta)`` with ``L_K phi = 0``
(Lemma 2.1), the constraints are ``O1 = O2 = 0`` and the output is ``O3 = y``, so along
``y = y_ref`` the system (14)/(16) is

    eta' = q(y_ref, ..., y_ref^(r_hat-1), eta) = (L_F phi)(x),   x = Phi^-1(0, y_ref, ..., eta),
    Gamma(x) (mu, lam, u) = (0, 0, y_ref^(r_hat)) - (L_F O1, L_F^2 O2, L_F^r_hat O3)(x).

The internal dynamics are a boundary value problem on ``[T0, Tf]`` with the classical
stable-inversion conditions (32), linearized: ``eta(T0) - eta_eq,0`` lies in the unstable
subspace of the linearization at the start equilibrium (its decaying modes are fixed at ``T0``),
``eta(Tf) - eta_eq,f`` in the stable subspace at the end equilibrium (its growing modes are fixed
at ``Tf``).  The horizon follows from the rates of these modes as in :mod:`.plan` (neglected
tails below ``tol``).  The BVP is solved by ``scipy.integrate.solve_bvp`` (:mod:`.internal_bvp`,
which says why); its right-hand side and Jacobian are mapped CasADi evaluations over all nodes
(:class:`NormalForm`: Newton for ``Phi^-1``, then SX functions of ``x``, composed in numpy).

Then ``x = Phi^-1(0, y_ref, ..., eta)`` and ``(mu, lam, u)`` from the ``r_hat``-th derivative
equation (15) are evaluated on a mesh together with their exact time derivatives (chain rule
through ``Phi^-1``; this needs ``y_ref^(r_hat+1)``: the reference must have ``r_hat + 1``
continuous derivatives), and the :class:`~invctl.inversion.Inverse` is the cubic Hermite
interpolant through them (the form of the Hermite-Simpson scheme), the mesh bisected until the
interpolation error is below ``tol``.  Without internal dynamics (a flat output, ``r_bar = 2n``)
everything is algebraic: ``T0 = t0``, ``Tf = tf``, no pre- or post-actuation.

Before returning, the forward dynamics under the computed ``u`` must reproduce the acceleration
and the multipliers, and the constraints and outputs (position and velocity levels) must hold
between the mesh points; otherwise :class:`~invctl.errors.InversionFailed` with the result in
``partial``.
"""
from __future__ import annotations

import hashlib
import math
import time
from typing import Any

import casadi as ca
import numpy as np

from ..analysis import internal_dynamics, operating_points, relative_degree
from ..analysis.auxiliary import auxiliary_system, cache_of
from ..analysis.internal import _as_expr, xi_expression
from ..analysis.relative_degree import lie_chain
from ..errors import (CoordinateError, InversionFailed, ReferenceSignalError, ReferenceSmoothnessError,
                      RelativeDegreeError, SingularHighGainError)
from .internal_bvp import samples, setup_bvp, solve_internal
from .plan import check_reference
from .result import Inverse

_NEWTON_OPTS = {"abstol": 1e-11, "abstolStep": 1e-14, "max_iter": 100}
#: relative residual of Phi(x) = target above which Phi^-1 counts as failed at a node
_PHI_RESIDUAL = 1e-9
#: Gamma counts as singular where its smallest singular value is below this fraction of the largest
_GAMMA_RCOND = 1e-10
#: mapped Functions kept per normal form (one per function and number of nodes)
_MAP_CACHE = 48


class _PhiInverse:
    """``(target, guess, theta) -> x`` with ``Phi(x) = target``, by Newton from ``guess`` (MX).

    When ``n`` rows of ``Phi`` depend on ``q`` only and the others are affine in ``v``
    (``Phi_v = C(q) v + c(q)``: position outputs with ``r_hat = 2`` and Lemma 3.1/3.2 coordinates, the
    crane's flat output, ...), Newton runs on those ``n`` rows for ``q`` and ``v`` follows from one
    linear solve (as 003 (28)); otherwise Newton runs on all ``2n`` rows.
    """

    def __init__(self, model, Phi):
        n, th = model.n, model.theta
        dep = [ca.depends_on(Phi[i], model.v) for i in range(Phi.shape[0])]
        rq, rv = [i for i, d in enumerate(dep) if not d], [i for i, d in enumerate(dep) if d]
        C = ca.jacobian(Phi[rv], model.v) if rv else ca.SX(0, n)
        self.two_stage = len(rq) == n and not ca.depends_on(C, model.v)
        T, G, TH = ca.MX.sym("target", 2 * n), ca.MX.sym("guess", 2 * n), ca.MX.sym("theta", th.shape[0])
        self.functions = {}
        for plugin in ("fast_newton", "newton"):   # fast (no line search) first, damped Newton where it fails
            opts = {**_NEWTON_OPTS, "error_on_fail": False}
            if self.two_stage:
                tq, tv = ca.SX.sym("target_q", n), ca.SX.sym("target_v", n)
                res = ca.Function("Phi_q_res", [model.q, ca.vertcat(tq, th)], [Phi[rq] - tq])
                rf = ca.rootfinder("Phi_q_inv", plugin, res, opts)
                c = ca.substitute(Phi[rv], model.v, ca.SX.zeros(n))
                vel = ca.Function("Phi_v_inv", [model.q, tv, th], [ca.solve(C, tv - c)])
                q = rf(G[:n], ca.vertcat(T[rq], TH))
                x = ca.vertcat(q, vel(q, T[rv], TH))
            else:
                ts = ca.SX.sym("target", 2 * n)
                res = ca.Function("Phi_res", [ca.vertcat(model.q, model.v), ca.vertcat(ts, th)], [Phi - ts])
                x = ca.rootfinder("Phi_inv", plugin, res, opts)(G, ca.vertcat(T, TH))
            self.functions[plugin] = ca.Function(f"Phi_inverse_{plugin}", [T, G, TH], [x],
                                                 ["target", "guess", "theta"], ["x"])
        target = ca.SX.sym("target", 2 * n)
        self.residual = ca.Function("Phi_residual", [ca.vertcat(model.q, model.v), target, th],
                                    [ca.mmax(ca.fabs(Phi - target)) / ca.fmax(1, ca.mmax(ca.fabs(target)))])


class NormalForm:
    """Compiled functions of the normal form of one model with internal coordinates ``phi``.

    ``Phi^-1`` by Newton (:class:`_PhiInverse`); everything after it is SX of ``x`` and composed in
    numpy at all nodes at once: ``x' = Phi'(x)^-1 d/dt (0, y, ..., y^(r-1), eta)`` (chain rule),
    ``Gamma u_aux = (0, y^(r)) - b`` (15) and its time derivative, ``d eta'/d eta = (L_F phi)'(x)
    Phi'(x)^-1 [0; I]`` (implicit functions).
    """

    def __init__(self, model, phi_expr: ca.SX):
        aux = auxiliary_system(model)
        chain = lie_chain(model)
        xi, out_blocks = xi_expression(model)
        n = model.n
        self.model, self.r_hat, self.dim = model, len(out_blocks), phi_expr.shape[0]
        self.sizes = (n, model.p, model.ell, model.ny)
        x, th = aux.x, model.theta
        Phi = ca.vertcat(xi, phi_expr)
        if Phi.shape[0] != 2 * n:
            raise CoordinateError(f"{model.name}: xi has {xi.shape[0]} rows and phi {self.dim}; together they must "
                                  f"be 2n = {2 * n} coordinates (phi needs 2n - r_bar = {2 * n - xi.shape[0]} rows)")
        inverse = _PhiInverse(model, Phi)
        self.two_stage = inverse.two_stage
        ed = aux.lie_F(phi_expr)                                                    # (16): eta' = L_F phi
        drift = ca.vertcat(*[aux.lie_F(chain.chains[i][-1]) for i in range(aux.n_aux)])
        dPhi = ca.jacobian(Phi, x)
        xd = ca.SX.sym("x_dot", 2 * n)
        self.fns = {
            "state": inverse.functions["fast_newton"], "state_damped": inverse.functions["newton"],
            "state_residual": inverse.residual,
            "phi": ca.Function("phi", [model.q, model.v, th], [phi_expr]),
            "rhs": ca.Function("internal_rhs", [x, th], [ed]),
            "rhs_jac": ca.Function("internal_jac", [x, th], [ed, ca.jacobian(ed, x), dPhi]),
            "core": ca.Function("normal_form_core", [x, th], [ed, dPhi, chain.gamma, drift]),
            "core_dot": ca.Function("normal_form_core_dot", [x, xd, th],
                                    [ca.jtimes(chain.gamma, x, xd), ca.jtimes(drift, x, xd)]),
        }
        self._maps: dict = {}

    def phi(self, q, v, theta):
        """``eta = phi(q, v)`` at the columns of ``q``, ``v``."""
        return self._eval("phi", q, v, theta)[0]

    def _eval(self, name, *args):
        K = args[0].shape[1] if np.ndim(args[0]) == 2 else 1
        key = (name, K)
        if key not in self._maps:
            if len(self._maps) >= _MAP_CACHE:       # solve_bvp changes its mesh: keep the recent sizes only
                self._maps.pop(next(iter(self._maps)))
            self._maps[key] = self.fns[name].map(K)
        args = [np.tile(np.asarray(a, float).reshape(-1, 1), (1, K)) if np.ndim(a) == 1 else a for a in args]
        out = self._maps[key](*args)
        return [np.array(o) for o in (out if isinstance(out, (list, tuple)) else [out])]

    def states(self, t, Y, eta, guess, theta) -> np.ndarray:
        """``x = Phi^-1(0, y, ..., y^(r-1), eta)`` at times ``t`` (``Y``: at least ``r m`` rows)."""
        n, p, l, m = self.sizes
        K = t.size
        target = np.vstack([np.zeros((p + 2 * l, K)), Y[:self.r_hat * m], eta.reshape(self.dim, K)])
        x = self._eval("state", target, guess, theta)[0]
        res = self._eval("state_residual", x, target, theta)[0].ravel()
        bad = np.flatnonzero(~(res <= _PHI_RESIDUAL))
        if bad.size:
            x[:, bad] = self._eval("state_damped", target[:, bad], guess[:, bad], theta)[0]
            res[bad] = self._eval("state_residual", x[:, bad], target[:, bad], theta)[0].ravel()
            still = bad[~(res[bad] <= _PHI_RESIDUAL)]
            if still.size:
                k = still[0]
                raise CoordinateError(
                    f"{self.model.name}: no state x with Phi(x) = (0, y_ref, ..., eta) found at t = {t[k]:.6g} "
                    f"(Newton from q = {np.round(guess[:n, k], 5).tolist()} stopped at relative residual "
                    f"{res[k]:.3g}; {still.size} of {K} points fail): the reference or the internal state leaves the "
                    "domain of the coordinates. Give q_guess on the intended branch, other internal coordinates "
                    "(phi) or a slower reference",
                    diagnostics={"t": float(t[k]), "eta": eta.reshape(self.dim, K)[:, k].tolist(),
                                 "residual": float(res[k]), "failed_points": int(still.size)})
        return x

    def eta_dot(self, t, Y, eta, guess, theta) -> np.ndarray:
        """Right-hand side of the internal dynamics (16) at the nodes: ``(dim, K)``."""
        return self._eval("rhs", self.states(t, Y, eta, guess, theta), theta)[0]

    def eta_jacobian(self, t, Y, eta, guess, theta):
        """``(eta', d eta'/d eta)`` at the nodes; the Jacobian has shape ``(K, dim, dim)``."""
        n, K, d = self.model.n, t.size, self.dim
        ed, dx, dP = self._eval("rhs_jac", self.states(t, Y, eta, guess, theta), theta)
        dP = dP.reshape(2 * n, K, 2 * n).transpose(1, 0, 2)
        dx = dx.reshape(d, K, 2 * n).transpose(1, 0, 2)
        sel = np.zeros((K, 2 * n, d))
        sel[:, 2 * n - d:, :] = np.eye(d)
        return ed, dx @ np.linalg.solve(dP, sel)

    def trajectory(self, t, Y, eta, guess, theta):
        """``X = (q, v, lam, mu, u)``, ``X'`` and Gamma at the nodes (``Y``: ``(r + 2) m`` rows,
        ``y .. y^(r+1)``)."""
        n, p, l, m = self.sizes
        r, K, k = self.r_hat, t.size, p + l + m
        x = self.states(t, Y, eta, guess, theta)
        ed, dP, Gm, b = self._eval("core", x, theta)
        dP = dP.reshape(2 * n, K, 2 * n).transpose(1, 0, 2)
        Gm = Gm.reshape(k, K, k).transpose(1, 0, 2)
        dtarget = np.vstack([np.zeros((p + 2 * l, K)), Y[m:(r + 1) * m], ed.reshape(self.dim, K)])
        xd = np.linalg.solve(dP, dtarget.T[:, :, None])[:, :, 0].T                 # chain rule through Phi^-1
        self._check_gamma(t, x, Gm)
        rhs = np.vstack([np.zeros((p + l, K)), Y[r * m:(r + 1) * m]]) - b
        ua = np.linalg.solve(Gm, rhs.T[:, :, None])[:, :, 0].T                     # (15)
        dG, db = self._eval("core_dot", x, xd, theta)
        dG = dG.reshape(k, K, k).transpose(1, 0, 2)
        drhs = np.vstack([np.zeros((p + l, K)), Y[(r + 1) * m:(r + 2) * m]]) - db
        uad = np.linalg.solve(Gm, (drhs.T - np.einsum("kij,jk->ki", dG, ua))[:, :, None])[:, :, 0].T
        order = list(range(p, p + l)) + list(range(p)) + list(range(p + l, k))    # (mu, lam, u) -> (lam, mu, u)
        return np.vstack([x, ua[order]]), np.vstack([xd, uad[order]]), Gm

    def _check_gamma(self, t, x, Gm):
        sv = np.linalg.svd(Gm, compute_uv=False)
        ratio = sv[:, -1] / np.maximum(sv[:, 0], 1e-300)
        bad = np.flatnonzero(~(ratio > _GAMMA_RCOND))
        if bad.size:
            j, md = bad[0], self.model
            raise SingularHighGainError(
                f"{md.name}: the high-gain matrix Gamma of (10) is singular along the inverse at t = {t[j]:.6g}, "
                f"q = {np.round(x[:md.n, j], 6).tolist()} (smallest/largest singular value {ratio[j]:.2g}, singular "
                f"at {bad.size} of {t.size} points): the relative degree {self.r_hat} of the outputs "
                f"{list(md.y_names)} does not exist there, so (15) cannot be solved for the multipliers and inputs. "
                "Choose another output or a reference that avoids this configuration",
                diagnostics={"t": float(t[j]), "q": x[:md.n, j].tolist(), "rcond": float(ratio[j]),
                             "singular_points": int(bad.size)})


def normal_form(model, phi_expr: ca.SX) -> NormalForm:
    """The cached :class:`NormalForm` of ``model`` with coordinates ``phi_expr`` (symbolic, so shared by
    ``with_params`` copies)."""
    fn = ca.Function("phi_key", [model.q, model.v, model.theta], [phi_expr])
    key = ("normal_form", hashlib.sha1(fn.serialize().encode()).hexdigest())
    cache = cache_of(model)
    if key not in cache:
        cache[key] = NormalForm(model, phi_expr)
    return cache[key]


def _guess_path(model, reference, q_guess, count: int = 41):
    """Equilibria along ``y_ref`` (continuation from ``q_guess``): Newton starts for ``Phi^-1``."""
    ops = operating_points(model, reference, count, guess_q=q_guess)
    tq = ops.t
    V = np.gradient(ops.q, tq, axis=0)

    def guess(t):
        t = np.atleast_1d(t)
        return np.vstack([np.interp(t, tq, col) for col in ops.q.T] + [np.interp(t, tq, col) for col in V.T])

    return ops, guess


def _check_reference(reference, order: int) -> None:
    try:
        reference.require(order, f"normal-form inversion (u needs y_ref^(r_hat), its Hermite slope "
                                 f"y_ref^(r_hat+1); r_hat = {order - 1})")
    except ReferenceSignalError as exc:
        raise ReferenceSmoothnessError(str(exc), diagnostics={"declared": reference.smoothness,
                                                              "needed": order}) from None
    try:
        check_reference(reference, order)
    except ReferenceSmoothnessError as exc:
        j = max(exc.diagnostics.get("jumps", [{}]), key=lambda d: d.get("size", 0.0))
        raise ReferenceSmoothnessError(
            f"{reference.name}: derivative {j.get('order')} jumps by {j.get('size', float('nan')):.3g} at t = "
            f"{j.get('t', float('nan')):.6g} although the reference is declared C^{reference.smoothness}; the "
            f"normal-form inversion needs y_ref and its first {order} derivatives continuous (r_hat + 1 = {order}). "
            "Build it with rest_to_rest/waypoints of that smoothness or declare the smoothness it has",
            diagnostics=exc.diagnostics) from None


def invert_normal_form(model, reference, *, tol: float = 1e-8, N: int = 200, T0: float | None = None,
                       Tf: float | None = None, phi=None, q_guess=None, max_horizon: float | None = None,
                       neutral: float = 1e-6, residual_tol: float = 1e-6, max_nodes: int = 20000,
                       samples: int = 200) -> Inverse:
    """Stable inversion of 003 (1) in Byrnes-Isidori coordinates (003 Sect. 2; module doc).

    Parameters
    ----------
    model : Model
        With as many outputs as inputs and a uniform relative degree ``r_hat`` of the outputs.
    reference : Reference
        ``y_ref``, with ``r_hat + 1`` continuous derivatives (checked).
    tol : float
        Accuracy asked of every approximation: neglected tails at ``T0``/``Tf`` (relative), the
        residual of the internal-dynamics BVP (``solve_bvp``'s ``tol``) and the interpolation error
        of the returned trajectories (relative to each block's largest value).
    N : int
        Intervals of the initial BVP mesh (graded outside ``[t0, tf]``) or, without internal
        dynamics, of the initial mesh of ``[t0, tf]``; both are refined as needed.
    T0, Tf : float, optional
        Horizon; derived from the slowest unstable rate at the start / stable rate at the end
        equilibrium when ``None`` (``t0``/``tf`` for a side without such modes).
    phi : SX or callable ``model -> SX``, optional
        Internal coordinates ``eta = phi(q, v)`` (``2n - r_bar`` rows, ``L_K phi = 0``); default
        Lemma 3.1/3.2 coordinates (position outputs with ``r_hat = 2``); none for a flat output.
    q_guess : array, optional
        Configuration at ``t0`` on the intended branch (start of the equilibrium continuation).
    max_horizon : float, optional
        Cap of ``Tf - T0`` (default ``200 (tf - t0)``).
    neutral : float
        Eigenvalues with ``|Re| <= neutral max(1, |lambda|)`` count as on the imaginary axis.
    residual_tol : float
        Largest accepted residual (constraints and outputs between mesh points, forward dynamics
        against the computed acceleration and multipliers), relative to the signal scales.
    max_nodes : int
        Largest mesh of the BVP and of the returned interpolant.
    samples : int
        Points of the operating region at which the relative degree is checked.

    Returns
    -------
    Inverse
        ``diagnostics["method"] == "normal-form"``, with the horizon, eigenvalues, tails, the BVP's
        report and the residuals.

    Raises
    ------
    RelativeDegreeError
        No uniform relative degree (``SingularHighGainError``: Gamma singular along the inverse).
    ReferenceSmoothnessError, NoDichotomyError, HorizonTooLongError, CoordinateError, InversionFailed
        As named; ``InversionFailed.partial`` holds the result that failed its checks.
    """
    if not 0 < tol < 1:
        raise ValueError(f"invert_normal_form: tol must be in (0, 1), got {tol!r}")
    if isinstance(N, bool) or int(N) != N or N < 2:
        raise ValueError(f"invert_normal_form: N must be an integer >= 2, got {N!r}")
    if not residual_tol > 0:
        raise ValueError(f"invert_normal_form: residual_tol must be positive, got {residual_tol!r}")
    if reference.m != model.ny:
        raise ReferenceSignalError(f"{model.name}: the reference has {reference.m} components, the model "
                                   f"{model.ny} outputs")
    t_start = time.perf_counter()
    theta = model.theta_values
    t0, tf = reference.t0, reference.tf
    if q_guess is not None and np.asarray(q_guess).size != model.n:
        raise ValueError(f"invert_normal_form: q_guess has {np.asarray(q_guess).size} entries, expected n = {model.n}")
    ops, guess = _guess_path(model, reference, q_guess)
    rd = relative_degree(model, samples=samples, points=ops)
    if rd.r_hat is None:
        raise RelativeDegreeError(
            f"{model.name}: the outputs have different relative degrees {list(rd.r_output)}; the normal form "
            "(003 (11)-(16)) needs a common r_hat. Choose outputs of equal relative degree (or a dynamic extension)",
            partial=rd)
    r, dim = rd.r_hat, 2 * model.n - rd.r_bar
    _check_reference(reference, r + 1)
    if dim == 0:
        if phi is not None and _as_expr(model, phi).shape[0]:
            raise CoordinateError(f"{model.name}: r_bar = 2n = {rd.r_bar}, there are no internal dynamics; phi must "
                                  "be empty (leave it None)")
        phi_expr, coords = ca.SX(0, 1), "none (r_bar = 2n: flat output)"
    else:
        idyn = internal_dynamics(model, "sect2", phi, point=ops.q[0], samples=samples,
                                 check_points=[(ops.q[-1], np.zeros(model.n))])
        phi_expr, coords = idyn.phi_expr, idyn.coordinates
    nf = normal_form(model, phi_expr)
    build_s = time.perf_counter() - t_start

    t_solve = time.perf_counter()
    if dim:
        setup = setup_bvp(model, nf, ops, guess, theta, t0, tf, T0, Tf, tol, max_horizon, neutral)
        T0v, Tfv = setup["T0"], setup["Tf"]
        sol, cont = solve_internal(nf, reference, guess, theta, setup, N, tol, max_nodes)
        grid, eta_of = np.union1d(sol.x, [t0, tf]), sol.sol
        bvp = {"status": int(sol.status), "message": sol.message, "iterations": int(sol.niter),
               "nodes": int(sol.x.size), "rms_residual": float(np.max(sol.rms_residuals)) if sol.x.size > 1 else 0.0,
               "continuation": cont}
    else:
        setup = {"describe": "no internal dynamics: algebraic inverse on [t0, tf]"}
        T0v, Tfv = (t0 if T0 is None else float(T0)), (tf if Tf is None else float(Tf))
        if not (T0v <= t0 and Tfv >= tf):
            raise ReferenceSignalError(f"the horizon [T0, Tf] = [{T0v}, {Tfv}] must contain [t0, tf] = [{t0}, {tf}]")
        grid = np.unique(np.concatenate([np.linspace(t0, tf, int(N) + 1), [T0v, Tfv]]))
        eta_of, sol, bvp = (lambda tt: np.zeros((0, np.size(tt)))), None, None
    inv, info = _represent(model, nf, reference, guess, theta, grid, eta_of, tol, max_nodes)
    solve_s = time.perf_counter() - t_solve
    res = _residuals(model, nf, inv, reference, theta, info, sol, setup)
    inv.diagnostics.update({
        "method": "normal-form", "scheme": "hermite-simpson", "representation": "cubic Hermite (values and exact "
        "slopes at the mesh)", "status": "Solve_Succeeded", "success": True,
        "iterations": 0 if bvp is None else bvp["iterations"], "N": inv.N, "r_hat": r, "internal_dim": dim,
        "coordinates": coords, "T0": T0v, "Tf": Tfv, "pre_actuation": t0 - T0v, "post_actuation": Tfv - tf,
        "tol": tol, "bvp": bvp, "residuals": res, "build_s": build_s, "solve_s": solve_s,
        "interpolation_error": info["interpolation_error"], "refinements": info["refinements"],
        "relative_degree": list(rd.r_aux), "horizon": {k: v for k, v in setup.items() if k not in ("W0", "Wf")},
    })
    bad = {k: res[k] for k in ("position", "velocity", "outputs", "dynamics", "multipliers") if res[k] > residual_tol}
    if bvp is not None and bvp["status"] != 0:
        inv.diagnostics.update(status="BVP_Failed", success=False)
        raise InversionFailed(
            f"{model.name}: the internal-dynamics BVP on [{T0v:.4g}, {Tfv:.4g}] was not solved to tol = {tol:.1e} "
            f"(solve_bvp: {bvp['message']}; {bvp['nodes']} nodes, largest rms residual {bvp['rms_residual']:.3g}). "
            "Raise max_nodes, loosen tol, or give a longer horizon; the last iterate is in exc.partial",
            partial=inv, diagnostics=inv.diagnostics)
    if bad or info["interpolation_error"] > tol:
        inv.diagnostics.update(status="Residual_Check_Failed", success=False)
        what = "; ".join(f"{k} {v:.3g}" for k, v in bad.items()) or (
            f"interpolation error {info['interpolation_error']:.3g} > tol = {tol:.1e} at {inv.N} intervals")
        raise InversionFailed(
            f"{model.name}: the normal-form inverse fails its checks ({what}; accepted {residual_tol:.1e}): raise "
            "max_nodes, lower tol, or check the internal coordinates; the result is in exc.partial",
            partial=inv, diagnostics=inv.diagnostics)
    return inv


def _blocks(model) -> dict:
    n, l, p, m = model.n, model.ell, model.p, model.m
    return {"q": slice(0, n), "v": slice(n, 2 * n), "lam": slice(2 * n, 2 * n + l),
            "mu": slice(2 * n + l, 2 * n + l + p), "u": slice(2 * n + l + p, 2 * n + l + p + m)}


def _scales(model, X) -> np.ndarray:
    """Per-entry scale: the largest value of the entry's block (q, v, lam, mu, u) along the inverse."""
    s = np.ones(X.shape[0])
    for sl in _blocks(model).values():
        if sl.stop > sl.start:
            s[sl] = max(float(np.max(np.abs(X[sl]))), 1e-12)
    return s


def _exact(model, nf, reference, guess, theta, t, eta_of):
    X, Xd, _ = nf.trajectory(t, samples(reference, t, nf.r_hat + 1), eta_of(t).reshape(nf.dim, t.size), guess(t),
                             theta)
    return X, Xd


def _hermite(t, ta, tb, Xa, Xb, Da, Db):
    h = tb - ta
    s = (t - ta) / h
    s2, s3 = s * s, s * s * s
    return (Xa * (2 * s3 - 3 * s2 + 1) + Da * (h * (s3 - 2 * s2 + s)) + Xb * (-2 * s3 + 3 * s2)
            + Db * (h * (s3 - s2)))


def _represent(model, nf, reference, guess, theta, grid, eta_of, tol, max_nodes):
    """Values and exact slopes on a mesh, bisected until the Hermite interpolant is within ``tol``."""
    t = np.asarray(grid, float)
    X, Xd = _exact(model, nf, reference, guess, theta, t, eta_of)
    err, rounds = math.inf, 0
    while True:
        mid = 0.5 * (t[:-1] + t[1:])
        Xm, _ = _exact(model, nf, reference, guess, theta, mid, eta_of)
        Xh = _hermite(mid, t[:-1], t[1:], X[:, :-1], X[:, 1:], Xd[:, :-1], Xd[:, 1:])
        scale = _scales(model, X)
        e = np.max(np.abs(Xh - Xm) / scale[:, None], axis=0)
        err = float(e.max()) if e.size else 0.0
        split = np.flatnonzero(e > 0.5 * tol)
        if split.size == 0 or t.size + split.size > max_nodes:
            break
        tn = mid[split]
        Xn, Xdn = _exact(model, nf, reference, guess, theta, tn, eta_of)
        order = np.argsort(np.concatenate([t, tn]), kind="stable")
        t = np.concatenate([t, tn])[order]
        X, Xd = np.hstack([X, Xn])[:, order], np.hstack([Xd, Xdn])[:, order]
        rounds += 1
    sizes = {"n": model.n, "l": model.ell, "p": model.p, "m": model.m}
    names = {"q": list(model.q_names), "v": [f"{s}_dot" for s in model.q_names],
             "lam": [f"lam{i + 1}" for i in range(model.ell)], "mu": [f"mu{i + 1}" for i in range(model.p)],
             "u": list(model.u_names)}
    inv = Inverse("hermite-simpson", t, X, Xd, np.zeros((X.shape[0], 0)), sizes, reference.t0, reference.tf,
                  names, {}, y_ref_fn=reference)
    return inv, {"interpolation_error": err, "refinements": rounds, "guess": guess, "eta_of": eta_of}


def _residuals(model, nf, inv, reference, theta, info, sol, setup) -> dict:
    """Checks before returning (relative to the signal scales): the forward dynamics under ``u``
    against the computed acceleration and multipliers at the mesh; all levels of ``xi`` (constraints
    and output derivatives) of the interpolant between mesh points; the BVP and its boundary conditions."""
    t = inv.t_mesh
    X, Xd = inv.X_mesh, inv.dX_mesh
    b = _blocks(model)
    K = t.size
    fwd = model.accel_and_multipliers.map(K)
    a, lam, mu = (np.array(o) for o in fwd(X[b["q"]], X[b["v"]], X[b["u"]], np.tile(theta[:, None], (1, K))))
    scale = _scales(model, X)
    acc_scale = max(float(np.max(np.abs(Xd[b["v"]]))), 1e-12)
    out: dict[str, Any] = {"dynamics": float(np.max(np.abs(a - Xd[b["v"]]))) / acc_scale,
           "kinematics": float(np.max(np.abs(Xd[b["q"]] - X[b["v"]]) / scale[b["v"], None])),
           "multipliers": max([float(np.max(np.abs(lam - X[b["lam"]]) / scale[b["lam"], None])) if model.ell else 0.0,
                               float(np.max(np.abs(mu - X[b["mu"]]) / scale[b["mu"], None])) if model.p else 0.0])}
    s = np.array([0.25, 0.5, 0.75])
    tt = (t[:-1, None] + np.diff(t)[:, None] * s[None, :]).ravel()
    Xi = inv.X(tt)
    Y = samples(reference, tt, nf.r_hat - 1)
    xi_fn = ca.Function("xi", [model.q, model.v, model.theta], [xi_expression(model)[0]]).map(tt.size)
    xi = np.array(xi_fn(Xi[b["q"]], Xi[b["v"]], np.tile(theta[:, None], (1, tt.size))))
    p, l, m, r = model.p, model.ell, model.ny, nf.r_hat
    cons = xi[:p + 2 * l]
    outs = xi[p + 2 * l:] - Y
    yscale = np.repeat([max(float(np.max(np.abs(Y[k * m:(k + 1) * m]))), 1e-12) for k in range(r)], m)[:, None]
    out["position"] = max(float(np.max(np.abs(xi[p:p + l]))) if l else 0.0, float(np.max(np.abs(outs[:m]))))
    out["velocity"] = max(float(np.max(np.abs(cons[:p]))) if p else 0.0,
                          float(np.max(np.abs(cons[p + l:]))) if l else 0.0)
    levels = np.max(np.abs(outs) / yscale, axis=1).reshape(r, m).max(axis=1)
    out["outputs"] = float(levels[:2].max())          # y and y' (acceptance); higher levels amplify by stiffness
    out["output_levels"] = [float(v) for v in levels]
    out["position_mesh"] = float(np.max(np.abs(np.array(model.function("h").map(K)(
        X[b["q"]], X[b["v"]], np.tile(theta[:, None], (1, K)))) - reference(t))))
    if sol is not None:
        ya, yb = sol.sol(inv.T0), sol.sol(inv.Tf)
        out["boundary"] = float(np.max(np.abs(np.concatenate([setup["W0"].T @ (ya - setup["eta0"]),
                                                                setup["Wf"].T @ (yb - setup["etaf"])]))))
        out["internal_rms"] = float(np.max(sol.rms_residuals)) if sol.x.size > 1 else 0.0
    return out
