"""Invariant, transmission and decoupling zeros of a linear system, and their classification.

Invariant zeros are the finite ``s`` where the Rosenbrock system matrix

    R(s) = [A - s I, B; C, D]

loses rank; they are the finite generalized eigenvalues of the pencil
``([A B; C D], [I 0; 0 0])``.  The pencil's infinite eigenvalues of higher order
(relative degree >= 2) make plain QZ return spurious large "finite" values, so
the system is first reduced (Emami-Naeini and Van Dooren, Automatica 18 (1982))
to one with the same finite zeros and an invertible ``D``; QZ on that pencil is
reliable.  Everything here is scipy/numpy; python-control is not needed.

* transmission zeros: invariant zeros of the minimal (controllable and observable)
  part, found by orthogonal staircase (Krylov) bases;
* input-decoupling zeros: eigenvalues of the uncontrollable part
  (PBH: ``rank [A - s I, B] < n``); output-decoupling zeros: of the unobservable part
  (``rank [A - s I; C] < n``).

At an equilibrium the eigenvalues of the linearized internal dynamics (003 Sect. 2/3)
are the invariant zeros of the plant; :func:`classify_zeros` says which are
transmission zeros (they decide minimum phase) and which only decoupling zeros
(modes the input cannot move or the output cannot see, e.g. the knife edge's
lateral position).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
from scipy.optimize import linear_sum_assignment

from ..errors import CoordinateError, DimensionError, ZeroError

#: Rank decisions (staircase, reduction, PBH) count a singular value as zero below ``ZERO_TOL``
#: times the norm of the system matrix.  The linearizations are exact to round-off (1e-16
#: relative), structural decoupling gives singular values at that level, and simple zeros are
#: computed to ~1e-14; 1e-8 keeps six orders of margin to both.
ZERO_TOL = 1e-8
#: Two zeros are the same when they differ by less than ``MATCH_TOL * max(1, |z|)``: a double
#: zero is only determined to ~sqrt(eps) = 1.5e-8 by any method.
MATCH_TOL = 1e-6


def system_matrices(sys) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(A, B, C, D)`` of a ``control.StateSpace``, a :class:`PlantLinearization` or a 4-tuple (checked)."""
    if isinstance(sys, (tuple, list)) and len(sys) == 4:
        A, B, C, D = sys
    elif all(hasattr(sys, k) for k in "ABCD"):
        A, B, C, D = sys.A, sys.B, sys.C, sys.D
    else:
        raise DimensionError(f"expected a state-space system (A, B, C, D), got {type(sys).__name__}")
    shapes = [np.shape(X) for X in (A, B, C, D)]
    try:
        A = np.atleast_2d(np.asarray(A, float)) if np.size(A) else np.zeros((0, 0))
        n = A.shape[0]
        B = np.asarray(B, float).reshape(n, -1)
        C = np.asarray(C, float).reshape(-1, n) if n else np.zeros((np.shape(D)[0] if np.ndim(D) == 2 else 0, 0))
        m, p = B.shape[1], C.shape[0]
        D = np.asarray(D, float).reshape(p, m) if np.size(D) else np.zeros((p, m))
        ok = A.shape == (n, n) and all(np.all(np.isfinite(X)) for X in (A, B, C, D))
    except (ValueError, TypeError):
        ok = False
    if not ok:
        raise DimensionError(f"inconsistent or non-finite state-space matrices: shapes of A, B, C, D are {shapes} "
                             "(need n x n, n x m, p x n, p x m)")
    return A, B, C, D


def _scale(A, B, C, D) -> float:
    S = np.block([[A, B], [C, D]]) if A.size or D.size else np.zeros((1, 1))
    s = float(np.linalg.norm(S, 2)) if S.size else 0.0
    return s if s > 0 else 1.0


def _orth(X: np.ndarray, atol: float) -> np.ndarray:
    if X.size == 0:
        return np.zeros((X.shape[0], 0))
    U, s, _ = np.linalg.svd(X, full_matrices=False)
    return U[:, s > atol]


def controllable_subspace(A, B, *, atol: float) -> np.ndarray:
    """Orthonormal basis of ``im [B, A B, A^2 B, ...]`` (orthogonal staircase: each new block is
    ``A`` times the last, orthogonalized twice against the basis, its rank by SVD with ``atol``)."""
    n = A.shape[0]
    basis = _orth(B, atol)
    new = basis
    while new.shape[1] and basis.shape[1] < n:
        X = A @ new
        for _ in range(2):
            X = X - basis @ (basis.T @ X)
        new = _orth(X, atol)
        basis = np.hstack([basis, new])
    return basis[:, :n]


