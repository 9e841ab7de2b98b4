"""The multibody model in the DAE form of 003 (1), with unilateral gaps (000 (1)).

    q' = v
    M(q) v' = f(q, v) + J(q)^T mu + G(q)^T lam + B(q) u
    0 = J(q) v + j(q)              (p non-holonomic constraints)
    0 = g(q),   G = g'(q)          (l holonomic constraints)
    y = h(q, v)                    (m outputs)
    f_i(q) >= 0                    (unilateral gaps, restitution e_i)

All expressions are CasADi SX in ``q``, ``v`` and the parameter column
``theta``; parameter *values* live beside them, so a reference model and a
mismatched plant share one symbolic model (``with_params``).
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
from functools import cached_property
from typing import Mapping, Sequence

import casadi as ca
import numpy as np

from ..errors import DimensionError, ModelError, ParameterError
from .params import DerivedRule, ParamSet, resolve_params
from .region import OperatingRegion


@dataclass(frozen=True)
class Gap:
    """A unilateral constraint ``f(q) >= 0`` with Newton restitution ``e``.

    ``restitution`` may be a number or the name of a model parameter.
    """

    name: str
    expr: ca.SX
    restitution: float | str = 0.0


def _col(x, name: str) -> ca.SX:
    if x is None:
        return ca.SX(0, 1)
    x = ca.SX(x)
    if x.shape[1] != 1 and x.shape[0] == 1:
        x = x.T
    if x.shape[1] != 1:
        raise DimensionError(f"{name} must be a column vector, got shape {x.shape}")
    return x


#: a mass matrix whose condition number exceeds this is singular in double precision (it resolves
#: fewer than one digit): its parameter values leave the range the model can be evaluated in
MAX_MASS_CONDITION = 1e15


class Model:
    """A symbolic multibody model in the form 003 (1).

    Parameters
    ----------
    name : str
        Name used in reports and errors.
    q, v : casadi.SX
        Column symbols of generalized coordinates and velocities (length n).
    params : ParamSet
        The parameter symbols used in the expressions.
    values : mapping
        Default parameter values (every name of ``params``).
    M, f, B : casadi.SX
        Mass matrix (n x n), generalized forces (n), input matrix (n x m).
    h : casadi.SX
        Output (m), a function of ``q`` and ``v``.
    g, G : casadi.SX, optional
        Holonomic constraints (l) and their Jacobian; ``G`` is derived when
        omitted and checked against ``g'`` when given.
    J, j : casadi.SX, optional
        Non-holonomic constraints ``J(q) v + j(q) = 0`` (p).
    gaps : sequence of Gap, optional
        Unilateral constraints.
    derived : mapping name -> rule, optional
        Derived parameters that follow their base parameters (e.g. ``X3``).
    region : OperatingRegion, optional
        Where the analysis is claimed to hold; used for sampling checks.
    q_names, u_names, y_names : sequence of str, optional
        Signal names for reports and plots.
    validate : bool
        Check dimensions, ``G = g'``, symmetry and positive definiteness of M
        at sample points, and ``l + p + m <= n`` on construction.
    """

    def __init__(
        self,
        name: str,
        q: ca.SX,
        v: ca.SX,
        params: ParamSet,
        values: Mapping[str, float],
        *,
        M,
        f,
        B,
        h=None,
        g=None,
        G=None,
        J=None,
        j=None,
        gaps: Sequence[Gap] = (),
        derived: Mapping[str, DerivedRule] | None = None,
        region: OperatingRegion | None = None,
        q_names: Sequence[str] | None = None,
        u_names: Sequence[str] | None = None,
        y_names: Sequence[str] | None = None,
        overrides: Mapping[str, float] | None = None,
        validate: bool = True,
    ):
        self.name = name
        self.q = _col(q, "q")
        self.v = _col(v, "v")
        self.params = params
        self.theta = params.sym
        self.derived = dict(derived or {})
        missing = sorted(set(params.names) - set(values))
        if missing:
            raise ParameterError(f"model {name!r}: no value given for parameter(s) {missing}")
        self.defaults = {k: float(values[k]) for k in params.names}
        self.overrides = dict(overrides or {})
        self.values = resolve_params(self.defaults, self.derived, self.overrides)
        self.M = ca.SX(M)
        self.f = _col(f, "f")
        self.B = ca.SX(B)
        self.g = _col(g, "g")
        self.J = ca.SX(J) if J is not None else ca.SX(0, self.q.shape[0])
        self.j = _col(j, "j")
        self.h = _col(h, "h") if h is not None else ca.SX(0, 1)
        self._G_given = G is not None
        self.G = ca.SX(G) if G is not None else ca.jacobian(self.g, self.q)
        self.gaps = tuple(gaps)
        self.region = region
        self.q_names = list(q_names) if q_names else [f"q{i + 1}" for i in range(self.n)]
        self.u_names = list(u_names) if u_names else [f"u{i + 1}" for i in range(self.m)]
        self.y_names = list(y_names) if y_names else [f"y{i + 1}" for i in range(self.h.shape[0])]
        self._functions: dict[str, ca.Function] = {}
        # objects derived from the symbols (analysis, inversion: invctl.analysis.auxiliary.cache_of), made here
        # so that with_params copies, which share the symbols, share them
        self._analysis_cache: dict = {}
        self._check_dimensions()
        if validate:
            self.validate()

    # ------------------------------------------------------------------ sizes
    @property
    def n(self) -> int:
        """Number of generalized coordinates."""
        return self.q.shape[0]

    @property
    def m(self) -> int:
        """Number of inputs."""
        return self.B.shape[1]

    @property
    def ell(self) -> int:
        """Number of holonomic constraints (l in 003)."""
        return self.g.shape[0]

    @property
    def p(self) -> int:
        """Number of non-holonomic constraints."""
        return self.j.shape[0]

    @property
    def ny(self) -> int:
        """Number of outputs."""
        return self.h.shape[0]

    @property
    def theta_values(self) -> np.ndarray:
        """Parameter values in the order of ``params.names``."""
        return np.array([self.values[k] for k in self.params.names], float)

    # ------------------------------------------------------------ construction
    @classmethod
    def from_lagrangian(
        cls,
        name: str,
        q: ca.SX,
        v: ca.SX,
        params: ParamSet,
        values: Mapping[str, float],
        *,
        T,
        V=0,
        Q=None,
        B,
        **kwargs,
    ) -> "Model":
        """Build ``M`` and ``f`` from kinetic energy ``T(q, v)``, potential ``V(q)``
        and non-conservative generalized forces ``Q(q, v)`` by CasADi differentiation.

        ``M = d^2T/dv^2`` and ``f = Q - dV/dq + dT/dq - (dM/dq v) v``, i.e. the
        Lagrange equations ``d/dt dT/dv - dT/dq + dV/dq = Q + ...`` solved for
        ``M v'``.
        """
        q = _col(q, "q")
        v = _col(v, "v")
        T = ca.SX(T)
        Mx, dTdv = ca.hessian(T, v)
        Mx = ca.simplify(Mx) if Mx.numel() < 400 else Mx
        dTdq = ca.gradient(T, q)
        dVdq = ca.gradient(ca.SX(V), q) if not (isinstance(V, (int, float)) and V == 0) else ca.SX.zeros(q.shape[0])
        # d/dt (dT/dv) = M v' + (d(dT/dv)/dq) v
        coriolis = ca.mtimes(ca.jacobian(dTdv, q), v)
        f = dTdq - dVdq - coriolis
        if Q is not None:
            f = f + _col(Q, "Q")
        return cls(name, q, v, params, values, M=Mx, f=f, B=B, **kwargs)

    @classmethod
    def from_urdf(cls, path, *, actuated, output=None, name: str | None = None, **kwargs) -> "Model":
        """A model of the robot described by the URDF file ``path`` (:mod:`invctl.model.urdf`):
        ``actuated`` joints, ``output(robot) -> SX``, and ``springs``/``dampers`` of elastic joints
        (keywords of :meth:`invctl.model.urdf.Robot.model`)."""
        from .urdf import robot_from_urdf

        robot = robot_from_urdf(path)
        return robot.model(name or robot.description.name, actuated=actuated, output=output, **kwargs)

    def with_params(self, **overrides: float) -> "Model":
        """A copy with other parameter values (same symbolic model).

        Derived parameters follow their base parameters unless overridden.
        """
        new = copy.copy(self)
        new.overrides = {**self.overrides, **overrides}
        new.values = resolve_params(self.defaults, self.derived, new.overrides)
        return new

    def scaled(self, **factors: float) -> "Model":
        """A copy with parameters multiplied by factors, e.g. ``scaled(m3=1.2)``."""
        return self.with_params(**{k: self.values[k] * float(v) for k, v in factors.items()})

    # --------------------------------------------------------------- checking
    def _check_dimensions(self) -> None:
        n, problems = self.n, []
        if self.v.shape[0] != n:
            problems.append(f"v has length {self.v.shape[0]}, q has length {n}")
        if self.M.shape != (n, n):
            problems.append(f"M has shape {self.M.shape}, expected ({n}, {n})")
        if self.f.shape[0] != n:
            problems.append(f"f has length {self.f.shape[0]}, expected {n}")
        if self.B.shape[0] != n:
            problems.append(f"B has {self.B.shape[0]} rows, expected {n}")
        if self.G.shape != (self.ell, n):
            problems.append(f"G has shape {self.G.shape}, expected ({self.ell}, {n}) = (len(g), n)")
        if self.J.shape != (self.p, n):
            problems.append(f"J has shape {self.J.shape}, expected ({self.p}, {n}) = (len(j), n)")
        if self.ny and self.ny != self.m:
            problems.append(f"h has {self.ny} components but B has {self.m} inputs (003 needs as many outputs as inputs)")
        if self.ell + self.p + self.m > n:
            problems.append(f"l + p + m = {self.ell} + {self.p} + {self.m} > n = {n} (003 (1) needs l + p + m <= n)")
        for name, expr, allowed in (
            ("M", self.M, (self.q, self.theta)),
            ("B", self.B, (self.q, self.theta)),
            ("g", self.g, (self.q, self.theta)),
            ("G", self.G, (self.q, self.theta)),
            ("J", self.J, (self.q, self.theta)),
            ("j", self.j, (self.q, self.theta)),
            ("f", self.f, (self.q, self.v, self.theta)),
            ("h", self.h, (self.q, self.v, self.theta)),
        ):
            free = ca.symvar(expr)
            names = {s.name() for s in ca.symvar(ca.vertcat(*allowed))}
            stray = sorted({s.name() for s in free} - names)
            if stray:
                problems.append(f"{name} depends on symbols {stray} that are not q, v or parameters")
        if problems:
            raise DimensionError(f"model {self.name!r} is malformed:\n  - " + "\n  - ".join(problems))

    def validate(self, samples: int = 16, rng: int = 0) -> None:
        """Check ``G = g'``, ``M = M^T > 0`` at sample points; report all problems at once."""
        problems: list[str] = []
        if self._G_given and self.ell:
            diff = ca.Function("dG", [self.q, self.theta], [self.G - ca.jacobian(self.g, self.q)])
        else:
            diff = None
        Mf = self.function("M")
        if self.region is not None:
            try:
                qs, _ = self.region.sample(samples, rng)
            except ModelError:
                qs = np.random.default_rng(rng).uniform(-1, 1, (samples, self.n))
        else:
            qs = np.random.default_rng(rng).uniform(-1, 1, (samples, self.n))
        th = self.theta_values
        for qk in qs:
            Mk = np.array(Mf(qk, th))
            asym = np.max(np.abs(Mk - Mk.T)) if Mk.size else 0.0
            scale = max(1.0, np.max(np.abs(Mk)))
            if asym > 1e-10 * scale:
                problems.append(f"M(q) is not symmetric at q={np.round(qk, 4).tolist()} (max |M - M^T| = {asym:.3g})")
                break
            ev = np.linalg.eigvalsh(0.5 * (Mk + Mk.T)) if Mk.size else np.array([1.0])
            if ev.min() <= 0:
                problems.append(
                    f"M(q) is not positive definite at q={np.round(qk, 4).tolist()} "
                    f"(smallest eigenvalue {ev.min():.3g}); check masses/inertias {self.values}"
                )
                break
            if ev.max() > MAX_MASS_CONDITION * ev.min():
                problems.append(
                    f"M(q) is singular in double precision at q={np.round(qk, 4).tolist()} (condition number "
                    f"{ev.max() / ev.min():.3g} > {MAX_MASS_CONDITION:.0e}: eigenvalues {ev.min():.3g} to "
                    f"{ev.max():.3g}); check the scales of masses/inertias/lengths {self.values}"
                )
                break
            if diff is not None:
                d = np.max(np.abs(np.array(diff(qk, th))))
                if d > 1e-9:
                    problems.append(
                        f"G != g'(q) at q={np.round(qk, 4).tolist()} (max difference {d:.3g}); "
                        "omit G to have it derived from g"
                    )
                    break
        if problems:
            raise ModelError(f"model {self.name!r} failed validation:\n  - " + "\n  - ".join(problems))

    # -------------------------------------------------------------- functions
    def function(self, what: str) -> ca.Function:
        """A cached CasADi Function of ``(q, v, theta)`` (or ``(q, theta)``) for
        one of ``M f B g G J j h gaps``."""
        if what in self._functions:
            return self._functions[what]
        q_only = {"M", "B", "g", "G", "J", "j", "gaps"}
        exprs = {
            "M": self.M, "f": self.f, "B": self.B, "g": self.g, "G": self.G,
            "J": self.J, "j": self.j, "h": self.h,
            "gaps": ca.vertcat(*[gp.expr for gp in self.gaps]) if self.gaps else ca.SX(0, 1),
        }
        if what not in exprs:
            raise KeyError(f"unknown model function {what!r}; choose from {sorted(exprs)}")
        if what in q_only:
            fn = ca.Function(what, [self.q, self.theta], [exprs[what]], ["q", "theta"], [what])
        else:
            fn = ca.Function(what, [self.q, self.v, self.theta], [exprs[what]], ["q", "v", "theta"], [what])
        self._functions[what] = fn
        return fn

    def evaluate(self, what: str, q, v=None) -> np.ndarray:
        """Evaluate ``what`` numerically at ``q`` (and ``v``) with this model's parameter values."""
        fn = self.function(what)
        q = np.asarray(q, float).ravel()
        if q.size != self.n:
            raise DimensionError(f"{self.name}.evaluate({what!r}): q has length {q.size}, expected {self.n}")
        if fn.n_in() == 2:
            return np.array(fn(q, self.theta_values))
        v = np.zeros(self.n) if v is None else np.asarray(v, float).ravel()
        if v.size != self.n:
            raise DimensionError(f"{self.name}.evaluate({what!r}): v has length {v.size}, expected {self.n}")
        return np.array(fn(q, v, self.theta_values))

    @cached_property
    def accel_and_multipliers(self) -> ca.Function:
        """``(q, v, u, theta) -> (v', lam, mu)`` from the index-1 system
        ``[M -G^T -J^T; G 0 0; J 0 0] [v'; lam; mu] = [f + B u; -G' v v; -(J' v) v - j' v]``
        (solved by the Schur complement on the LDL^T factors of ``M``, :mod:`invctl.model.linalg`)."""
        from .linalg import constrained_acceleration

        u = ca.SX.sym("u", self.m)
        l = self.ell
        Gdot_v = ca.jtimes(ca.mtimes(self.G, self.v), self.q, self.v)
        Jdot = ca.jtimes(ca.mtimes(self.J, self.v) + self.j, self.q, self.v)
        # the KKT system by the Schur complement on one LDL^T of M (no symbolic inverse of the KKT matrix)
        a, lam_mu = constrained_acceleration(self.M, self.f + ca.mtimes(self.B, u), ca.vertcat(self.G, self.J),
                                             ca.vertcat(-Gdot_v, -Jdot))
        return ca.Function(
            "accel", [self.q, self.v, u, self.theta],
            [a, lam_mu[:l], lam_mu[l:]], ["q", "v", "u", "theta"], ["a", "lam", "mu"],
        )

    def __repr__(self) -> str:
        return (
            f"Model({self.name!r}, n={self.n}, l={self.ell}, p={self.p}, m={self.m}, "
            f"gaps={len(self.gaps)}, params={self.values})"
        )
