"""Forward check of an inverse: simulate the model under ``u_ff`` and compare ``y`` with ``y_ref``.

Shares no code with the collocation: the model is integrated as the index-1
ODE of ``model.accel_and_multipliers`` (Baumgarte-stabilized holonomic
constraints) by CasADi's CVODES integrator (BDF, rtol = atol = 1e-12; default
``method="cvodes"``) or by ``scipy.integrate.solve_ivp`` (``method="DOP853"``,
the slower cross-check with a Python right-hand side).

The feedforward enters the compiled integrator as piecewise polynomials: on
every sub-interval of the output grid (which contains the inverse's mesh
points) ``u_ff`` -- read only through the public interpolant ``inverse.u`` --
is a polynomial of degree ``<= 3`` (Hermite-Simpson) or ``d`` (collocation
of degree ``d``), so sampling it at ``deg + 1`` points and solving the
Vandermonde system reproduces it exactly; the coefficients are the
integrator's piecewise-constant controls.  The whole window is one CVODES
call (no Python in the right-hand side): 40-60 ms instead of 0.3-0.4 s
(HS, N = 160).

Why windows
-----------
If the *open-loop* model (the plant under the fixed input ``u_ff``) is
unstable with rate ``r > 0``, any mismatch of the initial state -- rounding,
the integrator's own error -- grows like ``exp(r t)`` and a single forward run
measures that growth, not the inverse.  The check therefore restarts from the
inverse's state every ``ln(max_gain)/r`` seconds (``r`` from the eigenvalues of
the forward ODE linearized at the inverse at ``t0``) and reports the largest
output error over all windows on ``[t0, tf + 10 %]``.  For the manipulator the
open-loop rate is 1.4/s (the 24.4/s of the zero dynamics acts only when the
output is constrained), so one window covers the whole check.
"""
from __future__ import annotations

import math
from collections import OrderedDict

import casadi as ca
import numpy as np
from scipy.integrate import solve_ivp

from ..analysis.auxiliary import cached
from .servo import remember

#: integrators kept per model (one per output grid, the most recently used ones)
INTEGRATORS_KEPT = 32


def _forward_functions(model, alpha: float):
    """The forward ODE's right-hand side, Jacobian and output (kept by the model: they depend on its symbols
    only)."""
    return cached(model, ("forward_functions", float(alpha)), lambda: _make_forward_functions(model, alpha))


def _make_forward_functions(model, alpha: float):
    l = model.ell  # noqa: E741
    q, v = model.q, model.v
    u = ca.SX.sym("u", model.m)
    a, _lam, _mu = model.accel_and_multipliers(q, v, u, model.theta)
    if l and alpha > 0:
        Minv_GT = ca.solve(model.M, model.G.T)
        corr = ca.mtimes(Minv_GT, ca.solve(ca.mtimes(model.G, Minv_GT),
                                           2 * alpha * ca.mtimes(model.G, v) + alpha**2 * model.g))
        a = a - corr
    x = ca.vertcat(q, v)
    rhs = ca.Function("fwd_rhs", [x, u, model.theta], [ca.vertcat(v, a)])
    jac = ca.Function("fwd_jac", [x, u, model.theta], [ca.jacobian(ca.vertcat(v, a), x)])
    out = ca.Function("fwd_y", [x, model.theta], [model.h])
    return rhs, jac, out


def unstable_rate(model, inverse, t: float) -> float:
    """Largest real part of the eigenvalues of the forward ODE linearized at the inverse at ``t``."""
    _rhs, jac, _ = _forward_functions(model, 0.0)
    x = np.concatenate([inverse.q(t).ravel(), inverse.v(t).ravel()])
    A = np.array(jac(x, inverse.u(t).ravel(), model.theta_values))
    return float(max(0.0, np.max(np.linalg.eigvals(A).real)))


def _integrator(model, alpha: float, degree: int, t0: float, grid: tuple, rtol: float, atol: float):
    """The CVODES integrator of one window (kept by the model, the most recent :data:`INTEGRATORS_KEPT`)."""
    memo = cached(model, ("forward_integrators",), OrderedDict)
    return remember(memo, (alpha, degree, t0, grid, rtol, atol),
                    lambda: _make_integrator(model, alpha, degree, t0, grid, rtol, atol), INTEGRATORS_KEPT)


def _make_integrator(model, alpha: float, degree: int, t0: float, grid: tuple, rtol: float, atol: float):
    rhs, _jac, _out = _forward_functions(model, alpha)
    x = ca.SX.sym("x", 2 * model.n)
    t, a, h = ca.SX.sym("t"), ca.SX.sym("a"), ca.SX.sym("h")
    c = ca.SX.sym("c", model.m * (degree + 1))
    th = ca.SX.sym("theta", model.theta.numel())
    C = ca.reshape(c, model.m, degree + 1)
    s = (t - a) / h
    u = C[:, degree]
    for j in range(degree - 1, -1, -1):
        u = C[:, j] + s * u
    dae = {"t": t, "x": x, "u": ca.vertcat(c, a, h), "p": th, "ode": rhs(x, u, th)}
    return ca.integrator("forward_check", "cvodes", dae, t0, list(grid),
                         {"abstol": atol, "reltol": rtol, "linear_multistep_method": "bdf",
                          "max_num_steps": 200000})


def _poly_degree(inverse) -> int | None:
    """Degree of the pieces of ``inverse.u`` between its ``t_mesh`` points (``None``: unknown)."""
    deg = getattr(inverse, "poly_degree", None)
    if deg is not None:
        return int(deg)
    sch = getattr(inverse, "_scheme", None)
    if sch is None or getattr(inverse, "t_mesh", None) is None:
        return None
    return max(1, int(sch.poly_degree))


