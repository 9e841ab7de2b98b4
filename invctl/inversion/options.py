"""Options of :func:`~invctl.inversion.invert` and :func:`~invctl.inversion.minimum_time`, grouped
into small frozen keyword-only objects that check themselves where they are defined.

=====================  =====================================================================
:class:`Discretization`  collocation scheme, mesh, index reduction, mesh refinement (``tol``)
:class:`SolverOptions`   backend (IPOPT or Newton), limits, tolerances, IPOPT options verbatim
:class:`Horizon`         boundary selection 003 (36) and horizon ``[T0, Tf]`` (or their plan)
:class:`Bounds`          bounds on ``u``, ``u'``, ``q``, ``v`` and the pre-/post-actuation
:class:`Objective`       weights of the bounded (least-squares) inversion
=====================  =====================================================================

Each group has the package defaults in its field defaults; ``None`` means "derive it" (the
automatic setup of :mod:`invctl.inversion.plan`).  The flat keywords of ``invert`` (``N=``,
``backend=``, ``T0=``, ...) keep working: :func:`from_keywords` maps them onto these objects.
"""
from __future__ import annotations

import difflib
import math
from dataclasses import dataclass, field, fields, replace
from typing import Any, Mapping

import numpy as np

from ..errors import BoundsError, OptionError


def _finite(name, value, *, positive=False, nonnegative=False, integer=False, low=None, where=""):
    try:
        v = int(value) if integer else float(value)
    except (TypeError, ValueError):
        raise OptionError(f"{where}{name} must be a {'integer' if integer else 'number'}, got {value!r}") from None
    if integer and v != value:
        raise OptionError(f"{where}{name} must be an integer, got {value!r}")
    if not math.isfinite(v) or (positive and v <= 0) or (nonnegative and v < 0) or (low is not None and v < low):
        need = ("positive" if positive else "nonnegative" if nonnegative else f">= {low}" if low is not None
                else "finite")
        raise OptionError(f"{where}{name} must be {need} and finite, got {value!r}")
    return v


@dataclass(frozen=True, kw_only=True)
class Discretization:
    """How the inverse model is transcribed.

    Parameters
    ----------
    scheme : str
        ``hermite-simpson`` (default), ``legendre<d>``, ``radau<d>``.
    N : int
        Number of mesh intervals (ignored when ``mesh`` is given).
    mesh : array, optional
        The mesh itself (increasing from ``T0`` to ``Tf``; stored as a tuple).
    mesh_fraction : float, optional
        Fraction of the intervals on ``[t0, tf]`` for the piecewise-uniform mesh (default 0.5 when
        the horizon is given; a graded mesh when it is derived).
    formulation, omega : str, float
        Index reduction (:mod:`invctl.inversion.servo`): ``baumgarte`` (default) with rate ``omega``.
    compiled : bool or "auto"
        Compiled evaluation of the square system (``"auto"``: only when already cached).
    tol : float, optional
        Requested forward-check output error: refine the mesh until met.
    max_refinements, max_N : int
        Limits of the refinement.
    forward_options : dict, optional
        Keywords of :func:`~invctl.inversion.forward_check` during refinement.
    """

    scheme: str = "hermite-simpson"
    N: int = 200
    mesh: Any = None
    mesh_fraction: float | None = None
    formulation: str = "baumgarte"
    omega: float = 10.0
    compiled: bool | str = "auto"
    tol: float | None = None
    max_refinements: int = 6
    max_N: int = 4000
    forward_options: Mapping | None = None

    def __post_init__(self):
        from .schemes import get_scheme
        from .servo import FORMULATIONS

        w = "Discretization: "
        try:
            object.__setattr__(self, "scheme", get_scheme(self.scheme).name)
        except ValueError as exc:
            raise OptionError(w + str(exc)) from None
        object.__setattr__(self, "N", _finite("N", self.N, integer=True, low=2, where=w))
        if self.mesh is not None:
            mesh = np.array(self.mesh, float).ravel()
            if mesh.size < 3 or not np.all(np.isfinite(mesh)) or np.any(np.diff(mesh) <= 0):
                raise OptionError(f"{w}mesh must be finite and strictly increasing with at least 3 points, got "
                                  f"{mesh.size} point(s)")
            object.__setattr__(self, "mesh", tuple(float(t) for t in mesh))
        if self.mesh_fraction is not None and not 0 < float(self.mesh_fraction) < 1:
            raise OptionError(f"{w}mesh_fraction must be in (0, 1), got {self.mesh_fraction!r}")
        if self.formulation not in FORMULATIONS:
            raise OptionError(f"{w}formulation must be one of {FORMULATIONS}, got {self.formulation!r}")
        object.__setattr__(self, "omega", _finite("omega", self.omega, positive=True, where=w))
        if self.compiled not in (True, False, "auto"):
            raise OptionError(f"{w}compiled must be True, False or 'auto', got {self.compiled!r}")
        if self.tol is not None:
            object.__setattr__(self, "tol", _finite("tol", self.tol, positive=True, where=w))
        object.__setattr__(self, "max_refinements", _finite("max_refinements", self.max_refinements, integer=True,
                                                            low=0, where=w))
        object.__setattr__(self, "max_N", _finite("max_N", self.max_N, integer=True, low=2, where=w))
        if self.forward_options is not None and not isinstance(self.forward_options, Mapping):
            raise OptionError(f"{w}forward_options must be a dict of forward_check keywords, got "
                              f"{type(self.forward_options).__name__}")

    @property
    def intervals(self) -> int:
        """The number of mesh intervals (of ``mesh`` when given)."""
        return len(self.mesh) - 1 if self.mesh is not None else self.N