def _complement(V: np.ndarray, n: int) -> np.ndarray:
    return sla.null_space(V.T) if V.shape[1] else np.eye(n)


def _reduce(A, B, C, D, atol):
    """Same finite zeros, ``D`` of full row rank (Emami-Naeini and Van Dooren's reduction).

    Row-compress ``D``; the output rows without feedthrough, ``y2 = C2 x``, fix the part
    ``z2`` of the state that ``C2`` sees (rank rho), so the rows of ``z2`` in ``R(s)`` become
    output rows without ``s``: ``A <- A11``, ``B <- B1``, ``C <- [A21; C1]``, ``D <- [B2; D1]``
    in coordinates ``x = [V_ker, V_row] z``.  Each step removes rho >= 1 states or rows of
    ``R(s)`` that are identically zero after the (unimodular) eliminations; returns the reduced
    system and the number of such rows (> 0 means the normal rank is not full).
    """
    dropped = 0
    while True:
        n = A.shape[0]
        p = D.shape[0]
        if p == 0:
            return (A, B, C, D), dropped
        U, s, _ = np.linalg.svd(D)
        r = int(np.sum(s > atol))
        if r == p:
            return (A, B, C, D), dropped
        Cr, Dr = U.T @ C, U.T @ D
        C1, D1, C2 = Cr[:r], Dr[:r], Cr[r:]
        _, s2, Vt = np.linalg.svd(C2) if n else (None, np.zeros(0), np.zeros((0, 0)))
        rho = int(np.sum(s2 > atol))
        dropped += p - r - rho
        if rho == 0:
            C, D = C1, D1
            continue
        T = np.hstack([Vt[rho:].T, Vt[:rho].T])
        At, Bt, Ct = T.T @ A @ T, T.T @ B, C1 @ T
        k = n - rho
        A, B = At[:k, :k], Bt[:k]
        C, D = np.vstack([At[k:, :k], Ct[:, :k]]), np.vstack([Bt[k:], D1])


def invariant_zeros(sys, *, tol: float = ZERO_TOL) -> np.ndarray:
    """Invariant zeros of a square system: finite generalized eigenvalues of the Rosenbrock pencil.

    Returns the zeros (complex, with multiplicity) sorted by real, then imaginary part.

    Raises
    ------
    ZeroError
        If the system is not square or its system matrix is rank deficient for all ``s``
        (e.g. an output that is a combination of others): zeros are not defined by a pencil then.
    """
    A, B, C, D = system_matrices(sys)
    p, m = D.shape
    if p != m:
        raise ZeroError(f"invariant_zeros needs a square system (as many outputs as inputs), got {p} outputs and "
                        f"{m} inputs")
    atol = tol * _scale(A, B, C, D)
    (A1, B1, C1, D1), drop1 = _reduce(A, B, C, D, atol)
    (At, Ct, Bt, Dt), drop2 = _reduce(A1.T, C1.T, B1.T, D1.T, atol)
    A2, B2, C2, D2 = At.T, Bt.T, Ct.T, Dt.T
    n2, (p2, m2) = A2.shape[0], D2.shape
    if drop1 or drop2 or p2 != m2 or (m2 and np.linalg.svd(D2, compute_uv=False)[-1] <= atol):
        raise ZeroError(f"the system matrix [A - sI, B; C, D] is rank deficient for every s (normal rank below "
                        f"n + m = {A.shape[0] + m}; reduced to {p2} x {m2} feedthrough): the transfer matrix is "
                        "singular, so its zeros are not isolated. Check for dependent outputs or inputs",
                        diagnostics={"reduced_states": n2, "reduced_shape": (p2, m2)})
    if n2 == 0:
        return np.zeros(0, complex)
    L = np.block([[A2, B2], [C2, D2]])
    M = np.zeros_like(L)
    M[:n2, :n2] = np.eye(n2)
    ab = sla.eig(L, M, right=False, homogeneous_eigvals=True)
    alpha, beta = ab[0], ab[1]
    # with D invertible the pencil has exactly n2 finite eigenvalues: keep the n2 largest |beta|
    keep = np.argsort(-np.abs(beta) / np.maximum(np.hypot(np.abs(alpha), np.abs(beta)), 1e-300))[:n2]
    return _sort(alpha[keep] / beta[keep])


def _sort(z) -> np.ndarray:
    z = np.asarray(z, complex)
    z = np.where(np.abs(z.imag) <= 1e-14 * np.maximum(1.0, np.abs(z)), z.real + 0j, z)
    return z[np.lexsort((z.imag, z.real))]


