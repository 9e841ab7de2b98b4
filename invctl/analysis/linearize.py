"""Linearized internal dynamics and the stable/unstable split, 003 Sect. 5 steps 2-4.

(37)  eta' = Q eta + sum_i P_i y^(i-1)      (Jacobians of q at a point, or their mean)
(38)  eta' = Q eta + P y,   P = sum_i Q^(i-1) P_i,   eta_(38) = F0 eta + sum_i F_i y^(i-1),
      F0 = I,  F_l = -sum_{j=1}^{r_hat-l} Q^(j-1) P_(j+l)
(39)  T Q T^-1 = [[Q1^, Q2^], [0, Q~]],  T P = [P^; P~],  sigma(Q1^) in C-, sigma(Q~) in closed C+
(40)  eta2' = Q~ eta2 + P~ y
(A1), (A2), eta2_ref^0 by the integral (43) or the Sylvester equation (44).
"""
from __future__ import annotations

from typing import Any

from dataclasses import dataclass, field

import casadi as ca
import numpy as np
import scipy.linalg as sla

from ..errors import CoordinateError, StabilityError
from .auxiliary import as_points, eval_batch, region_samples, sampling_domain
from .internal import point_args, xi_expression
from .relative_degree import schur_complement

_IMAG_TOL = 1e-9