#: backends of the square solve
BACKENDS = ("ipopt", "newton")
#: Hessians of the bounded problems (:class:`~invctl.inversion.ocp.OCPTranscription`)
HESSIANS = ("auto", "gauss-newton", "exact", "limited-memory")


@dataclass(frozen=True, kw_only=True)
class SolverOptions:
    """How the transcription is solved.

    Parameters
    ----------
    backend : {"ipopt", "newton"}
        Square systems: IPOPT with an exact zero Hessian (default) or Newton with banded LU.
        Bounded problems always use IPOPT.
    ipopt_options : dict, optional
        Passed to IPOPT verbatim (``{"ipopt.tol": 1e-12}``); they override the package defaults.
    max_iter, max_wall_time : int, float
        Limits of every solve.
    newton_tol : float
        Residual tolerance of the Newton backend.
    residual_tol : float
        Largest accepted position-level constraint residual at the mesh.
    progress : bool
        One line per iteration to stderr.
    continuation : bool
        When a cold square solve fails, solve a slower transition first and continue.
    hessian : {"auto", "gauss-newton", "exact", "limited-memory"}
        Hessian of the Lagrangian of the bounded problems
        (:class:`~invctl.inversion.ocp.OCPTranscription`): ``"auto"`` is Gauss-Newton for
        least-squares tracking (cheaper per iteration) and the exact structured Hessian for
        free-time problems (the time-energy trade needs the constraint curvature).
    """

    backend: str = "ipopt"
    ipopt_options: Mapping | None = None
    max_iter: int = 100
    max_wall_time: float = 120.0
    newton_tol: float = 1e-10
    residual_tol: float = 1e-4
    progress: bool = False
    continuation: bool = True
    hessian: str = "auto"

    def __post_init__(self):
        w = "SolverOptions: "
        if self.backend not in BACKENDS:
            raise OptionError(f"{w}backend must be one of {BACKENDS}, got {self.backend!r}")
        if self.hessian not in HESSIANS:
            raise OptionError(f"{w}hessian must be one of {HESSIANS}, got {self.hessian!r}")
        if self.ipopt_options is not None:
            if not isinstance(self.ipopt_options, Mapping) or not all(isinstance(k, str) for k in self.ipopt_options):
                raise OptionError(f"{w}ipopt_options must be a dict with string keys (e.g. {{'ipopt.tol': 1e-12}}), "
                                  f"got {self.ipopt_options!r}")
            object.__setattr__(self, "ipopt_options", dict(self.ipopt_options))
        object.__setattr__(self, "max_iter", _finite("max_iter", self.max_iter, integer=True, low=0, where=w))
        for name in ("max_wall_time", "newton_tol", "residual_tol"):
            object.__setattr__(self, name, _finite(name, getattr(self, name), positive=True, where=w))
        object.__setattr__(self, "progress", bool(self.progress))
        object.__setattr__(self, "continuation", bool(self.continuation))