def kalman_parts(sys, *, tol: float = ZERO_TOL) -> dict:
    """Controllable/observable structure of ``(A, B, C)`` by orthogonal staircase bases.

    Returns a dict with ``controllable`` (basis), ``unobservable`` (basis), ``minimal``
    (``(A, B, C, D)`` of the controllable and observable part), ``input_decoupling``
    (eigenvalues of ``A`` on the quotient by the controllable subspace) and
    ``output_decoupling`` (eigenvalues of ``A`` on the unobservable subspace).
    """
    A, B, C, D = system_matrices(sys)
    n = A.shape[0]
    atol = tol * _scale(A, B, C, D)
    Vc = controllable_subspace(A, B, atol=atol)
    Wc = _complement(Vc, n)
    Vo = controllable_subspace(A.T, C.T, atol=atol)
    N = _complement(Vo, n)
    Ac, Bc, Cc = Vc.T @ A @ Vc, Vc.T @ B, C @ Vc
    Vo_c = controllable_subspace(Ac.T, Cc.T, atol=atol)
    minimal = (Vo_c.T @ Ac @ Vo_c, Vo_c.T @ Bc, Cc @ Vo_c, D)
    return {
        "controllable": Vc, "unobservable": N, "minimal": minimal,
        "input_decoupling": _sort(np.linalg.eigvals(Wc.T @ A @ Wc)) if Wc.shape[1] else np.zeros(0, complex),
        "output_decoupling": _sort(np.linalg.eigvals(N.T @ A @ N)) if N.shape[1] else np.zeros(0, complex),
        "invariance_residual": float(max(np.max(np.abs(Wc.T @ A @ Vc), initial=0.0),
                                         np.max(np.abs(Vo.T @ A @ N), initial=0.0)) / _scale(A, B, C, D)),
    }


def minimal_realization(sys, *, tol: float = ZERO_TOL) -> tuple:
    """``(A, B, C, D)`` of the controllable and observable part (same transfer matrix)."""
    return kalman_parts(sys, tol=tol)["minimal"]


def transmission_zeros(sys, *, tol: float = ZERO_TOL) -> np.ndarray:
    """Transmission zeros: the invariant zeros of the minimal realization (zeros of the transfer matrix)."""
    return invariant_zeros(minimal_realization(sys, tol=tol), tol=tol)