@dataclass
class LinearizedInternal:
    """Linearized internal dynamics with the derivative removal (38) and the split (39).

    Attributes
    ----------
    Q, P_list, P : ndarray
        ``Q`` and ``P_1 .. P_r_hat`` of (37); ``P`` of (38).
    F0, F : ndarray, list of ndarray
        The transformation (37) -> (38): ``eta_38 = F0 eta + sum_i F[i-1] y^(i-1)``.
    T : ndarray
        The split (39): ``T Q T^-1`` block upper triangular, stable block first.
    k : int
        Number of eigenvalues of Q in the closed right half plane (size of Q~).
    Q_hat1, Q_hat2, Q_tilde, P_hat, P_tilde : ndarray
        Blocks of (39).
    eigenvalues : ndarray
        Eigenvalues of Q (sorted by real part).
    split : str
        ``"schur"`` (orthogonal T from the ordered real Schur form), ``"eig"`` (T = inverse of
        the eigenvector matrix, each eigenvector scaled to last entry 1, as the printed
        ``T = [mu2/c mu1/c; 1 1]`` of 003 Sect. 6) or ``"eig-unit"`` (eigenvectors of unit length
        with negative last entry: the normalization of the printed ``T^-1 P`` of 003 Sect. 6, see
        :func:`eigenvector_columns`); with either ``"eig"`` form ``T Q T^-1`` is diagonal.
    eta2_offset : ndarray
        Constant added to ``Psi`` (k,) so that its value at the linearization points' equilibria is the
        equilibrium ``-Q~^-1 P~ y`` of (40) (mean over the points): the constant term of the linearization,
        e.g. gravity on an internal coordinate that is not zero at rest (:func:`linearize_internal`).
    """

    model: Any
    internal: Any
    Q: np.ndarray
    P_list: list
    P: np.ndarray
    F0: np.ndarray
    F: list
    T: np.ndarray
    k: int
    Q_hat1: np.ndarray
    Q_hat2: np.ndarray
    Q_tilde: np.ndarray
    P_hat: np.ndarray
    P_tilde: np.ndarray
    eigenvalues: np.ndarray
    points: list
    split: str = "schur"
    diagnostics: dict = field(default_factory=dict)
    eta2_offset: np.ndarray | None = None

    @property
    def r_hat(self) -> int:
        return len(self.P_list)

    @property
    def minimum_phase(self) -> bool:
        """True if every eigenvalue of Q is in the open left half plane (locally minimum phase)."""
        return self.k == 0 and bool(np.all(self.eigenvalues.real < 0))

    # -------------------------------------------------------------- Psi (58)
    def psi_function(self) -> ca.Function:
        """``Psi: (q, v, theta) -> eta2 = [0, I_k] T [0, F_1, ..., F_r, F_0] Phi(q, v) + eta2_offset`` (Sect. 5, (58));
        built once."""
        cached = self.__dict__.get("_psi")
        if cached is not None:
            return cached
        model, internal = self.model, self.internal
        _, out_blocks = xi_expression(model)
        eta38 = ca.mtimes(ca.DM(self.F0), internal.phi_expr)
        for Fi, yk in zip(self.F, out_blocks):
            eta38 = eta38 + ca.mtimes(ca.DM(Fi), yk)
        d = self.Q.shape[0]
        sel = ca.DM(self.T[d - self.k:, :])
        off = ca.DM(np.zeros(self.k) if self.eta2_offset is None else self.eta2_offset)
        fn = ca.Function("Psi", [model.q, model.v, model.theta], [ca.mtimes(sel, eta38) + off],
                         ["q", "v", "theta"], ["eta2"])
        self.__dict__["_psi"] = fn
        return fn

    # ------------------------------------------------------------- (A1), (A2)
    def check_A1(self, K, rho=None, k_i=None, samples=200, rng=0, points=None, *, radius=None,
                 v_radius=None) -> "A1Report":
        """Check (A1) for rows ``K = [K_1, ..., K_m]`` (``K_1..K_q`` of length k, the rest of length m).

        ``k_i`` (length q) defaults to all ones with q = number of rows of length k
        (listed first). ``rho`` in {-1, 1}; ``None`` tries both and keeps the one that
        holds at the design point. The matrix ``rho [K_i Q~^(k_i-1) P~; K_(q+1); ...] S~(w)``
        must be positive definite (symmetric part) at every sample point: ``samples`` points of
        the model's region, or, without a declared region, of the neighbourhood (half-widths
        ``radius``, ``v_radius``; defaults 0.1 and 1.0) of the polyline through the design point
        and ``points`` (e.g. the equilibria along the reference, ``operating_points``); plus
        the design point and ``points`` themselves.
        """
        m = self.P.shape[1]
        K = [np.atleast_1d(np.asarray(Ki, float)).ravel() for Ki in K]
        if len(K) != m:
            raise CoordinateError(f"(A1) needs m = {m} rows K_i, got {len(K)}")
        q = sum(1 for Ki in K if Ki.size == self.k and self.k != m) if k_i is None else len(k_i)
        k_i = [1] * q if k_i is None else [int(v) for v in k_i]
        if sum(k_i) != self.k:
            raise CoordinateError(f"(A1): k_1 + ... + k_q = {sum(k_i)} must equal k = {self.k}")
        Qt, Pt = self.Q_tilde, self.P_tilde
        zero_res, rows = 0.0, []
        for i in range(q):
            if K[i].size != self.k:
                raise CoordinateError(f"(A1): K_{i + 1} must have length k = {self.k}, got {K[i].size}")
            for j in range(k_i[i] - 1):
                zero_res = max(zero_res, float(np.max(np.abs(K[i] @ np.linalg.matrix_power(Qt, j) @ Pt))))
            rows.append(K[i] @ np.linalg.matrix_power(Qt, k_i[i] - 1) @ Pt)
        for i in range(q, m):
            if K[i].size != m:
                raise CoordinateError(f"(A1): K_{i + 1} must have length m = {m}, got {K[i].size}")
            rows.append(K[i])
        Kmat = np.vstack(rows)
        model = self.model
        S = schur_complement(model)
        pts = [(self.internal.point, np.zeros(model.n))] + as_points(model, points)
        qs, vs = region_samples(model, samples, rng, pts, radius=radius, v_radius=v_radius)
        Ss = eval_batch(S, qs, vs, theta=model.theta_values)[0]
        KS = np.einsum("ij,njk->nik", Kmat, Ss)
        design = int(samples)  # region samples come first, then the design point
        sym = 0.5 * (KS + KS.transpose(0, 2, 1))
        if rho is None:
            rho = 1 if np.linalg.eigvalsh(sym[design])[0] > 0 else -1
        sym_min = np.linalg.eigvalsh(rho * sym)[:, 0]
        ok = sym_min > 0
        worst = int(np.argmin(sym_min))
        return A1Report(
            passed=bool(zero_res < 1e-12 and ok.all()), rho=int(rho), q=q, k_i=tuple(k_i),
            zero_conditions_residual=zero_res, min_eig_sym=float(sym_min.min()),
            min_eig_at_design_point=float(sym_min[design]), fraction_satisfied=float(ok.mean()),
            worst_point=(qs[worst], vs[worst]), matrix=Kmat, samples=qs.shape[0],
            domain=sampling_domain(model, pts, radius, v_radius),
        )

    def _unstable_split(self):
        """W with W Q~ W^-1 = diag(Q1, Q2), sigma(Q1) in C+ (open), sigma(Q2) on iR (A2)."""
        Qt, Pt = self.Q_tilde, self.P_tilde
        if self.k == 0:
            return np.eye(0), np.zeros((0, 0)), np.zeros((0, Pt.shape[1])), np.zeros((0, 0)), np.zeros((0, Pt.shape[1])), 0
        S, Z, l1 = sla.schur(Qt, output="real", sort=lambda re, im: re > _IMAG_TOL * max(1.0, np.abs(Qt).max()))
        S11, S12, S22 = S[:l1, :l1], S[:l1, l1:], S[l1:, l1:]
        Y = sla.solve_sylvester(S11, -S22, -S12) if S12.size else np.zeros((l1, self.k - l1))
        Wt = np.eye(self.k)
        Wt[:l1, l1:] = -Y
        W = Wt @ Z.T
        WP = W @ Pt
        Qb = W @ Qt @ np.linalg.inv(W)
        return W, Qb[:l1, :l1], WP[:l1], Qb[l1:, l1:], WP[l1:], l1

    def check_A2(self, reference=None, exo=None) -> "A2Report":
        """Check (A2): ``z2' = Q2 z2 + P2 y_ref, z2(0) = 0`` has a bounded solution.

        Without eigenvalues of Q~ on the imaginary axis (l2 = 0) (A2) holds trivially.
        Otherwise: for a reference that is constant ``y_f`` after ``reference.tf`` it holds
        iff Q2 is semisimple and ``P2 y_f`` lies in the range of Q2; for an exosystem
        ``(A_e, C_e, w0)`` iff the Sylvester-type equation ``Q2 X - X A_e = P2 C_e`` is
        solvable on the excited modes (checked by least squares).
        """
        W, Q1, P1, Q2, P2, l1 = self._unstable_split()
        l2 = self.k - l1
        if l2 == 0:
            return A2Report(True, l1, 0, "sigma(Q~) has no eigenvalue on the imaginary axis: (A2) holds trivially", W)
        ev, vec = np.linalg.eig(Q2)
        semisimple = np.linalg.matrix_rank(vec, tol=1e-8) == l2
        if exo is not None:
            Ae, Ce = np.atleast_2d(np.asarray(exo[0], float)), np.atleast_2d(np.asarray(exo[1], float))
            A = np.kron(np.eye(Ae.shape[0]), Q2) - np.kron(Ae.T, np.eye(l2))
            b = (P2 @ Ce).ravel(order="F")
            X = np.linalg.lstsq(A, b, rcond=None)[0]
            res = np.linalg.norm(A @ X - b)
            ok = semisimple and res < 1e-9 * max(1.0, float(np.linalg.norm(b)))
            return A2Report(bool(ok), l1, l2, f"exosystem: Sylvester residual {res:.3g}, Q2 semisimple: {semisimple}", W)
        if reference is None:
            return A2Report(False, l1, l2, "Q~ has eigenvalues on the imaginary axis: give the reference to decide (A2)", W)
        yf = np.asarray(reference(reference.tf)).ravel()
        b = P2 @ yf
        z = np.linalg.lstsq(Q2, -b, rcond=None)[0]
        res = np.linalg.norm(Q2 @ z + b)
        ok = semisimple and res < 1e-9 * max(1.0, float(np.linalg.norm(b)))
        return A2Report(bool(ok), l1, l2, f"constant tail y_f: residual of Q2 z = -P2 y_f is {res:.3g}, "
                                          f"Q2 semisimple: {semisimple}", W)

    # ------------------------------------------------------------- (43), (44)
    def eta2_ref0(self, reference=None, method: str = "integral", exo=None, *, t_start: float = 0.0,
                  tol: float = 1e-10) -> np.ndarray:
        """Initial value of the new reference dynamics (42).

        ``method="integral"``: (43), ``W^-1 [-I; 0] int_0^inf exp(-Q1 s) P1 y_ref(s) ds`` with
        the integral over the transition by adaptive Gauss-Legendre panels and the constant
        tail after ``reference.tf`` in closed form (``exp(-Q1 tf) Q1^-1 P1 y_f``).
        ``method="sylvester"``: (44) for an exosystem ``exo = (A_e, C_e, w0)``: solve
        ``Q1 X - X A_e = P1 C_e`` and return ``W^-1 [-I; 0] X w0``.
        """
        W, Q1, P1, Q2, P2, l1 = self._unstable_split()
        Winv = np.linalg.inv(W) if W.size else W
        lift = np.vstack([-np.eye(l1), np.zeros((self.k - l1, l1))])
        if method == "sylvester":
            if exo is None:
                raise CoordinateError("eta2_ref0(method='sylvester') needs exo=(A_e, C_e, w0) of (44)")
            Ae, Ce = np.atleast_2d(np.asarray(exo[0], float)), np.atleast_2d(np.asarray(exo[1], float))
            w0 = np.asarray(exo[2], float).ravel()
            if np.any(np.linalg.eigvals(Ae).real > 1e-12):
                raise StabilityError("exosystem (44) needs sigma(A_e) in the closed left half plane")
            X = sla.solve_sylvester(Q1, -Ae, P1 @ Ce)
            return Winv @ lift @ (X @ w0)
        if method != "integral":
            raise CoordinateError(f"method must be 'integral' or 'sylvester', got {method!r}")
        if reference is None:
            raise CoordinateError("eta2_ref0(method='integral') needs the reference")
        if l1 == 0:
            return np.zeros(self.k)
        lam_min = float(np.min(np.linalg.eigvals(Q1).real))
        horizon = t_start + 40.0 / lam_min
        t_end = min(reference.tf, horizon) if np.isfinite(reference.tf) else horizon
        integral = _gauss_panels(
            lambda s: np.einsum("nij,jk,kn->ni", _expm_batch(-Q1, s), P1, _ref_batch(reference, s)),
            t_start, max(t_end, t_start), tol)
        if reference.tf < horizon:
            tf = max(reference.tf, t_start)
            yf = np.asarray(reference(tf)).ravel()
            integral = integral + sla.expm(-Q1 * tf) @ np.linalg.solve(Q1, P1 @ yf)
        return Winv @ lift @ integral

    def plot(self, ax=None):
        """Eigenvalues of Q (stable: o, closed right half plane: x) in the complex plane."""
        import matplotlib.pyplot as plt

        if ax is None:
            _, ax = plt.subplots(figsize=(4.5, 3.5))
        ev = self.eigenvalues
        st = ev.real < 0
        ax.plot(ev[st].real, ev[st].imag, "o", label="stable")
        ax.plot(ev[~st].real, ev[~st].imag, "x", ms=9, label="unstable / marginal")
        ax.axvline(0, color="k", lw=0.6)
        ax.set(xlabel="Re", ylabel="Im", title="linearized internal dynamics (38)")
        ax.legend()
        return ax

    def to_npz(self, path) -> None:
        """Save Q, P_1..P_r, P, F0, F, T, k and the split to ``path`` (.npz); read back with :func:`load_linearization`."""
        np.savez(path, Q=self.Q, P=self.P, P_list=np.array(self.P_list), F0=self.F0, F=np.array(self.F), T=self.T,
                 k=self.k, Q_tilde=self.Q_tilde, P_tilde=self.P_tilde, eigenvalues=self.eigenvalues,
                 split=self.split)

    def summary(self) -> str:
        ev = ", ".join(f"{e.real:.6g}" + (f"{e.imag:+.6g}j" if abs(e.imag) > 0 else "") for e in self.eigenvalues)
        return (f"linearized internal dynamics (38): eigenvalues of Q: [{ev}]; "
                f"{self.k} in the closed right half plane ({'minimum phase' if self.minimum_phase else 'non-minimum phase'})")

    def to_statespace(self):
        """``eta' = Q eta + P y`` of (38) as a ``control.StateSpace`` (see :func:`internal_statespace`)."""
        from .statespace import internal_statespace

        return internal_statespace(self)

    def to_dict(self) -> dict:
        return {"Q": self.Q, "P": self.P, "P_list": self.P_list, "T": self.T, "k": self.k,
                "Q_tilde": self.Q_tilde, "P_tilde": self.P_tilde, "eigenvalues": self.eigenvalues.real.tolist()
                if np.all(np.abs(self.eigenvalues.imag) == 0) else [[e.real, e.imag] for e in self.eigenvalues],
                "split": self.split}


