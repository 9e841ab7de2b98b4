"""The internal-dynamics BVP of the normal-form inversion (003 Sect. 2 and 4, (16), (32)).

At the start and end equilibria the internal dynamics ``eta' = q(y_ref, ..., eta)`` are linearized
(``d eta'/d eta`` through ``Phi^-1`` by implicit functions); eigenvalues on the imaginary axis or unequal
unstable counts mean no exponential dichotomy (:class:`~invctl.errors.NoDichotomyError`).  The
conditions (32), linearized: ``eta(T0) - eta_eq,0`` in the unstable subspace at the start (decaying modes
fixed at ``T0``), ``eta(Tf) - eta_eq,f`` in the stable subspace at the end (growing modes fixed at
``Tf``), as orthogonal-complement rows of ordered real Schur bases.  The horizon comes from the rates of
these modes as in :mod:`.plan` (the same ``_tail_span``: shortest spans with neglected tails below
``tol``, non-normality included); the initial mesh is :func:`.plan.graded_mesh`.

``scipy.integrate.solve_bvp`` (Lobatto IIIA, order 4, residual control and mesh refinement) solves the
BVP: it takes general (non-unit-row) boundary conditions, the unknown is only ``eta``, and it shares no
code with the servo route's collocation, so the two routes check each other.  When the direct solve
fails, the BVP is continued over slower transitions (stretch 4, 2, 1.4, 1), each warm-started from the
last, as the servo route does.
"""
from __future__ import annotations

import math

import casadi as ca
import numpy as np
import scipy.linalg as sla
from scipy.integrate import solve_bvp

from ..errors import CoordinateError, HorizonTooLongError, NoDichotomyError, ReferenceSignalError
from .boundary import neutral_tolerance
from .plan import HORIZON_CAP, _invariant_subspace, _tail_span, graded_mesh

#: order of solve_bvp's collocation (grading of the initial mesh)
ORDER = 4


def samples(reference, t, order: int) -> np.ndarray:
    """``(y, y', ..., y^(order))`` at ``t``: ``((order + 1) m, len(t))``."""
    t = np.atleast_1d(np.asarray(t, float))
    outs = reference.function(order).map(t.size)(t[None, :])
    outs = outs if isinstance(outs, (list, tuple)) else [outs]
    return np.vstack([np.array(o).reshape(reference.m, t.size) for o in outs])


def _linearization(nf, y, eta, guess, theta):
    """``d eta'/d eta`` at rest at output ``y`` and the residual ``|eta'|`` there."""
    m, r = nf.model.ny, nf.r_hat
    Y = np.concatenate([np.ravel(y), np.zeros((r - 1) * m)])[:, None]
    ed, A = nf.eta_jacobian(np.zeros(1), Y, np.asarray(eta, float)[:, None], np.asarray(guess)[:, None], theta)
    return A[0], float(np.max(np.abs(ed))) if nf.dim else 0.0


def _fmt(ev) -> str:
    return ", ".join(f"{z.real:+.4g}{z.imag:+.4g}i" if abs(z.imag) > 1e-12 else f"{z.real:+.4g}" for z in ev) or "none"


def _ends(nf, ops, guess, theta, neutral):
    """Equilibria, eta there, linearizations and the stable/unstable split at both ends."""
    out = []
    for k in (0, -1):
        q = ops.q[k]
        eta = nf.phi(q[:, None], np.zeros((nf.model.n, 1)), theta).ravel()
        A, resid = _linearization(nf, ops.y[k], eta, guess(ops.t[k])[:, 0], theta)
        ev = np.linalg.eigvals(A) if A.size else np.zeros(0)
        out.append({"q": q, "eta": eta, "A": A, "eig": ev, "thr": neutral_tolerance(ev, neutral), "rest": resid})
    return out


