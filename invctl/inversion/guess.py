"""Initial guesses and meshes of the inversion: the quasi-static path along ``y_ref`` (equilibria
with velocities, multipliers and inputs consistent with the motion) and the default meshes."""
from __future__ import annotations

import numpy as np

from .cache import equilibrium_solver as _equilibrium_solver
from .servo import check_decoupling


def quasi_static_guess(model, reference, times, q0=None, *, servo=None, where: str = "", path=None,
                       statics: list | None = None) -> np.ndarray:
    """Quasi-static inverses along ``y_ref``: equilibria at ``times`` (continued from
    ``q0``), with ``v`` and the multipliers/inputs made consistent with the motion.

    ``path``: an earlier result at the same ``times`` (other parameter values); its equilibria
    start one batched Newton solve, and the continuation runs only if a point fails.  ``statics``: a list
    that receives the equilibria ``(q, lam, mu, u)`` at ``times`` (columns) before the motion corrections.

    Raises
    ------
    ReferenceSignalError
        Where no equilibrium exists (reference outside the reachable workspace).
    """
    times = np.asarray(times, float)
    if times.size > 1 and np.any(np.diff(times) <= 1e-9 * (times[-1] - times[0])):
        raise ValueError("quasi_static_guess: times must be strictly increasing and distinct (velocities are "
                         "difference quotients)")
    eq = _equilibrium_solver(model)
    n, l, p, m = model.n, model.ell, model.p, model.m
    ys = reference(times) if servo is None else servo.reference_samples(reference, times)[:reference.m]
    th = model.theta_values

    def continuation(idx, w=None):
        out = []
        for k in idx:
            X, _ = eq.solve(ys[:, k], guess_q=q0 if w is None else None, guess_w=w, theta=th,
                            where=f" at t = {times[k]:.4g}{where}")
            w = np.concatenate([X[:n], X[2 * n:]])
            out.append(w)
        return np.array(out).T

    # continuation (one point after the other) on every 4th point keeps the branch of q0; the
    # points between start from the interpolated path and are solved together (batched Newton)
    W = None
    if path is not None and np.shape(path) == (2 * n + l + p + m, times.size):
        W, res = eq.solve_many(ys, np.vstack([path[:n], path[2 * n:]]), theta=th)
        if np.any(res > 1e-9):
            W = None
    if W is None:
        coarse = np.unique(np.r_[np.arange(0, times.size, 4), times.size - 1])
        Wc = continuation(coarse)
        W0 = np.array([np.interp(times, times[coarse], row) for row in Wc])
        W, res = eq.solve_many(ys, W0, theta=th)
        W[:, coarse] = Wc
        for k in np.flatnonzero(res > 1e-9):  # rare: fall back to continuation from the previous point
            if k not in coarse:
                W[:, k] = continuation([k], W[:, k - 1])[:, 0]
    if statics is not None:
        statics.append(W)
    Q = W[:n]
    V = np.gradient(Q, times, axis=1) if times.size > 2 else np.zeros_like(Q)
    if servo is None:
        return np.vstack([Q, V, W[n:]])
    # multipliers and inputs from the acceleration-level servo constraints at (q, v): A(q, v, z) = 0
    X = np.vstack([Q, V, np.zeros((l + p + m, times.size))])
    Y = servo.reference_samples(reference, times)
    th = model.theta_values
    _pos, _vel, acc = servo.maps.buffered_map(servo.evaluator("residuals"), times.size, once=(2,))(X, Y, th)
    Az = servo.maps.buffered_map(servo.evaluator("decoupling"), times.size, once=(2,))(X, Y, th)[0].reshape(
        l + p + m, l + p + m, times.size, order="F")
    check_decoupling(model, Az, times, Q, maps=servo.maps)
    Z = np.linalg.solve(Az.transpose(2, 0, 1), -acc.T[:, :, None])[:, :, 0].T
    return np.vstack([Q, V, Z])


def _split(N, lengths, weights):
    """Integers >= 1 (for positive lengths) summing to N, proportional to weights."""
    idx = [i for i, L in enumerate(lengths) if L > 1e-12]
    w = np.array([weights[i] for i in idx], float)
    raw = N * w / w.sum()
    n = np.maximum(1, np.floor(raw).astype(int))
    while n.sum() < N:
        n[np.argmax(raw - n)] += 1
    while n.sum() > N:
        n[np.argmax(n)] -= 1
    out = [0] * len(lengths)
    for i, k in zip(idx, n):
        out[i] = int(k)
    return out


def default_mesh(T0, Tf, t0, tf, N, fraction=0.5):
    """Piecewise-uniform mesh of ``[T0, Tf]`` with ``t0``, ``tf`` as mesh points and
    ``fraction`` of the ``N`` intervals on ``[t0, tf]`` (the rest by length)."""
    knots = [T0, max(T0, t0), min(Tf, tf), Tf]
    lengths = np.diff(knots)
    side = lengths[0] + lengths[2]
    weights = [(1 - fraction) * lengths[0] / side if side > 0 else 0, fraction,
               (1 - fraction) * lengths[2] / side if side > 0 else 0]
    counts = _split(N, lengths, weights)
    parts = [np.linspace(a, b, k + 1)[:-1] for a, b, k in zip(knots[:-1], knots[1:], counts) if k > 0]
    return np.concatenate(parts + [[Tf]])
