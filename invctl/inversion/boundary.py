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

import casadi as ca
import numpy as np

from ..errors import BoundaryConditionError, ReferenceSignalError

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
            "or at Tf counts once; fix the unstable internal modes at T0 and the stable ones at Tf"
            + ("" if have > need else " (or pass allow_underdetermined=True with an objective)"),
            diagnostics={"required": need, "given": have, "start": len(s), "end": len(e)})
    return Selection(tuple(s), tuple(e), labels)


class EquilibriumSolver:
    """Equilibria of 003 (1) with the servo constraints: ``v = 0``,

        g(q) = 0,   j(q) = 0,   h(q) = y,   f(q, 0) + G^T lam + J^T mu + B u = 0,

    solved for ``(q, lam, mu, u)`` by Gauss-Newton with exact Jacobians.
    """

    def __init__(self, model):
        self.model = model
        md = model
        n, l, p, m = md.n, md.ell, md.p, md.m
        w = ca.SX.sym("w", n + l + p + m)
        y = ca.SX.sym("y", m)
        q = w[:n]
        lam, mu, u = w[n:n + l], w[n + l:n + l + p], w[n + l + p:]
        zero_v = ca.SX.zeros(n)
        sub = lambda e: ca.substitute([ca.SX(e)], [md.q, md.v], [q, zero_v])[0]  # noqa: E731
        bal = sub(md.f) + ca.mtimes(sub(md.B), u)
        if l:
            bal = bal + ca.mtimes(sub(md.G).T, lam)
        if p:
            bal = bal + ca.mtimes(sub(md.J).T, mu)
        res = ca.vertcat(sub(md.g) if l else ca.SX(0, 1), sub(md.j) if p else ca.SX(0, 1), sub(md.h) - y, bal)
        self._F = ca.Function("equilibrium", [w, y, md.theta], [res, ca.jacobian(res, w)])
        self.sizes = (n, l, p, m)

    def solve(self, y, guess_q=None, guess_w=None, *, theta=None, tol: float = 1e-12, max_iter: int = 50,
              where: str = ""):
        """Equilibrium at output ``y``: returns ``X`` (q, 0, lam, mu, u) and the residual norm.

        Raises
        ------
        ReferenceSignalError
            No equilibrium found (``y`` outside the reachable workspace or a bad guess).
        """
        n, l, p, m = self.sizes
        th = self.model.theta_values if theta is None else np.asarray(theta, float)
        if guess_w is not None:
            w = np.array(guess_w, float).ravel()
        else:
            w = np.zeros(n + l + p + m)
            if guess_q is not None:
                w[:n] = np.asarray(guess_q, float).ravel()
        y = np.asarray(y, float).ravel()
        res = np.inf
        for _ in range(max_iter):
            r, Jm = self._F(w, y, th)
            r, Jm = np.array(r).ravel(), np.array(Jm)
            res = float(np.max(np.abs(r))) if r.size else 0.0
            if res < tol:
                break
            dw = np.linalg.lstsq(Jm, -r, rcond=None)[0]
            step = 1.0
            for _ in range(30):
                r2 = np.array(self._F(w + step * dw, y, th)[0]).ravel()
                if np.max(np.abs(r2)) < (1 - 1e-4 * step) * res:
                    break
                step *= 0.5
            w = w + step * dw
        if not np.isfinite(res) or res > max(1e3 * tol, 1e-9):
            raise ReferenceSignalError(
                f"no equilibrium with h(q) = y_ref = {np.round(y, 6).tolist()}{where}: the servo and loop "
                f"constraints are not solvable (residual {res:.3g} after {max_iter} Gauss-Newton steps). "
                "The reference is probably outside the reachable workspace; check y_ref or give a better "
                "initial configuration", diagnostics={"residual": res, "y": y.tolist()})
        X = np.concatenate([w[:n], np.zeros(n), w[n:]])
        return X, res
