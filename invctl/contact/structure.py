"""The structure of the open system of 000 Sect. 2: independent subsystems, their actuation and the
contacts between them.

With all clearances open, the mass matrix is block-diagonal, ``M = blockdiag(M_1(q_1), ...,
M_nind(q_nind))``, and so are ``C`` and ``g``; the subsystems interact only through the contact
forces ``grad f(q) lam`` whose gradients have the block pattern of 000 (2)-(3)
(``df_ij/dq = (0, ..., M_ij^T, ..., M_ji^T, ..., 0)``).  :func:`open_structure` finds the subsystems
of any :class:`~invctl.model.Model` from the couplings of its coordinates (entries of ``M``,
dependencies of ``f``, rows of bilateral constraints; for linkage models also the bodies: a floating
body's coordinates are decoupled in ``M``, ``C`` and ``g`` but belong to one subsystem), and classifies each one as fully actuated,
underactuated or unactuated from the rank of its rows of the input matrix (000 Example 2); a
subsystem that is not fully actuated and shares a contact with an actuated one is the object of a
juggling structure (000 Sect. 4, (23)).  For models built by :class:`~invctl.contact.linkage.Linkage`
it also reports whether the centre of mass of a floating subsystem is actuated, and the degree of
actuation of the clearance-free system (000 Assumption 1).

:func:`subsystem_report` is a ready-made ``compute`` for an ``analyze``
:class:`~invctl.scenes.Report`; :func:`contact_blocks` evaluates the blocks ``M_ij`` of (3).
"""
from __future__ import annotations

from typing import Any

from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..errors import ModelError


@dataclass(frozen=True)
class SubsystemInfo:
    """One subsystem ``S_i``: its coordinates, DoFs, actuators and status."""

    name: str
    coordinates: tuple
    q_names: tuple
    dof: int
    actuators: int
    status: str                     # "fully actuated" | "underactuated" | "unactuated"
    com_actuated: bool | None = None  # floating linkage subsystems: can the inputs move its centre of mass?


@dataclass(frozen=True)
class Structure:
    """The open system's structure (module docstring).

    Attributes
    ----------
    n, n_ind : int
        Coordinates (DoFs when there are no bilateral constraints) and independent subsystems.
    subsystems : tuple of SubsystemInfo
    contacts : tuple of (gap name, label, subsystem indices)
        ``label`` like ``"S1-S2"`` or ``"S3-ground"`` (000 (3): ``f_12``, ``f_30``).
    off_block : float
        Largest entry of ``M`` outside the subsystem blocks at the sample points (0 for an open system).
    juggling : tuple of str
        Subsystems that are not fully actuated and touch an actuated subsystem through a contact.
    """

    n: int
    n_ind: int
    subsystems: tuple
    contacts: tuple
    off_block: float
    juggling: tuple


def components(nodes, edges) -> list[list]:
    """Connected components of the graph (``nodes``, ``edges``), each in the order of ``nodes``, ordered by
    their first node (union-find with path halving)."""
    parent = {x: x for x in nodes}

    def find(x):
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for i, j in edges:
        parent[find(i)] = find(j)
    groups: dict[Any, list] = {}
    for x in nodes:
        groups.setdefault(find(x), []).append(x)
    return list(groups.values())


def _samples(model, q, samples, rng):
    r = np.random.default_rng(rng)
    if q is not None:   # around q: gap gradients may vanish at q itself (a centred journal)
        q = np.asarray(q, float).ravel()
        return [q] + [q + r.uniform(-0.05, 0.05, model.n) for _ in range(samples)]
    return [r.uniform(-1, 1, model.n) for _ in range(samples)]


