"""Linearizations as python-control ``StateSpace`` objects.

``plant_linearization(model, q0)`` linearizes the multibody DAE 003 (1) at an
equilibrium in minimal coordinates on the constraint manifold

    {(q, v): g(q) = 0,  G(q) v = 0,  J(q) v + j(q) = 0}    (dimension 2n - 2l - p).

The index-1 acceleration ``model.accel_and_multipliers`` keeps this manifold
invariant, so at an equilibrium the Jacobian of ``x' = (v, a(q, v, u))`` maps its
tangent space into itself, and ``(A, B, C, D)`` is that Jacobian restricted to the
tangent space.  The coordinates are ``n - l`` of the ``q`` and ``n - l - p`` of the
``v`` (the dependent ones chosen by pivoted QR of ``G`` and ``[G; J]``), so the
states carry the model's names (``<q name>``, ``<q name>_dot``).

``internal_statespace(lin)`` is the linearized internal dynamics (38),
``eta' = Q eta + P y``, driven by the outputs.

python-control is imported only when a ``StateSpace`` is built (it loads matplotlib).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca
import numpy as np
import scipy.linalg as sla

from ..errors import DimensionError, LinearizationError, ModelError
from .auxiliary import cached

#: Equilibrium and manifold tolerance, relative to the size of the terms (forces, accelerations, q0):
#: the linearization is only as good as the point it is taken at, and AD Jacobians are exact to round-off.
EQUILIBRIUM_TOL = 1e-8


@dataclass(frozen=True)
class PlantLinearization:
    """``x' = A x + B u``, ``y = C x + D u`` of 003 (1) at an equilibrium, in minimal coordinates.

    Attributes
    ----------
    A, B, C, D : ndarray
        The linearization in the coordinates ``states`` (``d = 2n - 2l - p`` of them).
    q0, v0, u0 : ndarray
        The equilibrium and its holding input.
    lam0, mu0 : ndarray
        Multipliers of the holonomic and non-holonomic constraints there.
    basis : ndarray
        ``T`` (2n x d): a perturbation ``z`` of the states is ``(dq, dv) = T z`` (tangent space).
    states, inputs, outputs : tuple of str
        Signal names (``states`` index into ``(q, v)`` through ``independent``).
    independent : tuple of int
        Entries of ``x = (q, v)`` used as states.
    diagnostics : dict
        ``equilibrium_residual`` (max |x'|), ``invariance_residual`` (max |Phi' A_full T|, relative),
        ``manifold_residual`` (max |(g, G v, J v + j)|).
    """

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    q0: np.ndarray
    v0: np.ndarray
    u0: np.ndarray
    lam0: np.ndarray
    mu0: np.ndarray
    basis: np.ndarray
    states: tuple
    inputs: tuple
    outputs: tuple
    independent: tuple
    name: str = ""
    diagnostics: dict = field(default_factory=dict)

    @property
    def nstates(self) -> int:
        return self.A.shape[0]

    def to_statespace(self):
        """The linearization as a named ``control.StateSpace``."""
        import control

        return control.ss(self.A, self.B, self.C, self.D, states=list(self.states), inputs=list(self.inputs),
                          outputs=list(self.outputs), name=self.name)

    def summary(self) -> str:
        ev = np.linalg.eigvals(self.A) if self.nstates else np.zeros(0)
        return (f"{self.name}: {self.nstates} states {list(self.states)}, inputs {list(self.inputs)}, outputs "
                f"{list(self.outputs)}; equilibrium at q = {np.round(self.q0, 6).tolist()}, u = "
                f"{np.round(self.u0, 6).tolist()}; poles {np.round(np.sort_complex(ev), 6).tolist()}")


def _linearization_function(model) -> ca.Function:
    """``(q, v, u, theta)`` -> state derivative, its Jacobians, output Jacobians, constraints (cached)."""

    def build():
        u = ca.SX.sym("u", model.m)
        a, lam, mu = model.accel_and_multipliers(model.q, model.v, u, model.theta)
        x = ca.vertcat(model.q, model.v)
        xdot = ca.vertcat(model.v, a)
        phi = ca.vertcat(model.g, ca.mtimes(model.G, model.v), ca.mtimes(model.J, model.v) + model.j)
        return ca.Function(
            "plant_linearization", [model.q, model.v, u, model.theta],
            [xdot, ca.jacobian(xdot, x), ca.jacobian(xdot, u), ca.jacobian(model.h, x), ca.jacobian(model.h, u),
             phi, ca.jacobian(phi, x), lam, mu],
            ["q", "v", "u", "theta"],
            ["x_dot", "A_full", "B_full", "C_full", "D_full", "phi", "Phi_x", "lam", "mu"])

    return cached(model, ("plant_linearization",), build)


def _vector(model, x, size: int, name: str) -> np.ndarray:
    x = np.asarray(x, float).ravel()
    if x.size != size or not np.all(np.isfinite(x)):
        raise DimensionError(f"{model.name}: {name} must be {size} finite numbers, got {np.round(x, 6).tolist()}")
    return x


def holding_input(model, q0, v0=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """``(u, lam, mu, residual)`` with ``f(q0, v0) + G^T lam + J^T mu + B u = 0`` (least norm).

    The residual is the max-norm of the force balance left over; it is ~0 exactly when
    some input holds the model at rest at ``q0`` (see :func:`plant_linearization`).
    """
    n, l, p, m = model.n, model.ell, model.p, model.m
    q0 = _vector(model, q0, n, "q0")
    v0 = np.zeros(n) if v0 is None else _vector(model, v0, n, "v0")
    f = model.evaluate("f", q0, v0).ravel()
    W = np.hstack([model.evaluate("B", q0), model.evaluate("G", q0).reshape(l, n).T,
                   model.evaluate("J", q0).reshape(p, n).T])
    w = np.linalg.lstsq(W, -f, rcond=None)[0] if W.size else np.zeros(0)
    res = float(np.max(np.abs(W @ w + f))) if n else 0.0
    return w[:m], w[m:m + l], w[m + l:], res


def _dependent(X: np.ndarray, k: int, what: str, model, q0) -> list:
    """The k columns of X (k rows) that pivoted QR selects as a well-conditioned square block."""
    if k == 0:
        return []
    _, R, piv = sla.qr(X, pivoting=True, mode="economic")
    d = np.abs(np.diag(R))
    if d.size < k or d[k - 1] <= 1e-10 * max(d[0], 1.0):
        raise ModelError(f"{model.name}: {what} has rank {int(np.sum(d > 1e-10 * max(d[0], 1.0)))} < {k} at "
                         f"q0 = {np.round(q0, 6).tolist()}; 003 (1) needs independent constraints there")
    return sorted(int(i) for i in piv[:k])


def plant_linearization(model, q0, *, u0=None, v0=None, states=None,
                        tol: float = EQUILIBRIUM_TOL) -> PlantLinearization:
    """Linearize 003 (1) at the equilibrium ``(q0, v0 = 0, u0)`` on the constraint manifold.

    Parameters
    ----------
    model : Model
    q0 : array (n)
        A configuration with ``g(q0) = 0`` and ``j(q0) = 0`` (e.g. from
        :class:`~invctl.analysis.equilibrium.EquilibriumSolver` or :func:`operating_points`).
    u0 : array (m), optional
        Holding input; default: the least-norm solution of the force balance (:func:`holding_input`).
    v0 : array (n), optional
        Velocity of the point (default 0; an equilibrium has ``q' = v0 = 0``).
    states : sequence of str, optional
        The ``2n - 2l - p`` coordinates to use as states, from ``q_names`` and ``<q name>_dot``
        (default: the complement of the dependent coordinates picked by pivoted QR).
    tol : float
        Relative tolerance of the manifold and equilibrium checks (:data:`EQUILIBRIUM_TOL`).

    Raises
    ------
    ModelError
        ``q0`` is off the constraint manifold or the constraints are dependent there.
    LinearizationError
        The point is not an equilibrium (no input holds the model there, ``v0 != 0``, or ``u0``
        does not hold it); the linearization at the point is kept in ``exc.partial``.
    """
    n, l, p, m = model.n, model.ell, model.p, model.m
    if model.ny == 0:
        raise DimensionError(f"{model.name}: the model has no output h; give it one to linearize y = h(q, v)")
    q0 = _vector(model, q0, n, "q0")
    v0 = np.zeros(n) if v0 is None else _vector(model, v0, n, "v0")
    th = model.theta_values
    computed_u = u0 is None
    if computed_u:
        u0, _, _, _ = holding_input(model, q0, v0)
    u0 = _vector(model, u0, m, "u0")
    out = _linearization_function(model)(q=q0, v=v0, u=u0, theta=th)
    xdot, A_full, B_full = (np.array(out[k]) for k in ("x_dot", "A_full", "B_full"))
    C_full, D_full, phi, Phi_x = (np.array(out[k]) for k in ("C_full", "D_full", "phi", "Phi_x"))
    xdot, phi = xdot.ravel(), phi.ravel()
    man = float(np.max(np.abs(phi))) if phi.size else 0.0
    if man > tol * max(1.0, float(np.max(np.abs(q0)))):
        raise ModelError(
            f"{model.name}: (q0, v0) is not on the constraint manifold: max |(g, G v, J v + j)| = {man:.3g} at "
            f"q0 = {np.round(q0, 6).tolist()}; project it with invctl.analysis.consistent_state(model, q0) or find "
            "an equilibrium with invctl.analysis.EquilibriumSolver", diagnostics={"manifold_residual": man})
    # minimal coordinates: dependent q from G (rows of g), dependent v from [G; J] (rows of G v, J v + j)
    names = list(model.q_names) + [f"{s}_dot" for s in model.q_names]
    d = 2 * n - 2 * l - p
    if states is None:
        dep = _dependent(Phi_x[:l, :n], l, "G", model, q0) + \
            [n + i for i in _dependent(Phi_x[l:, n:], l + p, "[G; J]", model, q0)]
        ind = [i for i in range(2 * n) if i not in dep]
    else:
        unknown = [s for s in states if s not in names]
        if unknown or len(set(states)) != len(states) or len(states) != d:
            raise DimensionError(f"{model.name}: states must be {d} = 2n - 2l - p distinct names of {names}, got "
                                 f"{list(states)}" + (f" (unknown: {unknown})" if unknown else ""))
        ind = sorted(names.index(s) for s in states)
        dep = [i for i in range(2 * n) if i not in ind]
    T = np.zeros((2 * n, d))
    T[ind, np.arange(d)] = 1.0
    if dep:
        Pd = Phi_x[:, dep]
        if np.linalg.cond(Pd) > 1e12:
            raise DimensionError(f"{model.name}: the states {[names[i] for i in ind]} are not coordinates of the "
                                 f"constraint manifold at q0 (the remaining {[names[i] for i in dep]} cannot be solved "
                                 "for); choose others or let pivoted QR choose (states=None)")
        T[dep] = -np.linalg.solve(Pd, Phi_x[:, ind])
    A, B = (A_full @ T)[ind], B_full[ind]
    C, D = C_full @ T, D_full
    scale = max(1.0, float(np.max(np.abs(A_full))), float(np.max(np.abs(B_full))) if B_full.size else 1.0)
    inv = float(max(np.max(np.abs(Phi_x @ A_full @ T), initial=0.0), np.max(np.abs(Phi_x @ B_full), initial=0.0)))
    eq = float(np.max(np.abs(xdot))) if xdot.size else 0.0
    # x' is affine in u: compare it with the free and the input-driven parts it balances
    bu = B_full @ u0
    accel_scale = max(1.0, float(np.max(np.abs(xdot - bu), initial=0.0)), float(np.max(np.abs(bu), initial=0.0)))
    lam0, mu0 = np.array(out["lam"]).ravel(), np.array(out["mu"]).ravel()
    lin = PlantLinearization(
        A=A, B=B, C=C, D=D, q0=q0, v0=v0, u0=u0, lam0=lam0, mu0=mu0, basis=T, states=tuple(names[i] for i in ind),
        inputs=tuple(model.u_names), outputs=tuple(model.y_names), independent=tuple(ind), name=model.name,
        diagnostics={"equilibrium_residual": eq, "invariance_residual": inv / scale, "manifold_residual": man})
    if eq > tol * accel_scale:
        raise LinearizationError(
            f"{model.name}: (q0, v0, u0) = ({np.round(q0, 6).tolist()}, {np.round(v0, 6).tolist()}, "
            f"{np.round(u0, 6).tolist()}) is not an equilibrium: max |x'| = {eq:.3g} "
            + ("(v0 != 0 moves q)" if np.any(v0) else "(no input holds the model at rest there)" if computed_u
               else "(u0 does not hold it)")
            + ". A linearization about a non-equilibrium point is not time invariant; find an equilibrium with "
            "EquilibriumSolver / operating_points, or leave u0 unset to compute the holding input",
            partial=lin, diagnostics=lin.diagnostics)
    if inv > 1e-8 * scale:
        raise LinearizationError(
            f"{model.name}: the linearization does not leave the tangent space of the constraint manifold "
            f"invariant (residual {inv / scale:.3g}, relative); the constraint Jacobians are inconsistent with "
            "the index-1 acceleration at this point", partial=lin, diagnostics=lin.diagnostics)
    return lin


def plant_statespace(model, q0, *, u0=None, v0=None, states=None, tol: float = EQUILIBRIUM_TOL):
    """The linearization of :func:`plant_linearization` as a named ``control.StateSpace``.

    States are named like the model's coordinates (``s1``, ``gamma_dot``, ...), inputs
    ``model.u_names``, outputs ``model.y_names``.
    """
    return plant_linearization(model, q0, u0=u0, v0=v0, states=states, tol=tol).to_statespace()


def internal_statespace(lin, *, name: str | None = None):
    """The linearized internal dynamics (38) ``eta' = Q eta + P y`` as a ``control.StateSpace``.

    Input: the outputs ``y`` (named as the model's), output: the state ``eta`` of (38)
    (``eta1``, ...; the ``F``-shifted coordinates ``F0 eta + sum F_i y^(i-1)``).
    Its poles are the eigenvalues of Q, which at an equilibrium are the invariant zeros
    of :func:`plant_statespace` (003 Sect. 2: zero dynamics).
    """
    import control

    Q, P = np.atleast_2d(lin.Q), np.atleast_2d(lin.P)
    d, m = Q.shape[0], P.shape[1]
    model = lin.model
    inputs = list(model.y_names) if model is not None and len(model.y_names) == m else [f"y{i + 1}" for i in range(m)]
    states = [f"eta{i + 1}" for i in range(d)]
    return control.ss(Q, P, np.eye(d), np.zeros((d, m)), states=states, inputs=inputs, outputs=states,
                      name=name or f"{getattr(model, 'name', 'model')}_internal")
