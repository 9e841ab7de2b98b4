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

Solves by M
-----------
``a`` and ``S = M^-1 [G; J; h']^T`` (so ``A_z = S^T [G^T J^T B]``) are solves with one symbolic
LDL^T of ``M`` (:class:`invctl.model.linalg.SymmetricSolver`); the jerk level and the Jacobian
``dF/dX`` differentiate them by the implicit-function rule (``d(M^-1 b) = M^-1 (db - dM M^-1 b)``
with the solution frozen), never through the factors: O(n^2) nodes per right-hand side (the
Jacobian of the n-link arm grows like n^2.3 instead of n^3.5).  Above :data:`NUMERIC_SOLVES_NX`
unknowns the same formulas are evaluated with numeric solves (:attr:`ServoModel.rhs_jac_numeric`).
"""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from functools import cached_property

import casadi as ca
import numpy as np

from ..errors import ModelError, PositionOutputError, SingularDecouplingError

FORMULATIONS = ("jerk", "baumgarte")
#: linear solver of :attr:`ServoModel.rhs_jac_numeric`: CasADi's sparse LDL^T (M is symmetric positive
#: definite; 3x faster than LAPACK LU through CasADi at n = 32, benchmarks/bench_scaling.py)
LINSOL = "ldl"
#: above this many unknowns per node (2n + l + p + m) Jacobians of the inverse model are evaluated with
#: numeric solves (:attr:`ServoModel.rhs_jac_numeric`) and the Hermite-Simpson blocks by MX matrix
#: products: 4x faster at 65 unknowns (benchmarks/bench_scaling.py), no gain below ~20
NUMERIC_SOLVES_NX = 20


#: sizes of a :class:`MapMemo`; past them the least recently used entry goes
MAPS_KEPT = 512
BUFFERED_KEPT = 64


def remember(memo: OrderedDict, key, make, limit: int):
    """``memo[key]``, made by ``make()`` when missing; past ``limit`` entries the least recently used one goes."""
    if key in memo:
        memo.move_to_end(key)
        return memo[key]
    out = memo[key] = make()
    while len(memo) > limit:
        memo.popitem(last=False)
    return out


class MapMemo:
    """``fn.map(k)`` and maps called through buffers, memoized per function object while it is alive (an
    entry holds it), the least recently used ones evicted past :data:`MAPS_KEPT` / :data:`BUFFERED_KEPT`
    entries (building a map costs ~0.4 ms, more than evaluating it on a mesh of a few hundred nodes).  A
    :class:`ServoModel` keeps one for its functions, its transcriptions' and the references it samples."""

    def __init__(self, maps_kept: int = MAPS_KEPT, buffered_kept: int = BUFFERED_KEPT):
        self.maps_kept, self.buffered_kept = maps_kept, buffered_kept
        self.maps: OrderedDict = OrderedDict()
        self.buffered: OrderedDict = OrderedDict()

    @staticmethod
    def _get(memo: OrderedDict, key, fn, make, limit: int):
        hit = memo.get(key)
        if hit is not None and hit[0] is not fn:  # the id of a dead function, reused
            del memo[key]
        return remember(memo, key, lambda: (fn, make()), limit)[1]

    def mapped(self, fn: ca.Function, k: int) -> ca.Function:
        """``fn.map(k)``."""
        return self._get(self.maps, (id(fn), k), fn, lambda: fn.map(k), self.maps_kept)

    def buffered_map(self, fn: ca.Function, k: int, once: tuple = ()) -> "Buffered":
        """``fn`` (one-column inputs) at ``k`` points (inputs of ``k`` columns, those numbered in ``once`` of
        one column, the same at every point), called through buffers (:class:`Buffered`)."""
        return self._get(self.buffered, (id(fn), k, once), fn,
                         lambda: Buffered(dense_map(fn, k, once, self)), self.buffered_kept)


class Buffered:
    """``fn`` (dense inputs and outputs) called through CasADi's zero-copy buffers: ``call(*arrays)`` returns
    the outputs as numpy arrays.  Converting a 13 x 400 array to a ``DM`` costs ~1 ms, several times a
    compiled evaluation on it; the buffers are shared, so calls are serialized by a lock."""

    def __init__(self, fn: ca.Function):
        import threading

        self.fn = fn
        self._in = [np.zeros(fn.nnz_in(i)) for i in range(fn.n_in())]
        self._out = [np.zeros(fn.nnz_out(i)) for i in range(fn.n_out())]
        self._shapes = [(fn.size1_out(i), fn.size2_out(i)) for i in range(fn.n_out())]
        self._buf, self._run = fn.buffer()
        for i, a in enumerate(self._in):
            self._buf.set_arg(i, memoryview(a))  # type: ignore[call-arg, arg-type]  # stubs: (i, buffer, size)
        for i, a in enumerate(self._out):
            self._buf.set_res(i, memoryview(a))  # type: ignore[call-arg, arg-type]
        self._lock = threading.Lock()

    def __call__(self, *args) -> list:
        with self._lock:
            for a, v in zip(self._in, args):
                np.copyto(a, np.asarray(v, float).ravel(order="F"))
            self._run()
            return [o.reshape(shape, order="F").copy() for o, shape in zip(self._out, self._shapes)]


def dense_map(fn: ca.Function, k: int, once: tuple, memo: MapMemo | None = None) -> ca.Function:
    """``fn`` at ``k`` points (inputs numbered in ``once`` shared) with dense outputs (a function with dense
    outputs is mapped as it is: through ``memo``'s :meth:`MapMemo.mapped` when no input is shared)."""
    if all(fn.sparsity_out(i).is_dense() for i in range(fn.n_out())):
        if once:
            return fn.map(f"{fn.name()}_at_{k}", "serial", k, list(once), [])
        return fn.map(k) if memo is None else memo.mapped(fn, k)
    ins = [ca.MX.sym(fn.name_in(i), fn.size1_in(i), 1 if i in once else k) for i in range(fn.n_in())]
    out = fn.map(k)(*ins)
    outs = [ca.densify(o) for o in (out if isinstance(out, (list, tuple)) else [out])]
    return ca.Function(f"{fn.name()}_at_{k}", ins, outs)


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

    @cached_property
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
        # what is derived from this servo model lives on it (no module state): the maps of its functions and
        # of the references it samples, its transcriptions (invctl.inversion.cache), its linearizations at
        # points (boundary.tangent_dynamics) and the last quasi-static path (problem.prepare)
        self.maps = MapMemo()
        self.transcriptions: OrderedDict = OrderedDict()
        self.ocp_transcriptions: OrderedDict = OrderedDict()
        self.tangents: OrderedDict = OrderedDict()
        self.quasi_static: dict = {}
        self.derived: dict = {}  # other functions derived from it (parameter sensitivities)

    @cached_property
    def names(self) -> dict[str, list[str]]:
        """Entry names per block (read by every selection and plan: built once; do not modify)."""
        md = self.model
        return {"q": list(md.q_names), "v": [f"{s}_dot" for s in md.q_names],
                "lam": [f"lam{i + 1}" for i in range(md.ell)], "mu": [f"mu{i + 1}" for i in range(md.p)],
                "u": list(md.u_names)}

    @cached_property
    def _sym(self):
        """The right-hand side ``F`` and the residuals with every solve by ``M`` through one shared
        LDL^T factorization (:mod:`invctl.model.linalg`); the derivatives of solutions are written
        by the implicit-function rule, never by AD through the factors (module doc)."""
        from ..model.linalg import SymmetricSolver

        md, L = self.model, self.layout
        X = ca.SX.sym("X", L.nx)
        Y = ca.SX.sym("Y", 4 * L.m)
        b = L.blocks
        q, v, z = X[b["q"]], X[b["v"]], X[2 * L.n:]

        def s(e):
            return ca.substitute([ca.SX(e)], [md.q, md.v], [q, v])[0]

        M, f, B, G, J, j, h = (s(e) for e in (md.M, md.f, md.B, md.G, md.J, md.j, md.h))
        yr, yd, ydd, yddd = (Y[k * L.m:(k + 1) * L.m] for k in range(4))
        H = ca.jacobian(h, q)
        # z = (lam, mu, u) enters the forces through W = [G^T J^T B]; the velocity-level rows are C v + c0
        W = ca.horzcat(*([G.T] if L.l else []), *([J.T] if L.p else []), B)
        C = ca.vertcat(*([G] if L.l else []), *([J] if L.p else []), H)
        force = f + ca.mtimes(W, z)
        solver = SymmetricSolver(M)
        A = ca.SX.sym("A", L.n)  # frozen acceleration: a = M^-1 force solves force - M A = 0
        # constraint residuals by level (rows: holonomic, non-holonomic, servo)
        phi_p = ca.vertcat(ca.SX(0, 1) if not L.l else s(md.g), h - yr)
        vel_h = ca.mtimes(G, v) if L.l else ca.SX(0, 1)
        vel_n = (ca.mtimes(J, v) + j) if L.p else ca.SX(0, 1)
        vel_s = ca.mtimes(H, v) - yd
        phi_v = ca.vertcat(vel_h, vel_n, vel_s)
        # acceleration level at v' = A: C A + d/dt(C) v (+ j' v) - (0, 0, y'')
        Cv = ca.vertcat(vel_h, vel_n, ca.mtimes(H, v))
        ydd_pad = ca.vertcat(ca.SX.zeros(L.l + L.p), ydd)
        phi_a_A = ca.mtimes(C, A) + ca.jtimes(Cv, q, v) - ydd_pad
        # jerk level (z frozen, z' unknown): C a' + [d/dt phi_a at frozen A], a' = M^-1 (r1 + W z'),
        # r1 = d/dt (force - M A) at frozen A and z (the implicit derivative of a along the motion)
        resid = force - ca.mtimes(M, A)
        r1 = ca.jtimes(resid, q, v) + ca.jtimes(force, v, A)
        Yd = ca.vertcat(yd, ydd, yddd, ca.SX.zeros(L.m))
        r2 = ca.jtimes(phi_a_A, ca.vertcat(q, v, Y), ca.vertcat(v, A, Yd))
        if self.formulation == "baumgarte":
            w = self.omega
            nh, nn = L.l, L.p
            parts = []
            if nh:
                parts.append(3 * w * phi_a_A[:nh] + 3 * w**2 * phi_v[:nh] + w**3 * phi_p[:nh])
            if nn:
                parts.append(2 * w * phi_a_A[nh:nh + nn] + w**2 * phi_v[nh:nh + nn])
            parts.append(3 * w * phi_a_A[nh + nn:] + 3 * w**2 * phi_v[nh + nn:] + w**3 * phi_p[nh:])
            r2 = r2 + ca.vertcat(*parts)
        # S = M^-1 C^T: A_z = C M^-1 W = S^T W (the decoupling matrix), C M^-1 r1 = S^T r1
        k = C.shape[0]
        Sh = ca.SX.sym("S", L.n, k)
        Uh = ca.SX.sym("U", L.n, k + 1)
        Wr = ca.horzcat(W, r1)
        # T = S^T [W r1] plus a term that vanishes at S = M^-1 C^T, U = M^-1 [W r1] and whose
        # q-derivative is the variation of S: d(S^T y) = S^T dy + (dC - S^T dM) M^-1 y
        T = ca.mtimes(Sh.T, Wr) + ca.mtimes(C, Uh) - ca.mtimes(Sh.T, ca.mtimes(M, Uh))
        zdot_T = -ca.solve(T[:, :k], T[:, k] + r2)
        # values
        a = solver.solve(force)
        S = solver.solve(C.T)
        sub_a = lambda e: ca.substitute(e, A, a)  # noqa: E731
        Az = ca.mtimes(S.T, W)
        zdot = -ca.solve(Az, ca.mtimes(S.T, sub_a(r1)) + sub_a(r2))
        F = ca.vertcat(v, a, zdot)
        return {"X": X, "Y": Y, "F": F, "a": a, "phi_p": phi_p, "phi_v": phi_v, "phi_a": sub_a(phi_a_A),
                "Az": Az, "h": h, "solver": solver, "A": A, "S": S, "Sh": Sh, "Uh": Uh, "Wr": Wr, "resid": resid,
                "zdot_T": zdot_T, "phi_a_A": phi_a_A, "M": M, "C": C, "force": force}

    def _da_dX(self):
        """``da/dX`` by the implicit-function rule: ``M^-1 d(force - M A)/dX`` at ``A = a``."""
        from ..model.linalg import solve_derivative

        S = self._sym
        return solve_derivative(S["solver"], S["resid"], S["A"], S["a"], S["X"])

    def _fn(self, name, outs, out_names):
        md, S = self.model, self._sym
        return ca.Function(name, [S["X"], S["Y"], md.theta], outs, ["X", "Y", "theta"], out_names)

    @cached_property
    def rhs(self) -> ca.Function:
        """``(X, Y, theta) -> F``: the index-reduced inverse model ``X' = F``."""
        return self._fn("servo_rhs", [self._sym["F"]], ["F"])

    @cached_property
    def rhs_jac(self) -> ca.Function:
        """``(X, Y, theta) -> (F, dF/dX)`` (dense Jacobian, for assembled Newton steps).

        ``d a/dX = M^-1 d(force - M A)/dX`` and ``d z'/dX`` by the chain rule through the frozen
        acceleration ``A`` and the frozen solves ``S``, ``U`` (their variations are carried by the
        term of ``T`` that vanishes at the solution), so no derivative passes through the factors."""
        S = self._sym
        X, n = S["X"], self.layout.n
        da = self._da_dX()
        Z = S["zdot_T"]
        U = S["solver"].solve(ca.substitute(S["Wr"], S["A"], S["a"]))
        frozen = ca.vertcat(S["A"], ca.vec(S["Sh"]), ca.vec(S["Uh"]))
        values = ca.vertcat(S["a"], ca.vec(S["S"]), ca.vec(U))
        part = ca.Function("zdot_jac", [X, S["Y"], self.model.theta, frozen],
                           [ca.jacobian(Z, X), ca.jacobian(Z, S["A"])])
        jZX, jZA = part(X, S["Y"], self.model.theta, values)
        dzdot = jZX + ca.mtimes(jZA, da)
        nx = X.shape[0]
        dv = ca.horzcat(ca.SX(n, n), ca.SX.eye(n), ca.SX(n, nx - 2 * n))
        return self._fn("servo_rhs_jac", [S["F"], ca.densify(ca.vertcat(dv, da, dzdot))], ["F", "dFdX"])

    @property
    def jacobian_evaluator(self) -> ca.Function:
        """The Jacobian function for numeric evaluation: :attr:`rhs_jac_numeric` above
        :data:`NUMERIC_SOLVES_NX` unknowns (cheaper to build and to evaluate), :attr:`rhs_jac` below."""
        return self.rhs_jac_numeric if self.layout.nx > NUMERIC_SOLVES_NX else self.rhs_jac

    @cached_property
    def rhs_jac_numeric(self) -> ca.Function:
        """``rhs_jac`` with the solves by ``M`` done numerically (MX, an LDL^T of ``M`` per evaluation)
        instead of with the symbolic factors: the same formulas, for large models, where the
        O(n^2 nx) SX instructions of the symbolic triangular solves dominate.  Not callable with
        SX arguments."""
        S, L, th = self._sym, self.layout, self.model.theta
        X, Y, A = S["X"], S["Y"], S["A"]
        n, nx, k = L.n, L.nx, S["Sh"].shape[1]
        f1 = ca.Function("servo_parts1", [X, th], [S["M"], S["force"], S["C"].T])
        f2 = ca.Function("servo_parts2", [X, Y, th, A], [S["Wr"], ca.jacobian(S["resid"], X)])
        frozen = ca.vertcat(A, ca.vec(S["Sh"]), ca.vec(S["Uh"]))
        Z = S["zdot_T"]
        f3 = ca.Function("servo_parts3", [X, Y, th, frozen], [Z, ca.jacobian(Z, X), ca.jacobian(Z, A)])
        Xm, Ym, Tm = ca.MX.sym("X", nx), ca.MX.sym("Y", Y.numel()), ca.MX.sym("theta", th.numel())
        Mm, force, CT = f1(Xm, Tm)
        sol = ca.solve(Mm, ca.horzcat(force, CT), LINSOL)
        a, Sm = sol[:, 0], sol[:, 1:]
        Wr, D1 = f2(Xm, Ym, Tm, a)
        sol2 = ca.solve(Mm, ca.horzcat(Wr, D1), LINSOL)
        U, da = sol2[:, :k + 1], sol2[:, k + 1:]
        zdot, jZX, jZA = f3(Xm, Ym, Tm, ca.vertcat(a, ca.vec(Sm), ca.vec(U)))
        J = ca.vertcat(ca.horzcat(ca.MX(n, n), ca.MX.eye(n), ca.MX(n, nx - 2 * n)), da, jZX + ca.mtimes(jZA, da))
        return ca.Function("servo_rhs_jac_numeric", [Xm, Ym, Tm], [ca.vertcat(Xm[n:2 * n], a, zdot), J],
                           ["X", "Y", "theta"], ["F", "dFdX"])

    @cached_property
    def residuals(self) -> ca.Function:
        """``(X, Y, theta) -> (pos, vel, acc, dyn)`` constraint residuals of (35) and the
        acceleration level; ``dyn`` is zero by construction (kept for reports)."""
        S = self._sym
        return self._fn("servo_residuals", [S["phi_p"], S["phi_v"], S["phi_a"]], ["pos", "vel", "acc"])

    @property
    def linearization(self) -> Buffered:
        """``(X, Y, theta) -> (dF/dX, C)``: the Jacobian of the inverse model and of the constraint residuals
        (:attr:`constraint_jacobian`) at one point, in one call through buffers (the linearizations of
        the plan and the dichotomy check at the equilibria); ``dF/dX`` by the compiled ``rhs_jac`` once a
        transcription has it (:meth:`use_compiled`)."""
        rj = self.__dict__.get("_compiled_rhs_jac")
        cj = self.__dict__.get("_compiled_constraint_jacobian")
        made = self.__dict__.setdefault("_linearizations", {})
        if rj is not None:
            hit = made.get("compiled")
            if hit is None or hit[0] is not rj or hit[1] is not cj:
                made["compiled"] = hit = (rj, cj, self._linearization(rj))
            return hit[2]
        if "vm" not in made:
            made["vm"] = (None, None, self._linearization(self.jacobian_evaluator))
        return made["vm"][2]

    def use_compiled(self, rhs_jac: ca.Function | None = None, residuals: ca.Function | None = None,
                     decoupling: ca.Function | None = None, constraint_jacobian: ca.Function | None = None) -> None:
        """Evaluate numerically with the compiled equivalents given (``None``: keep what is set): ``rhs_jac`` in
        :attr:`linearization` with ``constraint_jacobian``, the others through :meth:`evaluator`.  With all of
        them from the disk cache a first solve builds no SX function of the model."""
        for name, fn in (("rhs_jac", rhs_jac), ("residuals", residuals), ("decoupling", decoupling),
                         ("constraint_jacobian", constraint_jacobian)):
            if fn is not None:
                self.__dict__[f"_compiled_{name}"] = fn

    def evaluator(self, name: str) -> ca.Function:
        """``residuals``, ``decoupling``, ``constraint_jacobian`` for numeric evaluation: the compiled equivalent
        once set (:meth:`use_compiled`), else the SX function."""
        return self.__dict__.get(f"_compiled_{name}") or getattr(self, name)

    def disk_piece(self, name: str, key: str) -> ca.Function | None:
        """The compiled function ``name`` of this model from the disk cache (cache key ``key``), loaded once;
        ``None`` while it is not there."""
        from .compiled import cache_dir, load_cached

        memo = self.__dict__.setdefault("_disk_pieces", {})
        where = (name, key, str(cache_dir()))
        hit = memo.get(where)
        if hit is None:
            hit = load_cached(name, key)
            if hit is not None:
                memo[where] = hit
        return hit

    def _linearization(self, jac: ca.Function) -> Buffered:
        X, Y, th = (ca.MX.sym(k, *s) for k, s in (("X", (self.layout.nx, 1)), ("Y", (4 * self.layout.m, 1)),
                                                   ("theta", self.model.theta.shape)))
        return Buffered(ca.Function("servo_linearization", [X, Y, th],
                                    [ca.densify(jac(X, Y, th)[1]),
                                     ca.densify(self.evaluator("constraint_jacobian")(X, Y, th))]))

    @cached_property
    def constraint_jacobian(self) -> ca.Function:
        """``(X, Y, theta) -> C``: Jacobian w.r.t. ``X`` of the stacked position, velocity and
        acceleration residuals; its null space is the tangent space of the constraint manifold."""
        S = self._sym
        X, A = S["X"], S["A"]
        pos_vel = ca.vertcat(S["phi_p"], S["phi_v"])
        dacc = ca.substitute(ca.jacobian(S["phi_a_A"], X) + ca.mtimes(ca.jacobian(S["phi_a_A"], A), self._da_dX()),
                             A, S["a"])
        return self._fn("servo_constraint_jac", [ca.densify(ca.vertcat(ca.jacobian(pos_vel, X), dacc))], ["C"])

    @cached_property
    def output(self) -> ca.Function:
        """``(X, Y, theta) -> y = h(q)``."""
        return self._fn("servo_output", [self._sym["h"]], ["y"])

    @cached_property
    def decoupling(self) -> ca.Function:
        """``(X, Y, theta) -> A_z``: the matrix solved for ``z'`` (must be invertible)."""
        return self._fn("servo_Az", [self._sym["Az"]], ["Az"])

    def reference_samples(self, reference, t) -> np.ndarray:
        """``Y = (y, y', y'', y''')`` at times ``t``: shape ``(4m, len(t))``.

        A :class:`~invctl.reference.Reference` is constant outside ``[t0, tf]``: times before ``t0``
        (after ``tf``) take its samples at ``t0 - (tf - t0)`` (``tf + (tf - t0)``), so only the times of
        ``[t0, tf]`` are evaluated; the last few sample sets are remembered, so re-solves on the same mesh,
        or on a horizon that moved only outside ``[t0, tf]``, evaluate nothing.  A reference that is not at
        rest at one and two transition lengths outside (different values, or a derivative not zero: a
        periodic signal has equal values there) is evaluated at every time."""
        t = np.atleast_1d(np.asarray(t, float))
        # two memos: the evaluated sample sets, and whole answers per time set (a held re-solve asks for the
        # same times again: no probes); a re-planned solve asks for about ten sets, so each keeps 16
        done = self.__dict__.setdefault("_samples_of_times", OrderedDict())
        memo = self.__dict__.setdefault("_samples", OrderedDict())
        return MapMemo._get(done, (id(reference), t.tobytes()), reference,
                            lambda: self._reference_samples(reference, t, memo), 16).copy()

    def _reference_samples(self, reference, t, memo) -> np.ndarray:
        t0, tf = reference.t0, reference.tf

        def sample(ts):
            return MapMemo._get(memo, (id(reference), ts.tobytes()), reference,
                                lambda: (np.vstack(self.maps.buffered_map(reference.function(3), ts.size)(ts))
                                         if ts.size else np.zeros((4 * reference.m, 0))), 16)

        before, after = t < t0, t > tf
        if not (before.any() or after.any()):
            return sample(t).copy()
        tau = tf - t0
        inside = ~(before | after)
        # the probes and the times inside in one evaluation (one map for a reference sampled once)
        both = sample(np.r_[t0 - 2 * tau, t0 - tau, tf + tau, tf + 2 * tau, t[inside]])
        rest = both[:, :4]
        m = reference.m
        if not (np.array_equal(rest[:, 0], rest[:, 1]) and np.array_equal(rest[:, 2], rest[:, 3])
                and not np.any(rest[m:])):  # at rest there: equal values and zero derivatives at both probes
            return sample(t).copy()
        Y = np.empty((4 * reference.m, t.size))
        Y[:, inside] = both[:, 4:]
        Y[:, before] = rest[:, 1:2]
        Y[:, after] = rest[:, 2:3]
        return Y


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


def _decoupling_scales(model, Q, maps: MapMemo | None = None) -> np.ndarray:
    """``||C M^-1||_2 ||W||_2`` at the configurations ``Q`` (columns), ``C = [G; J; h']``,
    ``W = [G^T J^T B]`` (numerically; the scale of the product ``A_z = C M^-1 W``).  The parts
    come from one mapped evaluation (memoized in ``maps``) of a function the model keeps."""
    from ..analysis.auxiliary import cached

    def build():
        H = ca.jacobian(model.h, model.q)
        return ca.Function("decoupling_parts", [model.q, model.theta],
                           [model.M, ca.vertcat(model.G, model.J, H), ca.horzcat(model.G.T, model.J.T, model.B)])

    parts = cached(model, ("decoupling_parts",), build)
    K, n = Q.shape[1], model.n
    M, C, W = (maps or MapMemo()).buffered_map(parts, K, once=(1,))(Q, model.theta_values)
    M = M.reshape(n, K, n).transpose(1, 0, 2)
    C = C.reshape(C.shape[0], K, n).transpose(1, 0, 2)
    W = W.reshape(n, K, -1).transpose(1, 0, 2)
    CMinvT = np.linalg.solve(M, C.transpose(0, 2, 1))
    if CMinvT.shape == W.shape:  # both 2-norms from one batched SVD
        sv = np.linalg.svd(np.concatenate([CMinvT, W]), compute_uv=False)[:, 0]
        return sv[:K] * sv[K:]
    return np.linalg.norm(CMinvT, 2, axis=(1, 2)) * np.linalg.norm(W, 2, axis=(1, 2))


def check_decoupling(model, Az, times, Q, rcond: float = 1e-10, maps: MapMemo | None = None) -> None:
    """Raise :class:`SingularDecouplingError` where the decoupling matrices ``Az`` (shape
    ``(k, k, K)`` at ``times``, configurations ``Q``) are singular (smallest over largest singular
    value below ``rcond``): there the vector relative degree is not (2, ..., 2).  ``maps``: where the
    map of the check's function is memoized (the servo model's)."""
    sv = np.linalg.svd(Az.transpose(2, 0, 1), compute_uv=False)
    # A_z = (C M^-1) W: a singular value that is only rounding of that product counts as zero, so the
    # ratio is taken against ||C M^-1|| ||W|| too (a 1 x 1 A_z has sigma_min = sigma_max)
    ratio = sv[:, -1] / np.maximum(np.maximum(sv[:, 0], _decoupling_scales(model, Q, maps)), 1e-300)
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
