"""Symbolic linear solves with the mass matrix, without forming or differentiating an inverse.

``ca.solve(M, b)`` on SX builds a fresh symbolic QR factorization of ``M`` for every call
(O(n^3) nodes each), and differentiating the result w.r.t. ``q`` differentiates through that
factorization: n directions of O(n^3) nodes, O(n^5) for the second derivatives a Jacobian of
the servo-constraint ODE needs.  :class:`SymmetricSolver` factorizes a symmetric positive
definite ``M = L D L^T`` once (n^3/6 multiply-adds, no square roots, no pivoting: ``M > 0``
keeps ``D > 0``; structural zeros of ``M`` are skipped, so a diagonal ``M`` costs nothing)
and solves any right-hand side with two triangular substitutions (n^2 each).  Derivatives of
solutions are formed by the implicit-function rule instead of AD through the factors:

    d(M^-1 b) = M^-1 (db - dM M^-1 b),

i.e. one more solve with the (shared) factors for the Jacobian ``d(b - M A)/dx`` of the
residual at a frozen ``A = M^-1 b`` (:func:`solve_derivative`).  Expression sizes stay
O(n^2) per right-hand side plus O(n^3) once.
"""
from __future__ import annotations

import casadi as ca


def _is_zero(e) -> bool:
    return e is None or (isinstance(e, ca.SX) and e.is_zero())


class SymmetricSolver:
    """``M^-1 B`` for a symmetric positive definite SX matrix ``M`` by one symbolic LDL^T.

    Only the lower triangle of ``M`` is read.  ``solve(B)`` returns an SX matrix of the shape
    of ``B``; the factors are built once and shared by every call.
    """

    def __init__(self, M):
        M = ca.SX(M)
        n = M.shape[0]
        if M.shape != (n, n):
            raise ValueError(f"SymmetricSolver: M must be square, got shape {M.shape}")
        self.n = n
        L = [[None] * n for _ in range(n)]  # strictly lower part, None = structural zero
        D = [None] * n
        nz = M.sparsity()
        for j in range(n):
            w = [None if _is_zero(L[j][k]) else L[j][k] * D[k] for k in range(j)]
            d = M[j, j]
            for k in range(j):
                if w[k] is not None:
                    d = d - L[j][k] * w[k]
            D[j] = d
            for i in range(j + 1, n):
                s = M[i, j] if nz.has_nz(i, j) else None
                for k in range(j):
                    if w[k] is not None and not _is_zero(L[i][k]):
                        term = L[i][k] * w[k]
                        s = -term if s is None else s - term
                L[i][j] = None if s is None else s / d
        self._L, self._D = L, D
        rows, cols, vals = [], [], []
        for j in range(n):
            for i in range(j, n):
                if i == j or not _is_zero(L[i][j]):
                    rows.append(i)
                    cols.append(j)
                    vals.append(ca.SX(1) if i == j else L[i][j])
        self.L = ca.SX.triplet(rows, cols, ca.vertcat(*vals), n, n)
        self.D = ca.vertcat(*D)
        self._Dinv = ca.diag(1 / self.D)

    def solve(self, B) -> ca.SX:
        """``M^-1 B`` (two triangular substitutions with the shared factors)."""
        B = ca.SX(B)
        if B.shape[0] != self.n:
            raise ValueError(f"SymmetricSolver.solve: B has {B.shape[0]} rows, M is {self.n} x {self.n}")
        if B.shape[1] == 0:
            return ca.SX(self.n, 0)
        Y = ca.solve(self.L, B)                      # forward substitution (L unit lower triangular)
        Y = ca.mtimes(self._Dinv, Y)
        return ca.solve(self.L.T, Y)                 # back substitution