@dataclass(frozen=True, kw_only=True)
class Horizon:
    """Boundary conditions 003 (36) and horizon; ``None`` parts are derived (:func:`plan_inversion`).

    Parameters
    ----------
    T0, Tf : float, optional
        Start and end of the horizon (they must contain ``[t0, tf]``).
    start, end : dict, optional
        Entries of ``X = (q, v, lam, mu, u)`` fixed at ``T0`` / ``Tf``
        (:mod:`invctl.inversion.boundary`).
    q_guess : array, optional
        Configuration at which the equilibrium search starts.
    plan : InversionPlan, optional
        A plan computed before (fills what is ``None``).
    plan_options : dict, optional
        Keywords of :func:`plan_inversion` (``tol``, ``max_horizon``, ``neutral``, ``scale``).
    allow_underdetermined : bool
        Accept fewer conditions than unknowns (an input-energy objective then selects the inverse).
    """

    T0: float | None = None
    Tf: float | None = None
    start: Mapping | None = None
    end: Mapping | None = None
    q_guess: Any = None
    plan: Any = None
    plan_options: Mapping | None = None
    allow_underdetermined: bool = False

    def __post_init__(self):
        w = "Horizon: "
        for name in ("T0", "Tf"):
            if getattr(self, name) is not None:
                object.__setattr__(self, name, _finite(name, getattr(self, name), where=w))
        if self.T0 is not None and self.Tf is not None and not self.Tf > self.T0:
            raise OptionError(f"{w}Tf = {self.Tf} must be after T0 = {self.T0}")
        for name in ("start", "end", "plan_options"):
            v = getattr(self, name)
            if v is not None and not isinstance(v, Mapping):
                raise OptionError(f"{w}{name} must be a dict, got {type(v).__name__} ({v!r})")
        if self.plan is not None and self.plan_options is not None:
            raise OptionError(f"{w}give either plan (computed before) or plan_options (to compute one), not both")
        if self.q_guess is not None:
            q = np.array(self.q_guess, float).ravel()
            if not np.all(np.isfinite(q)):
                raise OptionError(f"{w}q_guess must be finite, got {self.q_guess!r}")
            object.__setattr__(self, "q_guess", tuple(float(v) for v in q))

    @property
    def complete(self) -> bool:
        """Whether nothing is left to derive."""
        return None not in (self.T0, self.Tf, self.start, self.end)


def _interval(value, name: str, where: str) -> tuple[float, float]:
    """``v`` -> ``(-v, v)`` (``v >= 0``); ``(lo, hi)`` with ``lo <= hi`` (``None`` or ``+-inf``: open)."""
    if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool):
        v = float(value)
        if not v >= 0:
            raise BoundsError(f"{where}{name}: a single number is a symmetric bound |.| <= v and must be >= 0, "
                              f"got {value!r}; give (lower, upper) for an asymmetric one")
        return -v, v
    if isinstance(value, (tuple, list)) and len(value) == 2:
        lo = -math.inf if value[0] is None else float(value[0])
        hi = math.inf if value[1] is None else float(value[1])
        if math.isnan(lo) or math.isnan(hi) or lo > hi:
            raise BoundsError(f"{where}{name}: need lower <= upper, got {value!r}")
        return lo, hi
    raise BoundsError(f"{where}{name}: expected a number v (|.| <= v) or a pair (lower, upper), got {value!r}")