@dataclass(frozen=True)
class A1Report:
    passed: bool
    rho: int
    q: int
    k_i: tuple
    zero_conditions_residual: float
    min_eig_sym: float
    min_eig_at_design_point: float
    fraction_satisfied: float
    worst_point: tuple
    matrix: np.ndarray
    samples: int
    domain: str = ""

    def to_dict(self) -> dict:
        return {"passed": self.passed, "rho": self.rho, "q": self.q, "k_i": list(self.k_i),
                "min_eig_sym": self.min_eig_sym, "min_eig_at_design_point": self.min_eig_at_design_point,
                "fraction_satisfied": self.fraction_satisfied, "samples": self.samples,
                "worst_q": self.worst_point[0], "domain": self.domain}


@dataclass(frozen=True)
class A2Report:
    passed: bool
    l1: int
    l2: int
    message: str
    W: np.ndarray

    def to_dict(self) -> dict:
        return {"passed": self.passed, "l1": self.l1, "l2": self.l2, "message": self.message}


def load_linearization(path) -> dict:
    """The arrays saved by :meth:`LinearizedInternal.to_npz` (a dict; rebuild with :func:`from_matrices`)."""
    with np.load(path) as data:
        out = {k: data[k] for k in data.files}
    out["P_list"] = list(out["P_list"])
    out["F"] = list(out["F"])
    out["k"] = int(out["k"])
    out["split"] = str(out["split"])
    return out