def match(a, b) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pair the entries of ``a`` and ``b`` (optimal assignment); returns ``(ia, ib, distance)``,
    distance relative to ``max(1, |a|)``."""
    a, b = np.asarray(a, complex).ravel(), np.asarray(b, complex).ravel()
    if not (a.size and b.size):
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    cost = np.abs(a[:, None] - b[None, :]) / np.maximum(1.0, np.abs(a))[:, None]
    ia, ib = linear_sum_assignment(cost)
    return ia, ib, cost[ia, ib]


def pbh(A, B, C, s, scale) -> tuple[float, float]:
    """Smallest singular values of ``[A - sI, B]`` and ``[A - sI; C]``, divided by ``scale``."""
    n = A.shape[0]
    As = A - s * np.eye(n)
    si = np.linalg.svd(np.hstack([As, B]), compute_uv=False)
    so = np.linalg.svd(np.vstack([As, C]), compute_uv=False)
    return float(si[n - 1] if si.size >= n else 0.0) / scale, float(so[n - 1] if so.size >= n else 0.0) / scale


@dataclass(frozen=True)
class ZeroReport:
    """Invariant zeros of a linearization and what kind each is.

    Attributes
    ----------
    invariant : ndarray
        All invariant zeros (Rosenbrock), sorted.
    kinds : tuple of str
        Per invariant zero: ``"transmission"``, ``"input decoupling"`` (uncontrollable mode),
        ``"output decoupling"`` (unobservable mode) or ``"input-output decoupling"`` (both;
        PBH tests at the value).
    transmission : ndarray
        Zeros of the transfer matrix (invariant zeros of the minimal realization).
    input_decoupling, output_decoupling : ndarray
        Eigenvalues of the uncontrollable / unobservable part (with multiplicity; a mode that
        is both appears in both).
    pbh_input, pbh_output : ndarray
        Per invariant zero: smallest singular value of ``[A - zI, B]`` / ``[A - zI; C]`` relative
        to the norm of the system matrix; below ``tol`` the test says "decoupling".
    internal_eigenvalues : ndarray or None
        Eigenvalues of the linearized internal dynamics (003 Sect. 2/3) compared with the
        invariant zeros; ``internal_mismatch`` is the largest relative difference.
    """

    invariant: np.ndarray
    kinds: tuple
    transmission: np.ndarray
    input_decoupling: np.ndarray
    output_decoupling: np.ndarray
    pbh_input: np.ndarray
    pbh_output: np.ndarray
    tol: float
    internal_eigenvalues: np.ndarray | None = None
    internal_mismatch: float | None = None
    where: str = ""
    diagnostics: dict = field(default_factory=dict)

    def _axis(self, z) -> np.ndarray:
        return np.abs(np.real(z)) <= MATCH_TOL * np.maximum(1.0, np.abs(z))

    @property
    def imaginary_axis(self) -> np.ndarray:
        """Transmission zeros on the imaginary axis (|Re z| <= MATCH_TOL max(1, |z|))."""
        return self.transmission[self._axis(self.transmission)]

    @property
    def unstable(self) -> np.ndarray:
        """Transmission zeros in the open right half plane."""
        return self.transmission[(self.transmission.real > 0) & ~self._axis(self.transmission)]

    @property
    def minimum_phase(self) -> bool:
        """Every transmission zero in the open left half plane (decoupling zeros do not count)."""
        return bool(self.imaginary_axis.size == 0 and self.unstable.size == 0)

    @property
    def decoupling(self) -> np.ndarray:
        """Invariant zeros that are not transmission zeros."""
        return self.invariant[np.array([k != "transmission" for k in self.kinds], bool)] \
            if self.invariant.size else self.invariant

    def describe(self) -> str:
        """One line: the zeros by kind and the verdict on minimum phase."""
        tr = _fmt(self.transmission)
        if self.minimum_phase:
            verdict = "minimum phase (all transmission zeros in the open left half plane)" if self.transmission.size \
                else "minimum phase (no transmission zeros)"
        else:
            bits = []
            if self.unstable.size:
                bits.append(f"{self.unstable.size} in the open right half plane")
            if self.imaginary_axis.size:
                bits.append(f"{self.imaginary_axis.size} on the imaginary axis")
            verdict = "not minimum phase: " + " and ".join(bits)
        dec = [f"{_fmt([z])[1:-1]} ({k})" for z, k in zip(self.invariant, self.kinds) if k != "transmission"]
        where = f"{self.where}: " if self.where else ""
        return (f"{where}{self.invariant.size} invariant zero(s); transmission zeros {tr}: {verdict}; "
                f"decoupling zeros: {', '.join(dec) if dec else 'none'}")

    def to_dict(self) -> dict:
        cx = lambda z: [[float(v.real), float(v.imag)] for v in np.asarray(z, complex)]  # noqa: E731
        return {"invariant": cx(self.invariant), "kinds": list(self.kinds), "transmission": cx(self.transmission),
                "input_decoupling": cx(self.input_decoupling), "output_decoupling": cx(self.output_decoupling),
                "pbh_input": self.pbh_input.tolist(), "pbh_output": self.pbh_output.tolist(),
                "minimum_phase": self.minimum_phase, "imaginary_axis": cx(self.imaginary_axis),
                "internal_mismatch": self.internal_mismatch, "tol": self.tol, "describe": self.describe()}


def _fmt(z) -> str:
    z = np.asarray(z, complex)
    return "[" + ", ".join(f"{v.real:.6g}" + (f"{v.imag:+.6g}j" if v.imag else "") for v in z) + "]"


def classify_statespace(sys, *, internal_eigenvalues=None, tol: float = ZERO_TOL, where: str = "") -> ZeroReport:
    """Invariant zeros of ``sys`` classified into transmission and decoupling zeros.

    Two routes must agree: the transmission zeros (Rosenbrock zeros of the staircase minimal
    realization) are a sub-multiset of the invariant zeros, and every other invariant zero fails
    a PBH rank test (``[A - zI, B]`` or ``[A - zI; C]`` rank deficient at ``tol``).

    Raises
    ------
    ZeroError
        If the two routes disagree (the tolerance does not separate the structure; the report is
        in ``exc.partial``), or ``internal_eigenvalues`` differ from the invariant zeros by more than
        :data:`MATCH_TOL`.
    """
    A, B, C, D = system_matrices(sys)
    scale = _scale(A, B, C, D)
    Z = invariant_zeros((A, B, C, D), tol=tol)
    parts = kalman_parts((A, B, C, D), tol=tol)
    T = invariant_zeros(parts["minimal"], tol=tol)
    tests = np.array([pbh(A, B, C, z, scale) for z in Z]).reshape(-1, 2)
    kinds = []
    iz, it, dist = match(Z, T)
    transmission_at = {int(i) for i, d in zip(iz, dist) if d <= MATCH_TOL}
    for i in range(Z.size):
        di, do = tests[i, 0] <= tol, tests[i, 1] <= tol
        if i in transmission_at:
            kinds.append("transmission")
        else:
            kinds.append("input-output decoupling" if di and do else "input decoupling" if di
                         else "output decoupling" if do else "unexplained")
    ev = None if internal_eigenvalues is None else _sort(np.asarray(internal_eigenvalues, complex).ravel())
    mismatch = None
    if ev is not None:
        _, _, d = match(Z, ev)
        mismatch = float(np.max(d)) if d.size else 0.0
        if ev.size != Z.size:
            mismatch = float("inf")
    rep = ZeroReport(
        invariant=Z, kinds=tuple(kinds), transmission=T, input_decoupling=parts["input_decoupling"],
        output_decoupling=parts["output_decoupling"], pbh_input=tests[:, 0], pbh_output=tests[:, 1], tol=tol,
        internal_eigenvalues=ev, internal_mismatch=mismatch, where=where,
        diagnostics={"unmatched_transmission": int(T.size - len(transmission_at)),
                     "staircase_invariance_residual": parts["invariance_residual"],
                     "minimal_order": parts["minimal"][0].shape[0], "order": A.shape[0]})
    prefix = f"{where}: " if where else ""
    if len(transmission_at) != T.size or "unexplained" in kinds:
        raise ZeroError(
            f"{prefix}the zero classification is inconsistent at tol = {tol:g}: invariant zeros {_fmt(Z)}, "
            f"transmission zeros {_fmt(T)}, PBH (input, output) {np.round(tests, 12).tolist()}; every invariant "
            "zero must be a transmission zero or fail a PBH test. The rank decisions are not separated at this "
            "tolerance: try another tol (the PBH values show the gap)", partial=rep, diagnostics=rep.diagnostics)
    if mismatch is not None and mismatch > MATCH_TOL:
        raise ZeroError(
            f"{prefix}the internal-dynamics eigenvalues {_fmt(ev)} are not the invariant zeros {_fmt(Z)} of the "
            f"linearization (largest relative difference {mismatch:.3g}); linearize the internal dynamics at the same "
            "equilibrium (one point, not a mean over several)", partial=rep, diagnostics=rep.diagnostics)
    return rep


def classify_zeros(model, point, *, u0=None, lin=None, internal=None, check_internal: bool = True,
                   tol: float = ZERO_TOL) -> ZeroReport:
    """Transmission vs decoupling zeros of ``model`` linearized at the equilibrium configuration ``point``.

    The plant is linearized with :func:`~invctl.analysis.statespace.plant_linearization`; its
    invariant zeros are compared with the eigenvalues of the linearized internal dynamics
    (``lin``; default: the Sect. 3 route with default coordinates at ``point``, or ``internal``)
    and classified (:func:`classify_statespace`).  ``minimum_phase`` is judged on the
    transmission zeros only.

    Raises
    ------
    LinearizationError, ModelError
        ``point`` is not an equilibrium on the constraint manifold.
    ZeroError
        Inconsistent classification or internal eigenvalues that are not the invariant zeros.
    CoordinateError
        The default internal dynamics cannot be built (pass ``internal``/``lin``, or
        ``check_internal=False``).
    """
    from .internal import internal_dynamics
    from .linearize import linearize_internal
    from .statespace import plant_linearization

    pl = plant_linearization(model, point, u0=u0)
    q0 = pl.q0
    ev = None
    if check_internal:
        if lin is None:
            try:
                idyn = internal if internal is not None else internal_dynamics(model, "sect3", point=q0)
                ys = [model.evaluate("h", q0).ravel()] + [np.zeros(model.ny)] * (idyn.r_hat - 1)
                eta0 = np.array(idyn.eta(q0, np.zeros(model.n), model.theta_values)).ravel()
                lin = linearize_internal(model, idyn, [(ys, eta0)])
            except CoordinateError as exc:
                raise CoordinateError(f"{model.name}: classify_zeros could not build the internal dynamics at "
                                      f"q = {np.round(q0, 6).tolist()} ({exc}); pass internal=..., lin=... or "
                                      "check_internal=False", partial=getattr(exc, "partial", None),
                                      diagnostics=getattr(exc, "diagnostics", None)) from None
        ev = lin.eigenvalues
    return classify_statespace(pl, internal_eigenvalues=ev, tol=tol,
                               where=f"{model.name} at q = {np.round(q0, 6).tolist()}")