@dataclass(frozen=True, kw_only=True)
class Bounds:
    """Bounds of the inversion (003 (35) with inequality constraints).

    Parameters
    ----------
    u, u_rate : number, pair or dict, optional
        Bounds on the inputs and on their rates ``du/dt``: ``v`` (``|u_i| <= v`` for every
        input), ``(lo, hi)``, or ``{input name: v or (lo, hi)}``.
    q, v : dict, optional
        ``{coordinate name: v or (lo, hi)}`` on coordinates and velocities (``v`` keys are
        coordinate names or ``<name>_dot``).
    max_pre_actuation, max_post_actuation : float, optional
        Longest allowed ``t0 - T0`` / ``Tf - tf``.  Shorter than the automatic horizon needs,
        the inverse must start (end) at rest there: exact tracking becomes impossible and the
        bounded problem trades output error for the shorter actuation.

    Bounds hold on the returned trajectory (the interpolating polynomials of every mesh interval),
    not only at the mesh and collocation points (:mod:`invctl.inversion.ocp`); rate bounds of the
    Legendre/Radau schemes hold at their collocation points only (a violation in between raises).
    """

    u: Any = None
    u_rate: Any = None
    q: Mapping | None = None
    v: Mapping | None = None
    max_pre_actuation: float | None = None
    max_post_actuation: float | None = None

    def __post_init__(self):
        w = "Bounds: "
        for name in ("u", "u_rate"):
            val = getattr(self, name)
            if isinstance(val, Mapping):
                object.__setattr__(self, name, {str(k): _interval(x, f"{name}[{k!r}]", w) for k, x in val.items()})
            elif val is not None:
                object.__setattr__(self, name, _interval(val, name, w))
        for name in ("q", "v"):
            val = getattr(self, name)
            if val is None:
                continue
            if not isinstance(val, Mapping):
                raise BoundsError(f"{w}{name} must be a dict {{name: v or (lower, upper)}}, got {val!r}")
            object.__setattr__(self, name, {str(k): _interval(x, f"{name}[{k!r}]", w) for k, x in val.items()})
        for name in ("max_pre_actuation", "max_post_actuation"):
            if getattr(self, name) is not None:
                object.__setattr__(self, name, _finite(name, getattr(self, name), nonnegative=True, where=w))

    @property
    def empty(self) -> bool:
        return all(getattr(self, f.name) is None for f in fields(self))

    def resolve(self, servo) -> "ResolvedBounds":
        """Numeric bounds on the entries of ``X`` and on ``u'`` for ``servo``'s model.

        Raises
        ------
        BoundsError
            Unknown names (the message lists the known ones).
        """
        names, L = servo.names, servo.layout
        nx = L.nx
        lo, hi = np.full(nx, -math.inf), np.full(nx, math.inf)
        rlo, rhi = np.full(L.m, -math.inf), np.full(L.m, math.inf)

        def assign(block, spec, lo_, hi_, offset, label):
            entries = names[block]
            if isinstance(spec, tuple):
                lo_[offset:offset + len(entries)], hi_[offset:offset + len(entries)] = spec
                return
            for key, (a, b) in spec.items():
                k = key
                if block == "v" and key in names["q"]:
                    k = names["v"][names["q"].index(key)]
                if k not in entries:
                    close = difflib.get_close_matches(key, entries + (names["q"] if block == "v" else []), n=3)
                    raise BoundsError(f"Bounds.{label}: unknown name {key!r}; known: {entries}"
                                      + (f" (did you mean {close}?)" if close else ""))
                i = offset + entries.index(k)
                lo_[i], hi_[i] = a, b

        blocks = L.blocks
        if self.u is not None:
            assign("u", self.u, lo, hi, blocks["u"].start, "u")
        if self.q is not None:
            assign("q", self.q, lo, hi, blocks["q"].start, "q")
        if self.v is not None:
            assign("v", self.v, lo, hi, blocks["v"].start, "v")
        if self.u_rate is not None:
            assign("u", self.u_rate, rlo, rhi, 0, "u_rate")
        labels = [f"{b}[{nm}]" for b in ("q", "v", "lam", "mu", "u") for nm in names[b]]
        return ResolvedBounds(lo, hi, rlo, rhi, tuple(labels), tuple(f"u_rate[{nm}]" for nm in names["u"]),
                              self.max_pre_actuation, self.max_post_actuation)

    @classmethod
    def parse(cls, items) -> "Bounds":
        """Bounds from strings (a command line; never evaluated): ``u=8`` (all inputs),
        ``u.u2=-5:8``, ``u_rate=100``, ``q.gamma=-0.2:0.2``, ``v.s2=1.5``, ``pre=0.3``, ``post=0.5``.
        An empty side of ``lo:hi`` is open."""
        kw: dict = {}
        for item in items or ():
            key, sep, text = str(item).partition("=")
            key = key.strip()
            if not sep:
                raise BoundsError(f"bound {item!r}: expected name=value (e.g. u=8, q.gamma=-0.2:0.2, pre=0.3)")

            def number(t):
                t = t.strip()
                if t == "":
                    return None
                try:
                    return float(t)
                except ValueError:
                    raise BoundsError(f"bound {item!r}: {t!r} is not a number") from None

            val = tuple(number(t) for t in text.split(":", 1)) if ":" in text else number(text)
            if val is None:
                raise BoundsError(f"bound {item!r}: missing value")
            block, _, name = key.partition(".")
            if block in ("pre", "post"):
                kw[f"max_{block}_actuation"] = val
            elif block in ("u", "u_rate", "q", "v"):
                if name:
                    kw.setdefault(block, {})
                    if not isinstance(kw[block], dict):
                        raise BoundsError(f"bound {item!r}: {block} given for all entries and by name")
                    kw[block][name] = val
                elif block in ("u", "u_rate"):
                    kw[block] = val
                else:
                    raise BoundsError(f"bound {item!r}: {block} bounds need a name ({block}.<name>=...)")
            else:
                raise BoundsError(f"bound {item!r}: unknown kind {block!r}; use u, u_rate, q, v, pre or post")
        return cls(**kw)