def _ref_batch(reference, s):
    return np.asarray(reference(s)).reshape(-1, np.size(s))


def _expm_batch(A, s):
    """exp(A s) for many s: returns (N, d, d) via eigen-decomposition when diagonalizable."""
    w, V = np.linalg.eig(A)
    if np.linalg.cond(V) < 1e8:
        Vi = np.linalg.inv(V)
        return np.real(np.einsum("ij,nj,jk->nik", V, np.exp(np.outer(s, w)), Vi))
    return np.stack([sla.expm(A * si) for si in s])


def _gauss_panels(fn, a, b, tol, order=20):
    """Integral of fn (vectorized: s (N,) -> (N, d)) over [a, b] by Gauss-Legendre panels, doubled until converged."""
    if b <= a:
        return 0.0
    x, w = np.polynomial.legendre.leggauss(order)

    def integrate(panels):
        edges = np.linspace(a, b, panels + 1)
        mid, half = 0.5 * (edges[1:] + edges[:-1]), 0.5 * np.diff(edges)
        s = (mid[:, None] + half[:, None] * x[None, :]).ravel()
        ws = (half[:, None] * w[None, :]).ravel()
        return np.einsum("n,nd->d", ws, fn(s))

    prev = integrate(8)
    for panels in (16, 32, 64, 128, 256):
        cur = integrate(panels)
        if np.max(np.abs(cur - prev)) <= tol * max(1.0, np.max(np.abs(cur))):
            return cur
        prev = cur
    return cur