def _piecewise_controls(inverse, grid: np.ndarray, degree: int) -> np.ndarray:
    """Coefficients ``(c_0..c_deg, a, h)`` of ``u_ff`` on each ``[grid[i], grid[i+1]]``
    in the local variable ``(t - a)/h`` (exact: ``u_ff`` is a polynomial there)."""
    a, h = grid[:-1], np.diff(grid)
    sn = np.linspace(0.0, 1.0, degree + 1)
    U = inverse.u((a[:, None] + h[:, None] * sn[None, :]).ravel())
    m = U.shape[0]
    U = U.reshape(m, a.size, degree + 1).transpose(2, 0, 1).reshape(degree + 1, -1)
    coef = np.linalg.solve(np.vander(sn, degree + 1, increasing=True), U).reshape(degree + 1, m, a.size)
    return np.vstack([coef.reshape((degree + 1) * m, a.size), a[None], h[None]])


def _simulate_window(model, inverse, a, b, x0, th, *, method, rtol, atol, alpha, samples):
    tt = np.linspace(a, b, samples)
    deg = _poly_degree(inverse)
    if method == "cvodes" and deg is not None:
        tm = np.asarray(inverse.t_mesh, float)
        grid = np.unique(np.concatenate([tt, tm[(tm > a) & (tm < b)]]))
        F = _integrator(model, float(alpha), deg, float(a), tuple(grid[1:]), float(rtol), float(atol))
        try:
            res = F(x0=x0, u=_piecewise_controls(inverse, grid, deg), p=th)
        except RuntimeError as exc:
            return None, None, str(exc)
        X = np.hstack([x0[:, None], np.array(res["xf"])])
        keep = np.isin(grid, tt)
        return grid[keep], X[:, keep], None
    if method not in ("cvodes", "DOP853"):
        raise ValueError(f"method must be 'cvodes' or 'DOP853', got {method!r}")
    rhs, _jac, _out = _forward_functions(model, float(alpha))

    def f(t, x):
        return np.array(rhs(x, inverse.u(t).ravel(), th)).ravel()

    sol = solve_ivp(f, (a, b), x0, method="DOP853", rtol=rtol, atol=atol, dense_output=True)
    if not sol.success:
        return None, None, sol.message
    return tt, sol.sol(tt), None


def forward_check(model, inverse, reference, *, t_start: float | None = None, t_end: float | None = None,
                  window: float | None = None, max_gain: float = 1e3, rtol: float = 1e-12, atol: float = 1e-12,
                  alpha: float = 20.0, samples_per_window: int = 200, method: str = "cvodes") -> dict:
    """Simulate ``model`` under ``inverse.u`` window by window (module doc).

    Parameters
    ----------
    inverse : Inverse or duck-typed object
        Needs ``q(t)``, ``v(t)``, ``u(t)``, ``t0``, ``Tf``.  CVODES needs the pieces of
        ``u``: ``t_mesh`` (breakpoints) and the polynomial degree between them (from the
        :class:`Inverse`'s scheme, or an attribute ``poly_degree``); without them the
        check falls back to DOP853.
    method : {"cvodes", "DOP853"}
        CasADi CVODES (BDF) with the compiled right-hand side and the feedforward as
        exact piecewise polynomials (default), or scipy's DOP853 with a Python
        right-hand side calling ``inverse.u(t)`` (slow; an independent cross-check).

    Returns
    -------
    dict
        ``error`` (max ``|y - y_ref|_inf``), ``t_worst``, ``window``, ``windows``,
        ``rate`` (unstable rate used), ``t``, ``y``, ``y_ref`` (sampled), ``method``.
    """
    t_start = inverse.t0 if t_start is None else float(t_start)
    if t_end is None:
        t_end = min(inverse.Tf, reference.tf + 0.1 * (reference.tf - reference.t0))
    rate = unstable_rate(model, inverse, t_start)
    if window is None:
        window = (t_end - t_start) if rate <= 0 else min(t_end - t_start, math.log(max_gain) / rate)
    nwin = max(1, int(math.ceil((t_end - t_start) / window - 1e-9)))
    edges = np.linspace(t_start, t_end, nwin + 1)
    _rhs, _jac, out = _forward_functions(model, float(alpha))
    th = model.theta_values
    ts, ys, yrs = [], [], []
    worst, t_worst = 0.0, t_start
    for a, b in zip(edges[:-1], edges[1:]):
        x0 = np.concatenate([inverse.q(a).ravel(), inverse.v(a).ravel()])
        tt, X, msg = _simulate_window(model, inverse, float(a), float(b), x0, th, method=method, rtol=rtol,
                                      atol=atol, alpha=alpha, samples=samples_per_window)
        if X is None:
            return {"error": math.inf, "t_worst": float(a), "window": window, "windows": nwin, "rate": rate,
                    "message": msg, "method": method, "t": np.zeros(0), "y": np.zeros((model.m, 0)),
                    "y_ref": np.zeros((model.m, 0))}
        y = np.array(out.map(tt.size)(X, th))
        yr = reference(tt)
        err = np.max(np.abs(y - yr), axis=0)
        i = int(np.argmax(err))
        if err[i] > worst:
            worst, t_worst = float(err[i]), float(tt[i])
        ts.append(tt)
        ys.append(y)
        yrs.append(yr)
    used = method if _poly_degree(inverse) is not None else "DOP853"
    return {"error": worst, "t_worst": t_worst, "window": float(window), "windows": nwin, "rate": rate,
            "method": used, "t": np.concatenate(ts), "y": np.hstack(ys), "y_ref": np.hstack(yrs)}