@dataclass(frozen=True)
class ResolvedBounds:
    """:class:`Bounds` on the entries of ``X`` (``lo``, ``hi``) and of ``u'`` (``rate_lo``, ``rate_hi``)."""

    lo: np.ndarray
    hi: np.ndarray
    rate_lo: np.ndarray
    rate_hi: np.ndarray
    labels: tuple
    rate_labels: tuple
    max_pre_actuation: float | None = None
    max_post_actuation: float | None = None

    @property
    def bounded(self) -> tuple[int, ...]:
        return tuple(int(i) for i in np.flatnonzero(np.isfinite(self.lo) | np.isfinite(self.hi)))

    @property
    def rated(self) -> tuple[int, ...]:
        return tuple(int(i) for i in np.flatnonzero(np.isfinite(self.rate_lo) | np.isfinite(self.rate_hi)))


@dataclass(frozen=True, kw_only=True)
class Objective:
    """Weights of the bounded (least-squares) inversion and of the time-energy trade.

    ``sum_i output_i int (y_i - y_ref,i)^2 dt + slack int |s|^2 dt + energy int |u|^2 dt
    + rate int |u'|^2 dt`` (:mod:`invctl.inversion.ocp`).

    Parameters
    ----------
    output : float, sequence or dict
        Weights of the output errors (one for all, one per output, or ``{output name: w}``).
    slack : float
        Weight of the servo-constraint slack ``s`` (the output error it admits at low
        frequencies); keeps the least-squares problem well posed at high frequencies.
    energy, rate : float
        Weights of the input energy and of the input rate.
    """

    output: Any = 1.0
    slack: float = 1e-2
    energy: float = 0.0
    rate: float = 0.0

    def __post_init__(self):
        w = "Objective: "
        for name in ("slack", "energy", "rate"):
            object.__setattr__(self, name, _finite(name, getattr(self, name), nonnegative=True, where=w))
        out = self.output
        if isinstance(out, Mapping):
            out = {str(k): _finite(f"output[{k!r}]", x, nonnegative=True, where=w) for k, x in out.items()}
        elif np.ndim(out) == 0:
            out = _finite("output", out, nonnegative=True, where=w)
        else:
            out = tuple(_finite(f"output[{i}]", x, nonnegative=True, where=w) for i, x in enumerate(np.ravel(out)))
        object.__setattr__(self, "output", out)

    @classmethod
    def parse(cls, items) -> "Objective":
        """Weights from strings (a command line; never evaluated): ``output=1`` (all outputs),
        ``output.NAME=10`` (one output by name), ``slack=1e-2``, ``energy=1e-3``, ``rate=0``."""
        kw: dict = {}
        for item in items or ():
            key, sep, text = str(item).partition("=")
            key = key.strip()
            if not sep or not text.strip():
                raise OptionError(f"weight {item!r}: expected name=value (e.g. output=1, output.y1=10, slack=1e-2, "
                                  "energy=1e-3, rate=0)")
            try:
                val = float(text)
            except ValueError:
                raise OptionError(f"weight {item!r}: {text.strip()!r} is not a number") from None
            block, _, name = key.partition(".")
            if block == "output" and name:
                if isinstance(kw.get("output"), float):
                    raise OptionError(f"weight {item!r}: output given for all outputs and by name")
                kw.setdefault("output", {})[name] = val
            elif block == "output":
                if isinstance(kw.get("output"), dict):
                    raise OptionError(f"weight {item!r}: output given for all outputs and by name")
                kw["output"] = val
            elif block in ("slack", "energy", "rate") and not name:
                kw[block] = val
            else:
                raise OptionError(f"weight {item!r}: unknown weight {key!r}; use output, output.<name>, slack, "
                                  "energy or rate")
        return cls(**kw)

    def output_weights(self, model) -> np.ndarray:
        """The output weights as an array over ``model``'s outputs."""
        if isinstance(self.output, float):
            return np.full(model.m, self.output)
        if isinstance(self.output, tuple):
            if len(self.output) != model.m:
                raise OptionError(f"Objective: {len(self.output)} output weights for {model.m} outputs "
                                  f"{list(model.y_names)}")
            return np.array(self.output)
        W = np.zeros(model.m)
        for k, x in self.output.items():
            if k not in model.y_names:
                raise OptionError(f"Objective: unknown output {k!r}; outputs are {list(model.y_names)}")
            W[list(model.y_names).index(k)] = x
        return W