def jacobian_function(internal) -> ca.Function:
    """``(y_0.., eta, theta) -> (dq/deta, dq/dy_0, ..., dq/dy_{r-1})`` (cached on the internal object)."""
    fn = internal.__dict__.get("_jac_fn")
    if fn is None:
        rhs = internal.rhs
        ins = rhs.mx_in()
        out = rhs.call(ins)[0]
        r = internal.r_hat
        jacs = [ca.jacobian(out, ins[r])] + [ca.jacobian(out, ins[k]) for k in range(r)]
        fn = ca.Function("internal_jac", ins, jacs, rhs.name_in(), ["dq_deta"] + [f"dq_dy_{k}" for k in range(r)])
        object.__setattr__(internal, "_jac_fn", fn)
    return fn


#: normalizations of eigenvector columns (:func:`eigenvector_columns`)
EIG_NORMALIZATIONS = ("last-one", "unit-last-positive", "unit-last-negative")


def eigenvector_columns(V, normalization: str) -> np.ndarray:
    """Real eigenvector columns ``V`` rescaled: ``"last-one"`` (last entry 1; the printed
    ``T = [mu2/c mu1/c; 1 1]`` of 003 Sect. 6), ``"unit-last-positive"`` or ``"unit-last-negative"``
    (Euclidean length 1, the sign fixed by the last entry; the printed ``T^-1 P`` of 003 Sect. 6
    uses ``"unit-last-negative"``, which is what LAPACK's ``dgeev`` (MATLAB ``eig``) returns there).
    A zero last entry keeps the scale (``"last-one"``) or the sign of the largest entry."""
    V = np.array(V, float, copy=True)
    if normalization not in EIG_NORMALIZATIONS:
        raise CoordinateError(f"eigenvector normalization must be one of {EIG_NORMALIZATIONS}, got {normalization!r}")
    last = V[-1]
    if normalization == "last-one":
        return V / np.where(np.abs(last) > 1e-12, last, 1.0)
    V = V / np.linalg.norm(V, axis=0)
    ref = np.where(np.abs(V[-1]) > 1e-12, V[-1], V[np.argmax(np.abs(V), axis=0), np.arange(V.shape[1])])
    sign = np.sign(ref) * (1.0 if normalization == "unit-last-positive" else -1.0)
    return V * sign


