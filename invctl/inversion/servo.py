"""The servo-constraint inverse model 003 (35) and its index reduction.

Unknowns ``X = (q, v, lam, mu, u)`` (``2n + l + p + m`` entries, the vector of
003 (36)).  The DAE (35) is

    q' = v,   M v' = f + J^T mu + G^T lam + B u,
    0 = J v + j,   0 = g(q),   0 = h(q) - y_ref(t).

Index reduction (default ``"jerk"``)
------------------------------------
The constraints are differentiated until every unknown has a derivative:
acceleration level ``A(q, v, z, t) = 0`` (``z = (lam, mu, u)``, ``v'`` replaced
by ``a = M^-1 (f + G^T lam + J^T mu + B u)``) and once more,

    dA/dt = A_q v + A_v a + A_z z' + A_t = 0,

which is solvable for ``z'`` because ``A_z = [G; J; h'] M^-1 [G^T J^T B]`` is the
decoupling matrix of the vector relative degree (2, ..., 2) (003 Sect. 2).  The
result is an ODE ``X' = F(X, t)`` in all ``2n + l + p + m`` unknowns, so the
simplified boundary conditions 003 (36) -- exactly that many -- make a square
boundary value problem, the problem a finite-difference BVP code (003 Sect. 4,
Simpson) or ``scipy.integrate.solve_bvp`` solves.  The constraint residuals
at position, velocity and acceleration level are invariants of this ODE up to
a polynomial drift in time whose coefficients are fixed by the boundary
conditions; at the equilibria they vanish, so the solution satisfies (35)
itself.  The residuals are computed and reported after every solve.

``"baumgarte"`` adds ``3w A + 3w^2 Phi_v + w^3 Phi_p`` (double pole for the
non-holonomic rows) to the differentiated constraint, so the drift decays
forward in time at rate ``w`` instead of growing polynomially.  It requires
the selection to fix the constraint modes at ``T0`` (decaying modes cannot be
fixed at ``Tf``); the paper's Sect. 6 selection does not, hence not the default.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import casadi as ca
import numpy as np

from ..errors import ModelError, PositionOutputError, SingularDecouplingError

FORMULATIONS = ("jerk", "baumgarte")


@dataclass(frozen=True)
class Layout:
    """Sizes and names of the unknown vector ``X = (q, v, lam, mu, u)``."""

    n: int
    l: int  # noqa: E741
    p: int
    m: int

    @property
    def nx(self) -> int:
        return 2 * self.n + self.l + self.p + self.m

    @property
    def blocks(self) -> dict[str, slice]:
        n, l, p, m = self.n, self.l, self.p, self.m
        return {"q": slice(0, n), "v": slice(n, 2 * n), "lam": slice(2 * n, 2 * n + l),
                "mu": slice(2 * n + l, 2 * n + l + p), "u": slice(2 * n + l + p, 2 * n + l + p + m)}


class ServoModel:
    """The inverse model 003 (35) of ``model`` as an ODE in ``X`` (see module doc).

    Parameters
    ----------
    model : invctl.model.Model
        A model whose output ``h`` depends on ``q`` only.
    formulation : {"jerk", "baumgarte"}
        Index reduction (module doc).
    omega : float
        Stabilization rate of ``"baumgarte"``.

    Notes
    -----
    All functions take the reference as a column ``Y = (y, y', y'', y''')``
    (``4m`` entries) instead of ``t``, so references enter a transcription as
    numeric samples and changing them does not change any graph.
    """

    def __init__(self, model, formulation: str = "jerk", omega: float = 10.0):
        if formulation not in FORMULATIONS:
            raise ValueError(f"formulation must be one of {FORMULATIONS}, got {formulation!r}")
        if model.ny != model.m:
            raise ModelError(f"model {model.name!r}: servo constraints need as many outputs as inputs "
                             f"(m = {model.m}, outputs = {model.ny})")
        _check_position_output(model)
        self.model = model
        self.formulation = formulation
        self.omega = float(omega)
        self.layout = Layout(model.n, model.ell, model.p, model.m)

    @property
    def names(self) -> dict[str, list[str]]:
        md = self.model
        return {"q": list(md.q_names), "v": [f"{s}_dot" for s in md.q_names],
                "lam": [f"lam{i + 1}" for i in range(md.ell)], "mu": [f"mu{i + 1}" for i in range(md.p)],
                "u": list(md.u_names)}

    @cached_property
    def _sym(self):
        md, L = self.model, self.layout
        X = ca.SX.sym("X", L.nx)
        Y = ca.SX.sym("Y", 4 * L.m)
        b = L.blocks
        q, v, lam, mu, u = (X[b[k]] for k in ("q", "v", "lam", "mu", "u"))
        sub_in = [md.q, md.v]
        sub_out = [q, v]

        def s(e):
            return ca.substitute([ca.SX(e)], sub_in, sub_out)[0]

        M, f, B, G, J, j, h = (s(e) for e in (md.M, md.f, md.B, md.G, md.J, md.j, md.h))
        yr, yd, ydd, yddd = (Y[k * L.m:(k + 1) * L.m] for k in range(4))
        H = ca.jacobian(h, q)
        force = f + ca.mtimes(B, u)
        if L.l:
            force = force + ca.mtimes(G.T, lam)
        if L.p:
            force = force + ca.mtimes(J.T, mu)
        a = ca.solve(M, force)
        # constraint residuals by level (rows: holonomic, non-holonomic, servo)
        phi_p = ca.vertcat(ca.SX(0, 1) if not L.l else s(md.g), h - yr)
        vel_h = ca.mtimes(G, v) if L.l else ca.SX(0, 1)
        vel_n = (ca.mtimes(J, v) + j) if L.p else ca.SX(0, 1)
        vel_s = ca.mtimes(H, v) - yd
        phi_v = ca.vertcat(vel_h, vel_n, vel_s)
        av = ca.SX.sym("av", L.n)

        def d_dt(expr, with_a):  # total time derivative along q' = v, v' = av (y_ref handled by caller)
            out = ca.mtimes(ca.jacobian(expr, q), v)
            if with_a:
                out = out + ca.mtimes(ca.jacobian(expr, v), av)
            return out

        acc_h = d_dt(vel_h, True) if L.l else ca.SX(0, 1)
        acc_n = d_dt(vel_n, True) if L.p else ca.SX(0, 1)
        acc_s = d_dt(ca.mtimes(H, v), True) - ydd
        phi_a_of_av = ca.vertcat(acc_h, acc_n, acc_s)
        phi_a = ca.substitute(phi_a_of_av, av, a)
        z = X[2 * L.n:]
        Az = ca.jacobian(phi_a, z)
        # d/dt phi_a with z' unknown: A_q v + A_v a + A_z z' + A_t
        Yd = ca.vertcat(yd, ydd, yddd, ca.SX.zeros(L.m))
        At = ca.mtimes(ca.jacobian(phi_a, Y), Yd)
        rest = ca.mtimes(ca.jacobian(phi_a, q), v) + ca.mtimes(ca.jacobian(phi_a, v), a) + At
        if self.formulation == "baumgarte":
            w = self.omega
            nh, nn = L.l, L.p
            parts = []
            if nh:
                parts.append(3 * w * phi_a[:nh] + 3 * w**2 * phi_v[:nh] + w**3 * phi_p[:nh])
            if nn:
                parts.append(2 * w * phi_a[nh:nh + nn] + w**2 * phi_v[nh:nh + nn])
            parts.append(3 * w * phi_a[nh + nn:] + 3 * w**2 * phi_v[nh + nn:] + w**3 * phi_p[nh:])
            rest = rest + ca.vertcat(*parts)
        zdot = -ca.solve(Az, rest)
        F = ca.vertcat(v, a, zdot)
        return {"X": X, "Y": Y, "F": F, "a": a, "phi_p": phi_p, "phi_v": phi_v, "phi_a": phi_a, "Az": Az,
                "h": h}

    def _fn(self, name, outs, out_names):
        md, S = self.model, self._sym
        return ca.Function(name, [S["X"], S["Y"], md.theta], outs, ["X", "Y", "theta"], out_names)

    @cached_property
    def rhs(self) -> ca.Function:
        """``(X, Y, theta) -> F``: the index-reduced inverse model ``X' = F``."""
        return self._fn("servo_rhs", [self._sym["F"]], ["F"])

    @cached_property
    def rhs_jac(self) -> ca.Function:
        """``(X, Y, theta) -> (F, dF/dX)`` (dense Jacobian, for assembled Newton steps)."""
        S = self._sym
        return self._fn("servo_rhs_jac", [S["F"], ca.densify(ca.jacobian(S["F"], S["X"]))], ["F", "dFdX"])

    @cached_property
    def residuals(self) -> ca.Function:
        """``(X, Y, theta) -> (pos, vel, acc, dyn)`` constraint residuals of (35) and the
        acceleration level; ``dyn`` is zero by construction (kept for reports)."""
        S = self._sym
        return self._fn("servo_residuals", [S["phi_p"], S["phi_v"], S["phi_a"]], ["pos", "vel", "acc"])

    @cached_property
    def constraint_jacobian(self) -> ca.Function:
        """``(X, Y, theta) -> C``: Jacobian w.r.t. ``X`` of the stacked position, velocity and
        acceleration residuals; its null space is the tangent space of the constraint manifold."""
        S = self._sym
        res = ca.vertcat(S["phi_p"], S["phi_v"], S["phi_a"])
        return self._fn("servo_constraint_jac", [ca.densify(ca.jacobian(res, S["X"]))], ["C"])

    @cached_property
    def output(self) -> ca.Function:
        """``(X, Y, theta) -> y = h(q)``."""
        return self._fn("servo_output", [self._sym["h"]], ["y"])

    @cached_property
    def decoupling(self) -> ca.Function:
        """``(X, Y, theta) -> A_z``: the matrix solved for ``z'`` (must be invertible)."""
        return self._fn("servo_Az", [self._sym["Az"]], ["Az"])

    def reference_samples(self, reference, t) -> np.ndarray:
        """``Y = (y, y', y'', y''')`` at times ``t``: shape ``(4m, len(t))``."""
        t = np.atleast_1d(np.asarray(t, float))
        fn = reference.function(3)
        outs = fn.map(t.size)(t[None, :])
        return np.vstack([np.array(o).reshape(reference.m, t.size) for o in outs])