#: the flat keywords of ``invert`` and the option object each belongs to
KEYWORDS = {
    **{k: "discretization" for k in ("scheme", "N", "mesh", "mesh_fraction", "formulation", "omega", "compiled",
                                     "tol", "max_refinements", "max_N", "forward_options")},
    **{k: "solver" for k in ("backend", "ipopt_options", "max_iter", "max_wall_time", "newton_tol", "residual_tol",
                             "progress", "continuation", "hessian")},
    **{k: "horizon" for k in ("T0", "Tf", "start", "end", "q_guess", "plan", "plan_options",
                              "allow_underdetermined")},
}
_CLASSES = {"discretization": Discretization, "solver": SolverOptions, "horizon": Horizon}


@dataclass(frozen=True)
class Options:
    """The resolved option groups of one call."""

    discretization: Discretization = field(default_factory=Discretization)
    solver: SolverOptions = field(default_factory=SolverOptions)
    horizon: Horizon = field(default_factory=Horizon)
    bounds: Bounds | None = None
    objective: Objective | None = None


def from_keywords(where: str, *, discretization=None, solver=None, horizon=None, bounds=None, objective=None,
                  **keywords) -> Options:
    """The option objects of a call: the given objects (or the defaults) with the flat keywords
    applied on top (a keyword overrides the same field of an object; ``None`` keywords are
    ignored, so wrappers can pass their optional arguments through).  ``objective`` may be a
    number (the legacy input-energy weight of underdetermined selections).

    Raises
    ------
    TypeError
        Unknown keywords (with the close matches) or objects of the wrong type.
    OptionError
        Invalid values (from the objects' checks).
    """
    given = {"discretization": discretization, "solver": solver, "horizon": horizon}
    unknown = sorted(set(keywords) - set(KEYWORDS))
    if unknown:
        hints = {k: difflib.get_close_matches(k, list(KEYWORDS) + ["bounds", "objective", "warm_start"], n=2)
                 for k in unknown}
        hint = "; ".join(f"{k!r} (did you mean {v}?)" for k, v in hints.items() if v)
        raise TypeError(f"{where}: unknown keyword(s) {unknown}" + (f"; {hint}" if hint else "")
                        + "; options are the fields of Discretization, SolverOptions, Horizon, Bounds and Objective")
    out = {}
    for group, cls in _CLASSES.items():
        obj = given[group]
        if obj is None:
            obj = cls()
        elif not isinstance(obj, cls):
            raise TypeError(f"{where}: {group} must be a {cls.__name__}, got {type(obj).__name__}")
        mine = {k: v for k, v in keywords.items() if KEYWORDS[k] == group and v is not None}
        out[group] = replace(obj, **mine) if mine else obj
    if bounds is not None and not isinstance(bounds, Bounds):
        if isinstance(bounds, Mapping):
            bounds = Bounds(**bounds)
        else:
            raise TypeError(f"{where}: bounds must be a Bounds (or a dict of its fields), got {type(bounds).__name__}")
    if objective is not None and not isinstance(objective, Objective):
        if isinstance(objective, (int, float)) and not isinstance(objective, bool):
            objective = Objective(energy=float(objective), output=0.0, slack=0.0)
        elif isinstance(objective, Mapping):
            objective = Objective(**objective)
        else:
            raise TypeError(f"{where}: objective must be an Objective (or a number: the input-energy weight), got "
                            f"{type(objective).__name__}")
    return Options(out["discretization"], out["solver"], out["horizon"],
                   None if bounds is None or bounds.empty else bounds, objective)
