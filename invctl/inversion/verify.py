"""Forward check of an inverse: simulate the model under ``u_ff`` and compare ``y`` with ``y_ref``.

Shares no code with the collocation: the model is integrated as the index-1
ODE of ``model.accel_and_multipliers`` (Baumgarte-stabilized holonomic
constraints) by ``scipy.integrate.solve_ivp`` (DOP853, tight tolerances).

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
from functools import lru_cache

import casadi as ca
import numpy as np
from scipy.integrate import solve_ivp


@lru_cache(maxsize=16)
def _forward_functions(model, alpha: float):
    n, l = model.n, model.ell  # noqa: E741
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


def forward_check(model, inverse, reference, *, t_start: float | None = None, t_end: float | None = None,
                  window: float | None = None, max_gain: float = 1e3, rtol: float = 1e-12, atol: float = 1e-12,
                  alpha: float = 20.0, samples_per_window: int = 200) -> dict:
    """Simulate ``model`` under ``inverse.u`` window by window (module doc).

    Returns
    -------
    dict
        ``error`` (max ``|y - y_ref|_inf``), ``t_worst``, ``window``, ``windows``,
        ``rate`` (unstable rate used), ``t``, ``y``, ``y_ref`` (sampled).
    """
    t_start = inverse.t0 if t_start is None else float(t_start)
    if t_end is None:
        t_end = min(inverse.Tf, reference.tf + 0.1 * (reference.tf - reference.t0))
    rate = unstable_rate(model, inverse, t_start)
    if window is None:
        window = (t_end - t_start) if rate <= 0 else min(t_end - t_start, math.log(max_gain) / rate)
    nwin = max(1, int(math.ceil((t_end - t_start) / window - 1e-9)))
    edges = np.linspace(t_start, t_end, nwin + 1)
    rhs, _jac, out = _forward_functions(model, float(alpha))
    th = model.theta_values
    ts, ys, yrs = [], [], []
    worst, t_worst = 0.0, t_start
    for a, b in zip(edges[:-1], edges[1:]):
        x0 = np.concatenate([inverse.q(a).ravel(), inverse.v(a).ravel()])

        def f(t, x):
            return np.array(rhs(x, inverse.u(t).ravel(), th)).ravel()

        sol = solve_ivp(f, (a, b), x0, method="DOP853", rtol=rtol, atol=atol, dense_output=True)
        if not sol.success:
            return {"error": math.inf, "t_worst": float(a), "window": window, "windows": nwin, "rate": rate,
                    "message": sol.message, "t": np.zeros(0), "y": np.zeros((model.m, 0)),
                    "y_ref": np.zeros((model.m, 0))}
        tt = np.linspace(a, b, samples_per_window)
        X = sol.sol(tt)
        y = np.array(out.map(tt.size)(X, th))
        yr = reference(tt)
        err = np.max(np.abs(y - yr), axis=0)
        i = int(np.argmax(err))
        if err[i] > worst:
            worst, t_worst = float(err[i]), float(tt[i])
        ts.append(tt)
        ys.append(y)
        yrs.append(yr)
    return {"error": worst, "t_worst": t_worst, "window": float(window), "windows": nwin, "rate": rate,
            "t": np.concatenate(ts), "y": np.hstack(ys), "y_ref": np.hstack(yrs)}