def linearize_internal(model, internal, points, combine: str = "mean", *, split: str = "schur") -> LinearizedInternal:
    """Linearize ``eta' = q(y, ..., eta)`` at one or more points and split it (37)-(39).

    Parameters
    ----------
    points : list of ``(ys, eta)``
        ``ys = (y, y', ..., y^(r_hat-1))``; one point, or several whose Jacobians are
        combined (``combine="mean"``, as 003 Sect. 6 does with the start and end of the path).
    split : {"schur", "eig", "eig-unit"}
        How T of (39) is built (see :class:`LinearizedInternal`).
    """
    if combine != "mean":
        raise CoordinateError(f"combine must be 'mean', got {combine!r}")
    if not points:
        raise CoordinateError("linearize_internal needs at least one point (ys, eta)")
    jac = jacobian_function(internal)
    th = model.theta_values
    Qs, Ps = [], []
    for pt in points:
        args = point_args(internal, pt)
        try:
            out = jac(**args, theta=th)
        except RuntimeError as exc:
            raise CoordinateError(f"{model.name}: could not linearize at {pt}: Newton for Phi^-1 failed "
                                  f"({str(exc).splitlines()[-1]})") from None
        Qs.append(np.array(out["dq_deta"]))
        Ps.append([np.array(out[f"dq_dy_{k}"]) for k in range(internal.r_hat)])
    Q = np.mean(Qs, axis=0)
    P_list = [np.mean([P[k] for P in Ps], axis=0) for k in range(internal.r_hat)]
    lin = from_matrices(model, internal, Q, P_list, split=split, points=list(points))
    states = []
    for pt in points:
        args = point_args(internal, pt)
        st = internal.state(**args, theta=th)
        states.append(np.array(st["q"]).ravel())
    lin.diagnostics["point_configurations"] = states
    lin.eta2_offset = _eta2_offset(lin, internal, points, th)
    if model.region is not None:
        lin.diagnostics["points_in_region"] = [bool(model.region.contains(q)) for q in states]
    if len(Qs) > 1:
        lin.diagnostics["jacobian_spread"] = float(max(np.max(np.abs(Qk - Q)) for Qk in Qs))
    return lin