def open_structure(model, q=None, *, samples: int = 3, tol: float = 1e-12, rng: int = 1) -> Structure:
    """Subsystems, actuation and contact pattern of ``model`` (module docstring).

    Couplings are read from the numeric entries of ``M``, ``d f / d(q, v)``, ``G`` and the input rows
    at ``q`` (or ``samples`` random configurations), so structurally present but vanishing entries
    do not couple.
    """
    n, th = model.n, model.theta_values
    if n == 0:
        raise ModelError(f"model {model.name!r} has no coordinates")
    fM, fB = model.function("M"), model.function("B")
    df = ca.Function("df", [model.q, model.v, model.theta], [ca.jacobian(model.f, ca.vertcat(model.q, model.v))])
    W = ca.Function("W", [model.q, model.theta], [ca.jacobian(ca.vertcat(*[g.expr for g in model.gaps]), model.q)
                                                  if model.gaps else ca.SX(0, n)])
    qs = _samples(model, q, samples, rng)
    r = np.random.default_rng(rng + 1)
    Mabs = np.zeros((n, n))
    couple = np.zeros((n, n), bool)
    Wabs = np.zeros((len(model.gaps), n))
    Bs = []
    for qk in qs:
        M = np.array(fM(qk, th))
        Mabs = np.maximum(Mabs, np.abs(M))
        D = np.abs(np.array(df(qk, r.uniform(-1, 1, n), th)))
        couple |= (D[:, :n] > tol) | (D[:, n:] > tol)
        if model.ell:
            G = np.abs(np.array(model.function("G")(qk, th)))
            for row in G:
                idx = np.flatnonzero(row > tol)
                couple[np.ix_(idx, idx)] = True
        Wabs = np.maximum(Wabs, np.abs(np.array(W(qk, th)).reshape(-1, n)))
        Bs.append(np.array(fB(qk, th)).reshape(n, model.m))
    scale = max(1.0, Mabs.max())
    couple |= Mabs > tol * scale
    edges = [(i, j) for i in range(n) for j in range(n) if i != j and couple[i, j]]
    link = getattr(model, "linkage", None)
    if link is not None:    # a floating body's x, y, phi are decoupled in M, C, g but belong together
        for sub in link.subsystems:
            edges += [(sub.coordinates[0], c) for c in sub.coordinates[1:]]
    groups = components(range(n), edges)
    label = np.empty(n, int)
    for k, g in enumerate(groups):
        label[g] = k
    off = float(max((Mabs[i, j] for i in range(n) for j in range(n) if label[i] != label[j]), default=0.0))
    subs = []
    for k, g in enumerate(groups):
        rank = max(int(np.linalg.matrix_rank(Bk[g, :], tol=1e-9 * max(1.0, np.abs(Bk).max()))) if model.m else 0
                   for Bk in Bs)
        dof = len(g)
        if model.ell:
            G = np.array(model.function("G")(qs[0], th))
            dof -= int(np.linalg.matrix_rank(G[:, g])) if G.size else 0
        status = "fully actuated" if rank >= dof else ("unactuated" if rank == 0 else "underactuated")
        com = None
        if link is not None and status != "fully actuated":
            com = _com_actuated(link, model, g, Bs[0])
        subs.append(SubsystemInfo(f"S{k + 1}", tuple(g), tuple(model.q_names[i] for i in g), dof, rank, status, com))
    contacts = []
    for i, gp in enumerate(model.gaps):
        touched = sorted({int(label[j]) for j in np.flatnonzero(Wabs[i] > tol * max(1.0, Wabs[i].max()))})
        names = [subs[t].name for t in touched]
        lab = "-".join(names) if len(names) > 1 else (f"{names[0]}-ground" if names else "none")
        contacts.append((gp.name, lab, tuple(touched)))
    actuated = {k for k, s in enumerate(subs) if s.actuators > 0}
    jug = sorted({subs[t].name for _, _, touched in contacts if len(touched) > 1 and set(touched) & actuated
                  for t in touched if subs[t].status != "fully actuated"})
    return Structure(n, len(subs), tuple(subs), tuple(contacts), off, tuple(jug))