def solve_derivative(solver: SymmetricSolver, residual, frozen, value, x) -> ca.SX:
    """``dA/dx`` of the solution ``A = value`` of ``residual(x, A) = b(x) - M(x) A = 0``.

    ``residual`` is an SX expression in ``x`` and the symbol ``frozen`` (standing for ``A``,
    any shape); returns ``M^-1 d residual/dx`` at ``A = value`` (``numel(A) x numel(x)``, columns
    of ``vec(A)``), the implicit-function rule of the module doc.
    """
    n = solver.n
    dR = ca.jacobian(ca.vec(residual), x)
    dR = ca.substitute(dR, ca.vec(frozen), ca.vec(value)) if ca.depends_on(dR, ca.vec(frozen)) else dR
    cols = frozen.numel() // n
    return ca.vertcat(*[solver.solve(dR[c * n:(c + 1) * n, :]) for c in range(cols)])


class ConstrainedSolver:
    """Solves the KKT system ``[M -C^T; C 0] [a; lam] = [r1; r2]`` of constrained accelerations by
    the Schur complement on the LDL^T factors of ``M`` (``C`` has few rows):
    ``(C M^-1 C^T) lam = r2 - C M^-1 r1``, ``a = M^-1 (r1 + C^T lam)``.  No KKT matrix is factorized."""

    def __init__(self, M, C, solver: SymmetricSolver | None = None):
        self.M = ca.SX(M)
        self.C = ca.SX(C)
        self.mass = solver or SymmetricSolver(self.M)
        self.k = self.C.shape[0]
        if self.k:
            self.S = self.mass.solve(self.C.T)             # M^-1 C^T
            self.schur = ca.mtimes(self.C, self.S)

    def solve(self, r1, r2=None):
        """``(a, lam)`` for right-hand sides ``r1`` (n x c) and ``r2`` (k x c)."""
        a_free = self.mass.solve(r1)
        if not self.k:
            return a_free, ca.SX(0, ca.SX(r1).shape[1])
        lam = ca.solve(self.schur, ca.SX(r2) - ca.mtimes(self.C, a_free))
        return a_free + ca.mtimes(self.S, lam), lam


def constrained_acceleration(M, force, C, bias, solver: SymmetricSolver | None = None):
    """``(a, lam)`` of ``M a = force + C^T lam``, ``C a = bias`` (:class:`ConstrainedSolver`)."""
    return ConstrainedSolver(M, C, solver).solve(force, bias)


def acceleration_function(name, q, v, u, theta, M, force, C, bias) -> ca.Function:
    """``(q, v, u, theta) -> (a, lam)`` of ``M a = force + C^T lam``, ``C a = bias`` with its exact
    Jacobian by the implicit-function rule (custom Jacobian, used by AD of any caller).

    With the residual ``R(x, A, L) = [force - M A + C^T L; bias - C A]`` (``x = (q, v, u, theta)``,
    ``A``, ``L`` frozen) the Jacobian is the KKT solve of ``dR/dx``: O(n^2) per input instead of AD
    through the factors (O(n^3) per input)."""
    solver = ConstrainedSolver(M, C)
    a, lam = solver.solve(force, bias)
    k = solver.k
    A, L = ca.SX.sym("A", a.shape[0]), ca.SX.sym("L", k)
    R1 = force - ca.mtimes(solver.M, A) + (ca.mtimes(solver.C.T, L) if k else 0)
    R2 = ca.SX(bias) - ca.mtimes(solver.C, A)
    ins = [q, v, u, theta]
    frozen, values = ca.vertcat(A, L), ca.vertcat(a, lam)
    blocks = []
    for x in ins:
        d1 = ca.substitute(ca.jacobian(R1, x), frozen, values)
        d2 = ca.substitute(ca.jacobian(R2, x), frozen, values) if k else ca.SX(0, x.numel())
        blocks.append(solver.solve(d1, d2))
    oa, ol = ca.SX.sym("out_a", a.shape[0]), ca.SX.sym("out_lam", k)
    names_in = ["q", "v", "u", "theta"]
    jac = ca.Function(f"jac_{name}", ins + [oa, ol], [b[0] for b in blocks] + [b[1] for b in blocks],
                      names_in + ["out_a", "out_lam"],
                      [f"jac_a_{x}" for x in names_in] + [f"jac_lam_{x}" for x in names_in])
    return ca.Function(name, ins, [a, lam], names_in, ["a", "lam"], {"custom_jacobian": jac, "jac_penalty": 0})