def _check_position_output(model) -> None:
    """Raise :class:`PositionOutputError` unless every output row is a function of ``q`` alone
    that depends on ``q`` (checked symbolically, before any solve)."""
    bad = []
    for i in range(model.ny):
        hi, name = model.h[i], model.y_names[i]
        if ca.depends_on(hi, model.v):
            bad.append(f"output {name!r} (row {i}) depends on the velocities v")
        elif not ca.depends_on(hi, model.q):
            bad.append(f"output {name!r} (row {i}) does not depend on q (it is constant)")
    if bad:
        raise PositionOutputError(
            f"model {model.name!r}: servo constraints h(q) = y_ref (003 (34)) need outputs that are functions "
            f"of the configuration q: {'; '.join(bad)}. Such an output cannot be prescribed by the inputs "
            "through the configuration; choose a position output (e.g. a coordinate or a point of a body)",
            diagnostics={"outputs": list(model.y_names), "problems": bad})


def check_decoupling(model, Az, times, Q, rcond: float = 1e-10) -> None:
    """Raise :class:`SingularDecouplingError` where the decoupling matrices ``Az`` (shape
    ``(k, k, K)`` at ``times``, configurations ``Q``) are singular (smallest over largest singular
    value below ``rcond``): there the vector relative degree is not (2, ..., 2)."""
    sv = np.linalg.svd(Az.transpose(2, 0, 1), compute_uv=False)
    ratio = sv[:, -1] / np.maximum(sv[:, 0], 1e-300)
    bad = np.flatnonzero(~(ratio >= rcond))
    if bad.size == 0:
        return
    k = bad[0]
    raise SingularDecouplingError(
        f"the decoupling matrix A_z = [G; J; h'(q)] M(q)^-1 [G^T J^T B] of the jerk-level index reduction of "
        f"003 (35) is singular at t = {times[k]:.6g}, q = {np.round(Q[:, k], 6).tolist()} (smallest/largest "
        f"singular value {ratio[k]:.2g}; singular at {bad.size} of {times.size} points of the quasi-static path): "
        f"the vector relative degree of the output(s) {list(model.y_names)} of {model.name!r} is not (2, ..., 2) "
        "there, so the inverse model cannot be solved for the multipliers and inputs. If h'(q) M^-1 B vanishes "
        "identically near this configuration, the output has a higher relative degree (e.g. a flat output, "
        "relative degree 2n: its inverse is algebraic in y_ref and its derivatives, use a flatness-based "
        "feedforward); otherwise the reference passes a singular configuration. Choose another output or a "
        "reference that avoids it",
        diagnostics={"t": float(times[k]), "q": Q[:, k].tolist(), "rcond": float(ratio[k]),
                     "singular_points": int(bad.size)})