def setup_bvp(model, nf, ops, guess, theta, t0, tf, T0, Tf, tol, max_horizon, neutral) -> dict:
    """Stable/unstable split at both ends, horizon and the boundary conditions (32), linearized."""
    dim = nf.dim
    e0, ef = _ends(nf, ops, guess, theta, neutral)
    for e, where in ((e0, "start"), (ef, "end")):
        if e["rest"] > 1e-8 * max(1.0, float(np.max(np.abs(e["eta"])))):
            raise CoordinateError(f"{model.name}: eta' = {e['rest']:.3g} != 0 at the {where} equilibrium; the "
                                  "internal coordinates are not consistent with the model (L_K phi != 0?)")
    ku0 = int(np.sum(e0["eig"].real > e0["thr"]))
    kuf = int(np.sum(ef["eig"].real > ef["thr"]))
    neutral_count = int(np.sum(np.abs(e0["eig"].real) <= e0["thr"]) + np.sum(np.abs(ef["eig"].real) <= ef["thr"]))
    if neutral_count or ku0 != kuf:
        cause = (f"{neutral_count} eigenvalue(s) on the imaginary axis" if neutral_count else
                 f"{ku0} unstable mode(s) at the start but {kuf} at the end")
        raise NoDichotomyError(
            f"{model.name}: no exponential dichotomy of the internal dynamics eta' = q(y_ref, ..., eta): "
            f"eigenvalues {_fmt(e0['eig'])} at the start and {_fmt(ef['eig'])} at the end equilibrium ({cause}), so "
            "there is no bounded stable inverse that settles at both equilibria (003 (32) needs hyperbolic "
            "equilibria with the same split). Choose another output or reference end points",
            diagnostics={"eigenvalues_start": e0["eig"].tolist(), "eigenvalues_end": ef["eig"].tolist()})
    U0, Au = _invariant_subspace(e0["A"], lambda re: re > e0["thr"]) if ku0 else (np.zeros((dim, 0)), np.zeros((0, 0)))
    Sf, As = (_invariant_subspace(ef["A"], lambda re: re < -ef["thr"]) if dim - kuf
              else (np.zeros((dim, 0)), np.zeros((0, 0))))
    tau = tf - t0
    cap = HORIZON_CAP * tau if max_horizon is None else float(max_horizon)
    spans = {}
    for key, M, given, anchor in (("pre", -Au, T0, t0), ("post", As, Tf, tf)):
        if given is not None:
            rate = None if M.size == 0 else float(-np.max(np.linalg.eigvals(M).real))
            spans[key] = (abs(anchor - float(given)), rate, 1.0)
        elif M.size == 0:
            spans[key] = (0.0, None, 1.0)
        else:
            spans[key] = _tail_span(M, tol, cap)
    (pre, rate_pre, k_pre), (post, rate_post, k_post) = spans["pre"], spans["post"]
    T0v = t0 - pre if T0 is None else float(T0)
    Tfv = tf + post if Tf is None else float(Tf)
    if not (T0v <= t0 and Tfv >= tf):
        raise ReferenceSignalError(f"the horizon [T0, Tf] = [{T0v}, {Tfv}] must contain [t0, tf] = [{t0}, {tf}]")
    if Tfv - T0v > cap:
        raise HorizonTooLongError(
            f"{model.name}: the horizon [{T0v:.4g}, {Tfv:.4g}] needed for neglected tails below tol = {tol:.1e} is "
            f"longer than max_horizon = {cap:.4g} s (slowest unstable rate at the start "
            f"{rate_pre if rate_pre is not None else 0:.4g}/s, stable rate at the end "
            f"{rate_post if rate_post is not None else 0:.4g}/s): raise max_horizon or tol, or give T0 and Tf",
            diagnostics={"pre_actuation": pre, "post_actuation": post, "max_horizon": cap})
    W0 = sla.null_space(U0.T) if U0.shape[1] else np.eye(dim)        # W0^T (eta(T0) - eta0) = 0: in span U0
    Wf = sla.null_space(Sf.T) if Sf.shape[1] else np.eye(dim)        # Wf^T (eta(Tf) - etaf) = 0: in span Sf
    tails = {"tail_pre": 0.0 if rate_pre is None else k_pre * math.exp(-rate_pre * pre),
             "tail_post": 0.0 if rate_post is None else k_post * math.exp(-rate_post * post)}
    return {"T0": T0v, "Tf": Tfv, "W0": W0, "Wf": Wf, "eta0": e0["eta"], "etaf": ef["eta"],
            "eigenvalues_start": [[float(z.real), float(z.imag)] for z in e0["eig"]],
            "eigenvalues_end": [[float(z.real), float(z.imag)] for z in ef["eig"]],
            "conditions_start": int(W0.shape[1]), "conditions_end": int(Wf.shape[1]), "rate_pre": rate_pre,
            "rate_post": rate_post, **tails,
            "describe": (f"{W0.shape[1]} condition(s) at T0 = {T0v:.6g} (decaying modes at the start equilibrium), "
                         f"{Wf.shape[1]} at Tf = {Tfv:.6g} (growing modes at the end equilibrium); internal "
                         f"eigenvalues {_fmt(e0['eig'])} / {_fmt(ef['eig'])}")}


