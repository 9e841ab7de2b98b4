"""Boundary conditions 003 (36): selections by name and the equilibria they fix.

A selection names, for each block of ``X = (q, v, lam, mu, u)``, which entries
are fixed to the initial equilibrium at ``T0`` (``start``) or to the final one
at ``Tf`` (``end``)::

    start = {"q": "all", "v": ["s1", "s2"], "lam": [0], "u": "all"}
    end   = {"q": ["gamma"], "lam": [1], "u": "all"}

Entries are ``"all"``, indices or names (``q``/``u`` names of the model,
``<q name>_dot`` for ``v``, ``lam1``..., ``mu1``...).  003 (36) needs exactly
``2n + l + p + m`` conditions in total.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import BoundaryConditionError

BLOCKS = ("q", "v", "lam", "mu", "u")


@dataclass(frozen=True)
class Selection:
    """Resolved boundary selection: indices into ``X`` at ``T0`` and at ``Tf``."""

    start: tuple[int, ...]
    end: tuple[int, ...]
    labels: tuple[str, ...]

    def describe(self) -> str:
        s = ", ".join(self.labels[i] for i in self.start) or "-"
        e = ", ".join(self.labels[i] for i in self.end) or "-"
        return f"at T0: {s};  at Tf: {e}"


def _resolve(side: str, spec, servo) -> list[int]:
    L, names = servo.layout, servo.names
    blocks = L.blocks
    out: list[int] = []
    if spec is None:
        return out
    if not isinstance(spec, dict):
        raise BoundaryConditionError(f"{side}: expected a dict block -> entries, e.g. {{'q': 'all'}}, got {spec!r}")
    for key, entries in spec.items():
        if key not in BLOCKS:
            raise BoundaryConditionError(f"{side}: unknown block {key!r}; blocks are {BLOCKS}")
        sl = blocks[key]
        size = sl.stop - sl.start
        if entries == "all":
            idx = list(range(size))
        elif entries is None or entries == [] or entries == ():
            idx = []
        else:
            if isinstance(entries, (str, int, np.integer)):
                entries = [entries]
            idx = []
            for e in entries:
                if isinstance(e, str):
                    if key == "v" and e in names["q"]:
                        e = names["v"][names["q"].index(e)]
                    if e not in names[key]:
                        raise BoundaryConditionError(
                            f"{side}[{key!r}]: unknown entry {e!r}; names are {names[key]} (or indices 0..{size - 1})")
                    idx.append(names[key].index(e))
                elif isinstance(e, (int, np.integer)) and 0 <= int(e) < size:
                    idx.append(int(e))
                else:
                    raise BoundaryConditionError(
                        f"{side}[{key!r}]: entry {e!r} is not a name or an index in 0..{size - 1} "
                        f"(block {key} has {size} entries: {names[key]})")
        if len(set(idx)) != len(idx):
            raise BoundaryConditionError(f"{side}[{key!r}]: entries repeated in {entries!r}")
        out.extend(sl.start + i for i in idx)
    return out


def resolve_selection(servo, start, end, *, allow_underdetermined: bool = False) -> Selection:
    """Check and resolve a selection (see module doc).

    Raises
    ------
    BoundaryConditionError
        Unknown blocks or entries, or a count other than ``2n + l + p + m``
        (fewer is accepted with ``allow_underdetermined``; an objective then
        selects the solution).
    """
    L = servo.layout
    labels = tuple(f"{k}:{nm}" for k in BLOCKS for nm in servo.names[k])
    s, e = _resolve("start", start, servo), _resolve("end", end, servo)
    need = L.nx
    have = len(s) + len(e)
    if have > need or (have < need and not allow_underdetermined):
        per = {k: (sum(1 for i in s if L.blocks[k].start <= i < L.blocks[k].stop),
                   sum(1 for i in e if L.blocks[k].start <= i < L.blocks[k].stop)) for k in BLOCKS}
        detail = ", ".join(f"{k}: {a}+{b}" for k, (a, b) in per.items())
        what = "remove" if have > need else "add"
        raise BoundaryConditionError(
            f"003 (36) needs n0 + nf = 2n + l + p + m = 2*{L.n} + {L.l} + {L.p} + {L.m} = {need} boundary "
            f"conditions, the selection has {have} ({len(s)} at T0 + {len(e)} at Tf; per block start+end: "
            f"{detail}); {what} {abs(need - have)} condition(s). Each entry of (q, v, lam, mu, u) fixed at T0 "
            "or at Tf counts once; fix the modes that decay forward (constraint drift, stable internal dynamics) at "
            "T0 and the growing ones (unstable internal dynamics) at Tf"
            + ("" if have > need else " (or pass allow_underdetermined=True with an objective)"),
            diagnostics={"required": need, "given": have, "start": len(s), "end": len(e)})
    return Selection(tuple(s), tuple(e), labels)


def tangent_dynamics(servo, X, Y, theta):
    """The linearized inverse model at ``X`` and its restriction to the constraint manifold.

    Returns ``(A, T, A_T)``: ``A = dF/dX``, an orthonormal basis ``T`` of the null space of the
    Jacobian of the position, velocity and acceleration residuals (the tangent space of the
    invariant manifold on which (35) holds) and ``A_T = T^T A T``.  At an equilibrium ``A`` maps
    ``T`` into itself, and the eigenvalues of ``A_T`` are those of the linearized internal
    (zero) dynamics (003 Sect. 2-3); the other ``nx - dim T`` eigenvalues of ``A`` belong to
    the constraint drift (``-omega`` with Baumgarte stabilization, ``0`` without).  The last few
    results are remembered by ``servo`` (read-only arrays): the same point is linearized once.
    """
    return _tangent(servo, X, Y, theta)[0]


def tangent_spectra(servo, X, Y, theta):
    """The eigenvalues of ``A`` and ``A_T`` of :func:`tangent_dynamics` (remembered with it: the plan
    and the dichotomy check of its equilibria compute them once)."""
    entry = _tangent(servo, X, Y, theta)
    if entry[1] is None:
        A, _T, AT = entry[0]
        entry[1] = (np.linalg.eigvals(A), np.linalg.eigvals(AT))
        for a in entry[1]:
            a.flags.writeable = False
    return entry[1]


def _tangent(servo, X, Y, theta) -> list:
    import scipy.linalg as sla

    X, Y, theta = (np.asarray(a, float).ravel() for a in (X, Y, theta))
    from .servo import remember

    def make():  # the linearization and, once asked for, its spectra
        A, C = servo.linearization(X, Y, theta)
        T = sla.null_space(C) if C.size else np.eye(A.shape[0])
        out = (A, T, T.T @ A @ T)
        for a in out:
            a.flags.writeable = False
        return [out, None]

    # a plan and the dichotomy check of its equilibria linearize the same points
    return remember(servo.tangents, (X.tobytes(), Y.tobytes(), theta.tobytes()), make, 8)


def neutral_tolerance(eigenvalues, neutral: float = 1e-6) -> float:
    """Real parts with ``|Re| <= neutral * max(1, max |lambda|)`` count as on the imaginary axis."""
    ev = np.asarray(eigenvalues)
    return neutral * max(1.0, float(np.max(np.abs(ev))) if ev.size else 1.0)


def dichotomy(servo, selection: Selection, X0, Y0, Xf, Yf, theta, *, neutral: float = 1e-3) -> dict:
    """Check a boundary selection against the modes of the index-reduced inverse model.

    Before ``t0`` and after ``tf`` the reference is at rest and the inverse model
    ``X' = F(X, t)`` (all ``2n+l+p+m`` unknowns differentiated) linearized at the
    equilibria ``X0``, ``Xf`` is time invariant.  A two-point BVP on a long horizon is
    well conditioned exactly when the conditions at ``T0`` fix every mode that decays
    forward and those at ``Tf`` every mode that grows (exponential dichotomy): with
    Baumgarte stabilization the ``2(l+m) + (l+p+m)`` constraint-drift modes decay
    (rate ``omega``), the internal (zero) dynamics split into stable and unstable modes.
    Conditions at ``Tf`` on entries that the constraint invariants determine (``lam``,
    ``u``, the constrained coordinates) act only on the ``2(n-l-m) - p`` dimensional
    tangent space of the invariant manifold, and on its decaying part only through
    ``exp(-rate (Tf - T0))``: they are redundant, and the Jacobian is singular up to
    that exponential.

    Returns
    -------
    dict
        ``decaying``, ``growing``, ``neutral`` (mode counts), ``n_start``, ``n_end``,
        ``rank_start`` (rank of the ``T0`` conditions on the decaying subspace at
        ``X0``), ``rank_end`` (of the ``Tf`` conditions on the growing subspace at
        ``Xf``), ``tangent_dim``, ``rank_end_tangent`` (rank of the ``Tf`` conditions on
        the tangent space of the invariant manifold at ``Xf``), ``well_posed`` (``None``
        when neutral modes make the criterion inapplicable, e.g. unstabilized
        index reduction), ``neutral_internal`` (internal eigenvalues on the imaginary
        axis at either end, :func:`neutral_tolerance`: no dichotomy whatever the
        selection), ``eigenvalues_start``, ``eigenvalues_end``,
        ``eigenvalues_internal_start``, ``eigenvalues_internal_end``.
    """
    import scipy.linalg as sla

    nx = servo.layout.nx
    S0 = np.eye(nx)[list(selection.start)]
    Sf = np.eye(nx)[list(selection.end)]
    e0, ef = _tangent(servo, X0, Y0, theta), _tangent(servo, Xf, Yf, theta)
    (A0, _T0, AT0), (Af, T, ATf) = e0[0], ef[0]
    # one ordered real Schur form per end: its invariant subspace and, unless the plan has them already, the
    # eigenvalues of its blocks (remembered with the linearization, as tangent_spectra does)
    S0_, Zs, dec = sla.schur(A0, output="real", sort=lambda re, im: re < -neutral)
    Sf_, Zu, grow = sla.schur(Af, output="real", sort=lambda re, im: re > neutral)
    Zs, Zu = Zs[:, :dec], Zu[:, :grow]
    for entry, S_, AT in ((e0, S0_, AT0), (ef, Sf_, ATf)):
        if entry[1] is None:
            spectra = (_schur_eigenvalues(S_), np.linalg.eigvals(AT))
            for a in spectra:
                a.flags.writeable = False
            entry[1] = spectra
    (ev0, it0), (evf, itf) = e0[1], ef[1]
    neut = int(max(np.sum(np.abs(ev0.real) <= neutral), np.sum(np.abs(evf.real) <= neutral)))
    neut_int = int(max(np.sum(np.abs(it0.real) <= neutral_tolerance(it0)),
                       np.sum(np.abs(itf.real) <= neutral_tolerance(itf))))

    def rank(M):
        if M.size == 0:
            return 0
        sv = np.linalg.svd(M, compute_uv=False)
        return int(np.sum(sv > 1e-8 * max(1.0, sv[0])))

    out = {"decaying": dec, "growing": grow, "neutral": neut, "n_start": S0.shape[0], "n_end": Sf.shape[0],
           "rank_start": rank(S0 @ Zs), "rank_end": rank(Sf @ Zu), "tangent_dim": T.shape[1],
           "rank_end_tangent": rank(Sf @ T), "neutral_internal": neut_int, "eigenvalues_start": ev0,
           "eigenvalues_end": evf, "eigenvalues_internal_start": it0, "eigenvalues_internal_end": itf}
    out["well_posed"] = None if neut else bool(
        out["n_start"] == dec and out["n_end"] == grow and out["rank_start"] == dec and out["rank_end"] == grow)
    return out


def _schur_eigenvalues(S) -> np.ndarray:
    """The eigenvalues of a real quasi-triangular Schur form (its 1x1 and 2x2 diagonal blocks)."""
    n = S.shape[0]
    ev = S.diagonal().astype(complex)
    i = 0
    while i < n - 1:
        if S[i + 1, i] != 0.0:  # a 2x2 block of a complex pair
            a, b, c, d = S[i, i], S[i, i + 1], S[i + 1, i], S[i + 1, i + 1]
            m, det = 0.5 * (a + d), a * d - b * c
            w = np.sqrt(complex(m * m - det))
            ev[i], ev[i + 1] = m + w, m - w
            i += 2
        else:
            i += 1
    return ev


def explain_no_dichotomy(eig_start, eig_end, where: str = "") -> str:
    """Message of :class:`~invctl.errors.NoDichotomyError` for internal eigenvalues ``eig_start``
    (at the start equilibrium) and ``eig_end`` (at the end equilibrium)."""
    def fmt(ev):
        return ", ".join(f"{z.real:+.4g}{z.imag:+.4g}i" if abs(z.imag) > 1e-12 else f"{z.real:+.4g}"
                         for z in np.asarray(ev))

    n0 = int(np.sum(np.abs(np.real(eig_start)) <= neutral_tolerance(eig_start)))
    nf = int(np.sum(np.abs(np.real(eig_end)) <= neutral_tolerance(eig_end)))
    u0 = int(np.sum(np.real(eig_start) > neutral_tolerance(eig_start)))
    uf = int(np.sum(np.real(eig_end) > neutral_tolerance(eig_end)))
    if n0 or nf:
        cause = (f"{max(n0, nf)} internal eigenvalue(s) lie on the imaginary axis (neutral: {n0} at the start, "
                 f"{nf} at the end equilibrium): the zero dynamics oscillate or drift without decay, so the "
                 "inverse has no exponential dichotomy and no bounded stable inverse that settles at the "
                 "equilibria; no horizon and no selection with conditions at Tf can fix that")
    else:
        cause = (f"the number of unstable internal modes changes along the reference ({u0} at the start, {uf} at "
                 "the end equilibrium): 003 (36) needs the same split at both ends")
    ivp = ("" if u0 or uf else "; or, if an inverse whose internal motion keeps oscillating after tf is "
           "acceptable, fix every entry at T0 (start with all of q, v, lam, mu, u; end={}) and give T0 = t0 and Tf: "
           "that initial value problem needs no dichotomy")
    return (f"no exponential dichotomy{where}: internal (zero-dynamics) eigenvalues of the inverse model "
            f"{fmt(eig_start)} at the start and {fmt(eig_end)} at the end equilibrium; {cause}. Choose another "
            "output (one whose zero dynamics are hyperbolic, e.g. with damping or a different output "
            "combination) or another reference (end points where the zero dynamics are hyperbolic)" + ivp)


def explain_dichotomy(d: dict, selection: Selection) -> str:
    """A readable explanation of a :func:`dichotomy` report for a failed check."""
    return (f"boundary selection ({selection.describe()}) does not match the modes of the inverse model: "
            f"linearized at the equilibria it has {d['decaying']} modes that decay forward in time (constraint-drift "
            f"modes of the stabilized index reduction and the stable internal dynamics; they must be fixed at T0) "
            f"and {d['growing']} that grow (unstable internal dynamics; fixed at Tf). The selection has {d['n_start']} "
            f"conditions at T0 (rank {d['rank_start']} on the decaying modes) and {d['n_end']} at Tf (rank "
            f"{d['rank_end']} on the growing modes; rank {d['rank_end_tangent']} on the {d['tangent_dim']}-dimensional "
            f"tangent space of the constraint manifold, so {d['n_end'] - d['rank_end_tangent']} of them are redundant "
            f"there: lam, u and constrained coordinates at Tf are fixed by the invariants). The collocation Jacobian "
            f"is singular up to exp(-rate (Tf - T0)). Move conditions to T0 until it has {d['decaying']} and Tf has "
            f"{d['growing']} (e.g. all of q, lam, u and the velocities of the constrained coordinates at T0, the "
            "unstable internal coordinate at Tf), or use formulation='jerk' (no stabilization, ill-conditioned)")