def _com_actuated(link, model, coords, B) -> bool | None:
    """Floating linkage subsystem: do the inputs act on the translation of its root (hence on its
    centre of mass)?  None when the subsystem is attached to the ground."""
    for sub in link.subsystems:
        if set(sub.coordinates) == set(coords):
            if sub.grounded:
                return None
            xy = sub.coordinates[:2]
            return bool(np.any(np.abs(B[xy, :]) > 1e-12))
    return None


def contact_blocks(model, q) -> dict:
    """The blocks ``M_ij`` of 000 (2)-(3) at ``q``: ``{gap name: {subsystem name: gradient block}}``
    (the rows of ``grad f_k`` belonging to each subsystem the gap touches)."""
    st = open_structure(model, q)
    W = np.array(ca.Function("W", [model.q, model.theta], [ca.jacobian(ca.vertcat(*[g.expr for g in model.gaps]),
                                                                        model.q)])(np.asarray(q, float),
                                                                                   model.theta_values))
    out = {}
    for k, (name, _, touched) in enumerate(st.contacts):
        out[name] = {st.subsystems[t].name: W[k, list(st.subsystems[t].coordinates)] for t in touched}
    return out


def _clearance_free(model, q):
    """Degree of actuation of the clearance-free system (000 Assumption 1) of a linkage model."""
    link = getattr(model, "linkage", None)
    if link is None or link.closure.shape[0] == 0:
        return {}
    Gq = np.array(ca.Function("Gq", [model.q, model.theta], [ca.jacobian(link.closure, model.q)])(q, model.theta_values))
    B = np.array(model.function("B")(q, model.theta_values)).reshape(model.n, model.m)
    rank_g = int(np.linalg.matrix_rank(Gq))
    dim = model.n - rank_g
    _, s, Vt = np.linalg.svd(Gq)
    N = Vt[rank_g:].T                       # tangent directions of the clearance-free configuration space
    E = N.T @ B
    rank_e = int(np.linalg.matrix_rank(E, tol=1e-9 * max(1.0, np.abs(E).max()))) if E.size else 0
    p = model.m
    kind = ("fully actuated" if p == dim and rank_e == dim else "overactuated" if p > dim and rank_e == dim
            else "underactuated")
    return {"clearance-free DoFs (dim q_wc)": dim, "actuators p": p, "rank E_wc": rank_e,
            "clearance-free system (000 Assumption 1)": f"{kind} (p = {p}, dim q_wc = {dim}, rank E_wc = {rank_e})"}


def subsystem_report(ctx) -> dict:
    """``compute`` of an ``analyze`` :class:`~invctl.scenes.Report`: the open system's subsystems, their
    actuation, the contacts between them and the clearance-free degree of actuation (000 Sect. 2,
    Example 2, Assumption 1)."""
    model = ctx.model
    q = None
    link = getattr(model, "linkage", None)
    if link is not None and getattr(link, "nominal", None) is not None:
        q = link.nominal
    st = open_structure(model, q)
    out: dict[str, Any] = {"n (open system)": st.n, "n_ind": st.n_ind, "unilateral constraints m_u": len(model.gaps)}
    for s in st.subsystems:
        bodies = ""
        if link is not None:
            for sub in link.subsystems:
                if set(sub.coordinates) == set(s.coordinates):
                    bodies = f"({', '.join(sub.bodies)}) "
        text = (f"{bodies}q = ({', '.join(s.q_names)}): {s.dof} DoF, {s.actuators} actuator"
                f"{'s' if s.actuators != 1 else ''}: {s.status}")
        if s.com_actuated is False:
            text += ", centre of mass unactuated"
        out[s.name] = text
    out["DoFs per subsystem"] = [s.dof for s in st.subsystems]
    out["contacts"] = ", ".join(f"{name}: {lab}" for name, lab, _ in st.contacts)
    out["M block-diagonal (largest off-block entry)"] = st.off_block
    out["juggling structure (unactuated or underactuated, touching an actuated one)"] = (
        ", ".join(st.juggling) if st.juggling else "none")
    if link is not None:
        out.update(_clearance_free(model, np.zeros(model.n) if q is None else q))
    return out