def _stretched(reference, s: float):
    """``y_ref`` slowed down by ``s`` (transition ``[t0, t0 + s (tf - t0)]``) and the map of its times
    back to the original ones."""
    t0, tau = reference.t0, reference.tf - reference.t0
    if s == 1.0:
        return reference, (lambda t: np.asarray(t, float))
    from ..reference import Reference

    t = reference.t
    slow = ca.substitute(reference.expr, t, t0 + (t - t0) / s)
    ref = Reference(t, slow, t0, t0 + s * tau, reference.smoothness, reference.name)

    def back(tt):
        tt = np.asarray(tt, float)
        return np.where(tt <= t0, tt, np.where(tt <= t0 + s * tau, t0 + (tt - t0) / s, tt - (s - 1) * tau))

    return ref, back


def _solve_bvp(nf, reference, guess, theta, setup, N, tol, max_nodes, *, stretch=1.0, init=None):
    """The BVP for ``eta`` (``reference`` slowed down by ``stretch``; ``init(t_original) -> eta`` as the
    initial guess, default: ``phi`` along the quasi-static path)."""
    r, dim, n = nf.r_hat, nf.dim, nf.model.n
    W0, Wf, eta0, etaf = setup["W0"], setup["Wf"], setup["eta0"], setup["etaf"]
    ref, back = _stretched(reference, stretch)
    T0, t0, tf = setup["T0"], ref.t0, ref.tf
    Tf = setup["Tf"] + (tf - reference.tf)
    decay = tuple(0.0 if rt is None else rt / (ORDER + 1) for rt in (setup["rate_pre"], setup["rate_post"]))
    mesh = graded_mesh(T0, Tf, t0, tf, int(N), decay)

    def fun(t, eta):
        return nf.eta_dot(t, samples(ref, t, r - 1), eta, guess(back(t)), theta)

    def fun_jac(t, eta):
        return nf.eta_jacobian(t, samples(ref, t, r - 1), eta, guess(back(t)), theta)[1].transpose(1, 2, 0)

    def bc(ya, yb):
        return np.concatenate([W0.T @ (ya - eta0), Wf.T @ (yb - etaf)])

    def bc_jac(ya, yb):
        k0 = W0.shape[1]
        return (np.vstack([W0.T, np.zeros((dim - k0, dim))]), np.vstack([np.zeros((k0, dim)), Wf.T]))

    if init is None:
        G = guess(back(mesh))
        eta_guess = nf.phi(G[:n], G[n:], theta)
    else:
        eta_guess = init(back(mesh))
    sol = solve_bvp(fun, bc, mesh, eta_guess, fun_jac=fun_jac, bc_jac=bc_jac, tol=max(tol, 1e-12),
                    bc_tol=max(tol, 1e-12), max_nodes=int(max_nodes))
    tau, s = reference.tf - reference.t0, stretch

    def on_original(tt):  # the solution as a function of the original times (warm start of the next stretch)
        tt = np.asarray(tt, float)
        fw = np.where(tt <= reference.t0, tt, np.where(tt <= reference.tf, reference.t0 + (tt - reference.t0) * s,
                                                        tt + (s - 1) * tau))
        return sol.sol(np.clip(fw, sol.x[0], sol.x[-1]))

    return sol, on_original


def solve_internal(nf, reference, guess, theta, setup, N, tol, max_nodes):
    """The BVP at once, or by continuation over slower transitions (stretch 4, 2, 1.4, 1, each
    warm-started from the last) when the direct solve fails."""
    steps, first = [], None
    try:
        sol, _ = _solve_bvp(nf, reference, guess, theta, setup, N, tol, max_nodes)
        if sol.status == 0:
            return sol, None
        first = f"solve_bvp: {sol.message}"
    except CoordinateError as exc:
        first = str(exc)
    init, sol = None, None
    for s in (4.0, 2.0, 1.4, 1.0):
        try:
            sol, init = _solve_bvp(nf, reference, guess, theta, setup, N, tol, max_nodes, stretch=s, init=init)
        except CoordinateError as exc:
            raise CoordinateError(f"{exc} (also in the continuation over slower transitions, at stretch {s}; the "
                                  f"direct solve failed: {first[:300]})", diagnostics=exc.diagnostics) from None
        steps.append({"stretch": s, "status": int(sol.status), "nodes": int(sol.x.size)})
        if sol.status != 0 and s != 1.0:
            break
    return sol, {"first_attempt": first, "steps": steps}