def _eta2_offset(lin, internal, points, th):
    """``Q~^-1 c~`` with ``c~ = [0, I_k] T c`` and ``c`` the constant term of the linearization (37),
    ``eta' = Q eta + sum_i P_i y^(i-1) + c``, averaged over the points.  (40) drops ``c``; it is not zero where an
    internal coordinate is loaded at rest (gravity on an elastic joint), and without it ``K_i (eta2 - eta2_ref)``
    would not vanish at the reference's equilibria.  Zero when ``Q~`` is singular (an eigenvalue at 0)."""
    k, d = lin.k, lin.Q.shape[0]
    if k == 0 or np.linalg.cond(lin.Q_tilde) > 1e8:
        return np.zeros(k)
    cs = []
    for pt in points:
        args = point_args(internal, pt)
        rhs = np.array(internal.rhs(**args, theta=th)[internal.rhs.name_out(0)]).ravel()
        cs.append(rhs - lin.Q @ args["eta"] - sum(P @ args[f"y_{i}"] for i, P in enumerate(lin.P_list)))
    return np.linalg.solve(lin.Q_tilde, lin.T[d - k:] @ np.mean(cs, axis=0))


def from_matrices(model, internal, Q, P_list, *, split="schur", points=None) -> LinearizedInternal:
    """Build (38), (39) from given ``Q`` and ``P_1..P_r`` of (37)."""
    Q = np.atleast_2d(np.asarray(Q, float))
    P_list = [np.atleast_2d(np.asarray(P, float)) for P in P_list]
    d, r = Q.shape[0], len(P_list)
    P = sum(np.linalg.matrix_power(Q, i) @ P_list[i] for i in range(r))
    F0 = np.eye(d)
    # F_l = -sum_{j=1}^{r-l} Q^(j-1) P_(j+l)  (the printed recursion of 003 Sect. 5 omits Q^(j-1); it only
    # matters for r_hat >= 3, see docs/analysis.md)
    F = [-sum((np.linalg.matrix_power(Q, j - 1) @ P_list[l + j] for j in range(1, r - l)), np.zeros_like(P_list[0]))
         for l in range(r)]
    ev = np.linalg.eigvals(Q) if d else np.zeros(0, complex)
    ev = ev[np.argsort(ev.real)]
    tol = _IMAG_TOL * max(1.0, np.abs(Q).max(initial=0.0))
    k = int(np.sum(ev.real >= -tol))
    if split not in ("schur", "eig", "eig-unit"):
        raise CoordinateError(f"split must be 'schur', 'eig' or 'eig-unit', got {split!r}")
    if d == 0:  # no internal dynamics (flat output): nothing to split
        T = np.eye(0)
    elif split in ("eig", "eig-unit"):
        if np.any(np.abs(ev.imag) > 0):
            raise CoordinateError(f"split={split!r} needs real eigenvalues; use split='schur'")
        w, V = np.linalg.eig(Q)
        order = np.argsort(w.real)
        V = eigenvector_columns(np.real(V[:, order]), "last-one" if split == "eig" else "unit-last-negative")
        T = np.linalg.inv(V)
    else:
        _, Z, sdim = sla.schur(Q, output="real", sort=lambda re, im: re < -tol)
        T = Z.T
    TQ = T @ Q @ np.linalg.inv(T) if d else Q
    TP = T @ P
    s = d - k
    lin = LinearizedInternal(
        model=model, internal=internal, Q=Q, P_list=P_list, P=P, F0=F0, F=F, T=T, k=k,
        Q_hat1=TQ[:s, :s], Q_hat2=TQ[:s, s:], Q_tilde=TQ[s:, s:], P_hat=TP[:s], P_tilde=TP[s:],
        eigenvalues=ev, points=points or [], split=split,
        diagnostics={"lower_block_residual": float(np.max(np.abs(TQ[s:, :s]))) if s and k else 0.0},
    )
    return lin
