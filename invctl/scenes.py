"""Scenes: what a system declares, and how invctl finds it.

A scene is a Python file that defines ``SCENE = Scene(...)``.  It declares data and the functions
that build its model (and, where it needs them, its reference, controllers, drawing); it contains no
command code.  Every ``invctl`` command is written once against :class:`Scene`; which commands a
scene offers follows from what it declares:

=====================================  =============================================================
declared                               commands
=====================================  =============================================================
``tracking=Tracking(reference=...)``   analyze, invert, design, simulate (C1/C2/C3), pipeline, study
``tracking=Tracking()`` (no reference) analyze, study
``contact=Contact(controllers=...)``   simulate, pipeline, study (analyze when it declares reports)
``switched=Switched()``                analyze, simulate, design, pipeline, study
=====================================  =============================================================

A scene given by path (``invctl analyze ./my_scene.py``) works exactly like a shipped one
(``invctl_scenes/<name>.py``).
"""
from __future__ import annotations

import hashlib
import importlib
import importlib.util
import math
import pkgutil
import sys
import traceback
from dataclasses import dataclass, field, fields
from functools import cached_property
from pathlib import Path
from types import MappingProxyType, ModuleType
from typing import TYPE_CHECKING, Any, Callable, Mapping, Union

from .errors import (DimensionError, InvctlError, ModelError, ParameterError, SceneError, URDFError, check_interrupt,
                     remember_sigint)

if TYPE_CHECKING:
    import casadi as ca
    from numpy.typing import ArrayLike

    from .control.pdplus import FeedbackLaw
    from .model import Model
    from .plot.animate import Drawing
    from .reference import Reference
    from .studies.switched import SwitchedProblem

# ---------------------------------------------------------------- the hooks a scene declares
#: ``build(**overrides) -> Model`` (a switched scene: ``-> SwitchedProblem``)
BuildHook = Callable[..., Union["Model", "SwitchedProblem"]]
#: ``reference(model) -> Reference``
ReferenceHook = Callable[["Model"], "Reference"]
#: ``f(model) -> q`` (a design or initial configuration)
ConfigurationHook = Callable[["Model"], "ArrayLike"]
#: ``internal_coordinates(model) -> SX`` (the phi of 003 Sect. 3), ``potential(model) -> SX``
ExpressionHook = Callable[["Model"], "ca.SX"]
#: ``signal(model) -> (y -> SX)``: an extra signal computed from the output
SignalHook = Callable[["Model"], Callable[[Any], Any]]
#: ``law(model, settings) -> FeedbackLaw``: a contact scene's controller
ControllerHook = Callable[["Model", dict[str, Any]], "FeedbackLaw"]
#: ``initial_state(model, settings, controller) -> (q0, v0)``
InitialStateHook = Callable[["Model", dict[str, Any], str], tuple["ArrayLike", "ArrayLike"]]
#: ``exact_impacts(model, settings, t_max) -> (times, post-impact normal velocities)``
ExactImpactsHook = Callable[["Model", dict[str, Any], float], tuple[Any, Any]]
#: ``f(model, settings) -> float`` (the closed-form rest time, the joints' clearance)
ModelNumberHook = Callable[["Model", dict[str, Any]], float]
#: ``drawing(model) -> Drawing``
DrawingHook = Callable[["Model"], "Drawing"]
#: ``validate(values) -> None`` raising ParameterError
ValidateHook = Callable[[dict[str, Any]], None]
#: ``compute(ctx: ReportContext) -> dict`` of named values
ReportHook = Callable[["ReportContext"], Mapping[str, Any]]

#: every command of ``invctl`` that acts on a scene
SCENE_COMMANDS = ("analyze", "invert", "design", "simulate", "pipeline", "study")
#: the magnitudes a ``--set`` value may have (0 aside): a product of three stays inside double precision
MAGNITUDE = (1e-100, 1e100)


def _frozen(mapping, what: str, scene: str = "") -> Mapping:
    if mapping is None:
        return MappingProxyType({})
    if not isinstance(mapping, Mapping):
        raise SceneError(f"scene {scene!r}: {what} must be a dict, got {type(mapping).__name__}")
    return MappingProxyType(dict(mapping))


def _callable(obj, what: str, scene: str = "", optional: bool = True):
    if obj is None and optional:
        return None
    if not callable(obj):
        raise SceneError(f"scene {scene!r}: {what} must be a function, got {type(obj).__name__} ({obj!r})")
    return obj


def _one_of(value, allowed, what: str, scene: str) -> None:
    if value not in allowed:
        raise SceneError(f"scene {scene!r}: {what} must be one of {', '.join(map(repr, allowed))}, got {value!r}")


def _non_numbers(values: Mapping) -> dict:
    """The entries of ``values`` that are not finite numbers."""
    return {k: v for k, v in values.items()
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v)}


@dataclass(frozen=True)
class Tracking:
    """What a tracking scene (003) declares beyond its model.

    Parameters
    ----------
    reference : callable, optional
        ``reference(model) -> Reference`` (``y_ref``); without it the scene offers analysis only.
    point : callable or sequence, optional
        Design configuration ``q`` for the analysis when there is no reference
        (``point(model) -> q`` or a fixed ``q``).
    plant : dict
        Factors of the simulated plant's parameters (model mismatch), e.g. ``{"m3": 1.2}``.
    initial_configuration : callable, optional
        ``initial_configuration(model) -> q``: a guess for the equilibria (the branch to follow).
    inversion : dict
        Overrides of the automatic inversion setup: any keyword of :func:`invctl.inversion.invert`
        (``T0``, ``Tf``, ``start``, ``end``, ``N``, ``scheme``, ...).
    feedback : dict
        Overrides of the automatic funnel design (``K``, ``k_i``, ``rho``, ``funnels``, ``kappa``,
        ``kappa_bar``, ``phi_bar``).
    expected_error : float, optional
        Expected output error under the plant mismatch (output units), for the funnel design.
    internal_coordinates : callable, optional
        ``internal_coordinates(model) -> SX`` (the ``phi`` of 003 Sect. 3); default: automatic.
    linearize_at : {"ends", "start"}
        Where the internal dynamics are linearized: the mean of the Jacobians at the start and end
        equilibria of the reference (as 003 Sect. 6 does) or at the start only.
    split : {"schur", "eig", "eig-unit"}
        How ``T`` of 003 (39) is built (:func:`invctl.analysis.linearize.from_matrices`).
    signals : dict
        Extra signals computed from the output, ``name -> (model -> (y -> SX))``, reported with
        their cumulative tracking error (e.g. the end effector).
    t_end : float, optional
        End of the closed-loop runs (default: the transition end plus its length).
    a1 : dict
        Further choices of ``K`` to check against (A1) in ``invctl analyze`` (name -> dict with
        ``K``, ``k_i``, ``rho``), e.g. the paper's printed ones.
    printed : dict
        Numbers the paper prints for this scene, compared in reports (e.g.
        ``{"reduction": {"output": 0.40, "end effector": 0.50}}``).
    controllers : tuple of str
        The runs ``invctl pipeline`` compares.
    funnel_levels : {"per-output", "shared"}
        How the automatic design chooses funnels and gains: per output and level (invctl's extension,
        default) or one funnel and one gain per level shared by all outputs, the rule of 003 Sect. 6
        (``phi_i,j = phi_j``, ``kappa_i,j = kappa_j``, ``phi = phi_2``); declare ``"shared"`` where the paper's
        rules apply.
    units : dict
        Units of the named quantities for figures and reports, ``name -> unit`` (outputs, inputs,
        coordinates and signals by their names, e.g. ``{"s2": "m", "u1": "N"}``); unnamed ones are unlabelled.
    """

    reference: ReferenceHook | None = None
    point: ConfigurationHook | ArrayLike | None = None
    plant: Mapping[str, float] = field(default_factory=dict)
    initial_configuration: ConfigurationHook | None = None
    inversion: Mapping[str, Any] = field(default_factory=dict)
    feedback: Mapping[str, Any] = field(default_factory=dict)
    expected_error: float | None = None
    internal_coordinates: ExpressionHook | None = None
    linearize_at: str = "ends"
    split: str = "schur"
    signals: Mapping[str, SignalHook] = field(default_factory=dict)
    t_end: float | None = None
    a1: Mapping[str, Mapping] = field(default_factory=dict)
    printed: Mapping[str, Any] = field(default_factory=dict)
    controllers: tuple = ("C1", "C2", "C3")
    funnel_levels: str = "per-output"
    units: Mapping[str, str] = field(default_factory=dict)

    def _check(self, scene: str) -> None:
        for name in ("reference", "initial_configuration", "internal_coordinates"):
            _callable(getattr(self, name), f"tracking.{name}", scene)
        _one_of(self.funnel_levels, ("per-output", "shared"), "tracking.funnel_levels", scene)
        for k, unit in dict(self.units).items():
            if not (isinstance(k, str) and isinstance(unit, str)):
                raise SceneError(f"scene {scene!r}: tracking.units maps names to unit strings, got {k!r}: {unit!r}")
        for name in ("plant", "inversion", "feedback", "signals", "a1", "printed", "units"):
            object.__setattr__(self, name, _frozen(getattr(self, name), f"tracking.{name}", scene))
        for k, v in self.signals.items():
            _callable(v, f"tracking.signals[{k!r}]", scene, optional=False)
        _one_of(self.linearize_at, ("ends", "start"), "tracking.linearize_at", scene)
        _one_of(self.split, ("schur", "eig", "eig-unit"), "tracking.split", scene)
        for k, factor in self.plant.items():
            if not (isinstance(factor, (int, float)) and math.isfinite(factor) and factor > 0):
                raise SceneError(f"scene {scene!r}: tracking.plant[{k!r}] must be a positive factor, got {factor!r}")
        if self.t_end is not None and not (isinstance(self.t_end, (int, float)) and self.t_end > 0):
            raise SceneError(f"scene {scene!r}: tracking.t_end must be a positive number, got {self.t_end!r}")
        object.__setattr__(self, "controllers", tuple(self.controllers))


@dataclass(frozen=True)
class Contact:
    """What a contact scene (000) declares beyond its model (whose gaps carry the unilateral constraints).

    Parameters
    ----------
    controllers : dict
        ``name -> law(model, settings) -> FeedbackLaw`` (:mod:`invctl.control.pdplus`,
        :mod:`invctl.control.preload`, ...); ``{}`` for an unactuated system.
    initial_state : callable
        ``initial_state(model, settings, controller) -> (q0, v0)``.
    default_controller : str or callable, optional
        The controller of ``invctl simulate`` without ``--controller`` (or
        ``(model, settings) -> name``); default: the first one.
    potential : callable, optional
        ``potential(model) -> SX``, the potential energy reported in the energy balance.
    exact_impacts : callable, optional
        ``exact_impacts(model, settings, t_max) -> (times, post-impact normal velocities)`` of the
        default run in closed form (the reference of ``invctl study tradeoff --job impacts``).
    exact_rest : callable, optional
        ``exact_rest(model, settings) -> float``: the closed-form rest (accumulation) time of the default
        run (with ``exact_impacts``, the reference of ``invctl study tradeoff --job rest``).
    clearance : callable, optional
        ``clearance(model, settings) -> float``: the free room of the joints (the scale a run's
        penetration is judged against); default: the largest gap at the start of the run.
    requires : dict, optional
        ``name -> {parameter or setting: value}``: the values a controller needs (e.g.
        ``{"juggling": {"actuators": 2}}``); ``invctl pipeline`` runs the controllers whose
        requirements the given values meet and reports the others as skipped.
    """

    controllers: Mapping[str, ControllerHook] = field(default_factory=dict)
    initial_state: InitialStateHook | None = None
    default_controller: str | Callable[["Model", dict[str, Any]], str] | None = None
    potential: ExpressionHook | None = None
    exact_impacts: ExactImpactsHook | None = None
    exact_rest: ModelNumberHook | None = None
    clearance: ModelNumberHook | None = None
    requires: Mapping[str, Mapping[str, float]] = field(default_factory=dict)

    def _check(self, scene: str) -> None:
        object.__setattr__(self, "controllers", _frozen(self.controllers, "contact.controllers", scene))
        object.__setattr__(self, "requires", _frozen(self.requires, "contact.requires", scene))
        for k, req in self.requires.items():
            if k not in self.controllers:
                raise SceneError(f"scene {scene!r}: contact.requires names {k!r}, which is not one of its "
                                 f"controllers {sorted(self.controllers)}")
            if not isinstance(req, Mapping) or not all(isinstance(v, (int, float)) for v in req.values()):
                raise SceneError(f"scene {scene!r}: contact.requires[{k!r}] must map parameter or setting names "
                                 f"to numbers, got {req!r}")
        for k, v in self.controllers.items():
            _callable(v, f"contact.controllers[{k!r}]", scene, optional=False)
        _callable(self.initial_state, "contact.initial_state", scene, optional=False)
        for name in ("potential", "exact_impacts", "exact_rest", "clearance"):
            _callable(getattr(self, name), f"contact.{name}", scene)
        dc = self.default_controller
        if isinstance(dc, str) and dc not in self.controllers:
            raise SceneError(f"scene {scene!r}: contact.default_controller {dc!r} is not one of "
                             f"{sorted(self.controllers)}")
        if dc is not None and not isinstance(dc, str):
            _callable(dc, "contact.default_controller", scene)

    def controller_for(self, model, settings: dict, name: str | None) -> str:
        """The controller to run: ``name``, the declared default, or the first one."""
        if name is None:
            dc = self.default_controller
            name = dc(model, settings) if callable(dc) else dc
            if name is None:
                name = next(iter(self.controllers), "none")
        if name != "none" and name not in self.controllers:
            raise SceneError(f"unknown controller {name!r}; this scene offers: "
                             f"{', '.join(sorted(self.controllers)) or 'none'} (and 'none': no input)")
        return name

    def unmet(self, name: str, values: Mapping) -> str | None:
        """Why controller ``name`` cannot run with the parameter and setting ``values`` (None: it can)."""
        bad = {k: v for k, v in self.requires.get(name, {}).items() if float(values.get(k, math.nan)) != float(v)}
        if not bad:
            return None
        return (f"controller {name!r} needs {', '.join(f'{k}={v:g}' for k, v in bad.items())} (here "
                f"{', '.join(f'{k}={float(values.get(k, math.nan)):g}' for k in bad)}); use "
                f"{' '.join(f'--set {k}={v:g}' for k, v in bad.items())}")


#: the plants a switched scene may declare, and the parameters each one needs beside the rigid arm's
SWITCHED_PLANTS = {"rigid_wall": (), "compliant_wrist": ("Mt", "kt", "bt")}


@dataclass(frozen=True)
class Switched:
    """A switched position/force scene (002): ``build`` returns a
    :class:`invctl.studies.switched.SwitchedProblem`, and the scene declares its plant: ``"rigid_wall"`` (the arm
    against the Kelvin-Voigt wall, 002 Sect. 4) or ``"compliant_wrist"`` (a compliant wrist between the arm and
    the wall, 002 Sect. 6, analysed through its reduced model (27)-(28); it needs ``Mt``, ``kt``, ``bt``)."""

    plant: str = "rigid_wall"

    def _check(self, scene: str) -> None:
        _one_of(self.plant, sorted(SWITCHED_PLANTS), "switched.plant", scene)

    @property
    def wrist(self) -> bool:
        return self.plant == "compliant_wrist"


@dataclass(frozen=True)
class ReportContext:
    """What a :class:`Report` sees: the scene, the parameters and the run (or None in ``analyze``)."""

    scene: "Scene"
    model: Any
    params: Mapping[str, float]
    settings: Mapping[str, float]
    result: Any = None
    controller: str | None = None


@dataclass(frozen=True)
class Report:
    """Numbers a scene wants to see, computed from a run (``command="simulate"``) or the model
    (``command="analyze"``), optionally beside the values the paper prints.

    ``compute(ctx: ReportContext) -> dict`` returns named values; ``printed`` holds the paper's
    values for some of those names (compared in the report); ``controllers`` restricts a simulate
    report to some controllers.
    """

    title: str
    compute: ReportHook
    command: str = "simulate"
    printed: Mapping[str, Any] = field(default_factory=dict)
    controllers: tuple = ()

    def _check(self, scene: str) -> None:
        _callable(self.compute, f"report {self.title!r}: compute", scene, optional=False)
        _one_of(self.command, ("analyze", "simulate"), f"report {self.title!r}: command", scene)
        object.__setattr__(self, "printed", _frozen(self.printed, f"report {self.title!r}: printed", scene))
        object.__setattr__(self, "controllers", tuple(self.controllers))

    def applies(self, command: str, controller: str | None = None) -> bool:
        return self.command == command and (not self.controllers or controller in self.controllers)


@dataclass(frozen=True)
class Scene:
    """A scene: a model, its parameters, and what to do with it (see the module docstring).

    Parameters
    ----------
    name : str
        Short name (used in reports, file names, JSON).
    build : callable
        ``build(**params) -> Model`` (or, for ``switched`` scenes, a ``SwitchedProblem``); receives
        the overridden entries of ``params`` only.
    params : dict
        Defaults of the parameters ``build`` accepts (``--set name=value``; a plant in a closed
        loop may differ from the model in these).
    settings : dict
        Defaults of run settings (time step, horizon, gains of declared controllers, ...), also set
        with ``--set``; never part of the model.
    choices : dict
        Named text options of ``build``, ``name -> (allowed values, ...)``, the first being the
        default (e.g. ``{"coordinates": ("angles", "cartesian")}``): ``--set name=value`` takes one
        of the listed words (anything else is a :class:`~invctl.errors.ParameterError`; nothing is
        evaluated), and ``build`` receives it as a string like the other overrides.
    integer : tuple of str
        Names in ``params``/``settings`` that must be integers (e.g. a number of actuators).
    positive : tuple of str
        Names that must be > 0 (lengths, masses, time steps ...); every value must be finite.
    validate : callable, optional
        ``validate(values) -> None`` raising :class:`~invctl.errors.ParameterError` for
        further conditions (``values`` = params and settings together).
    ranges : dict
        ``name -> (low, high)``: the closed range a parameter or setting may take (``-inf``/``inf``
        for an open side), e.g. the lengths the model is meant for; other values are a
        :class:`~invctl.errors.ParameterError` naming the range.
    tracking, contact, switched : optional
        What the scene is for (:class:`Tracking`, :class:`Contact`, :class:`Switched`).
    drawing : callable, optional
        ``drawing(model) -> invctl.plot.animate.Drawing`` (points and links of the mechanism).
    presets : dict
        Named parameter sets, ``name -> {parameter or setting: value}`` (``--preset NAME``), applied
        before the ``--set`` values; e.g. a parameter set identified from a paper's printed numbers.
    reports : tuple of Report
        Numbers the scene wants to see in ``analyze``/``simulate``.
    studies : dict
        Scene-specific speed-versus-accuracy studies: ``name -> spec(scene, params, settings, smoke)``
        returning a :class:`~invctl.studies.tradeoff.TradeoffSpec` (``invctl study tradeoff --job name``).
    description : str
        One paragraph shown by ``invctl analyze`` and in the gallery.
    """

    name: str
    build: BuildHook
    params: Mapping[str, float] = field(default_factory=dict)
    settings: Mapping[str, float] = field(default_factory=dict)
    choices: Mapping[str, tuple] = field(default_factory=dict)
    integer: tuple = ()
    positive: tuple = ()
    validate: ValidateHook | None = None
    tracking: Tracking | None = None
    contact: Contact | None = None
    switched: Switched | None = None
    drawing: DrawingHook | None = None
    presets: Mapping[str, Mapping[str, float]] = field(default_factory=dict)
    reports: tuple = ()
    studies: Mapping[str, Callable] = field(default_factory=dict)
    description: str = ""
    source: str = ""
    ranges: Mapping[str, tuple] = field(default_factory=dict)

    def __post_init__(self):
        name = self.name
        if not isinstance(name, str) or not name.isidentifier():
            raise SceneError(f"scene name must be an identifier-like string, got {name!r}")
        _callable(self.build, "build", name, optional=False)
        _callable(self.validate, "validate", name)
        _callable(self.drawing, "drawing", name)
        for what in ("params", "settings"):
            values = _frozen(getattr(self, what), what, name)
            if bad := _non_numbers(values):
                raise SceneError(f"scene {name!r}: {what} must map names to finite numbers, got {bad}")
            object.__setattr__(self, what, values)
        both = sorted(set(self.params) & set(self.settings))
        if both:
            raise SceneError(f"scene {name!r}: {both} are both parameters and settings; pick one")
        choices = {}
        for cname, allowed in _frozen(self.choices, "choices", name).items():
            allowed = tuple(allowed) if isinstance(allowed, (tuple, list)) else ()
            if (not isinstance(cname, str) or not cname.isidentifier() or not allowed
                    or not all(isinstance(a, str) and a.isidentifier() for a in allowed)
                    or len(set(allowed)) != len(allowed)):
                raise SceneError(f"scene {name!r}: choices must map identifier-like names to non-empty tuples of "
                                 f"distinct identifier-like words (the first is the default), got "
                                 f"{cname!r}: {self.choices[cname]!r}")
            if cname in self.params or cname in self.settings:
                raise SceneError(f"scene {name!r}: {cname!r} is both a choice and a parameter or setting")
            choices[cname] = allowed
        object.__setattr__(self, "choices", MappingProxyType(choices))
        for what in ("integer", "positive"):
            names = tuple(getattr(self, what))
            unknown = sorted(set(names) - set(self.params) - set(self.settings))
            if unknown:
                raise SceneError(f"scene {name!r}: {what} names unknown values {unknown}")
            object.__setattr__(self, what, names)
        ranges = {}
        for k, r in _frozen(self.ranges, "ranges", name).items():
            try:
                lo, hi = (float(x) for x in r)
            except (TypeError, ValueError):
                lo = hi = math.nan
            if k not in self.params and k not in self.settings or not lo <= hi:
                raise SceneError(f"scene {name!r}: ranges must map names of params or settings to (low, high) with "
                                 f"low <= high, got {k!r}: {r!r}")
            ranges[k] = (lo, hi)
        object.__setattr__(self, "ranges", MappingProxyType(ranges))
        presets = {}
        for pname, pvalues in _frozen(self.presets, "presets", name).items():
            if not isinstance(pname, str) or not pname.isidentifier():
                raise SceneError(f"scene {name!r}: preset names must be identifier-like strings, got {pname!r}")
            pvalues = _frozen(pvalues, f"presets[{pname!r}]", name)
            unknown, bad = sorted(set(pvalues) - set(self.params) - set(self.settings)), _non_numbers(pvalues)
            if unknown or bad:
                raise SceneError(f"scene {name!r}: preset {pname!r} "
                                 + (f"names unknown values {unknown}" if unknown else f"has non-numbers {bad}"))
            presets[pname] = pvalues
        object.__setattr__(self, "presets", MappingProxyType(presets))
        kinds = [k for k in ("tracking", "contact", "switched") if getattr(self, k) is not None]
        if len(kinds) > 1:
            raise SceneError(f"scene {name!r} declares {kinds}; a scene is one of tracking, contact, switched")
        expected = {"tracking": Tracking, "contact": Contact, "switched": Switched}
        for k in kinds:
            obj = getattr(self, k)
            if not isinstance(obj, expected[k]):
                raise SceneError(f"scene {name!r}: {k}= must be an invctl.scenes.{expected[k].__name__}, "
                                 f"got {type(obj).__name__}")
            if hasattr(obj, "_check"):
                obj._check(name)
        reports = tuple(self.reports)
        for r in reports:
            if not isinstance(r, Report):
                raise SceneError(f"scene {name!r}: reports must be invctl.scenes.Report objects, got {r!r}")
            r._check(name)
        object.__setattr__(self, "reports", reports)
        object.__setattr__(self, "studies", _frozen(self.studies, "studies", name))
        for k, v in self.studies.items():
            _callable(v, f"studies[{k!r}]", name, optional=False)

    # ------------------------------------------------------------------ kinds
    @property
    def kind(self) -> str:
        """``"tracking"``, ``"contact"``, ``"switched"`` or ``"model"`` (nothing declared)."""
        for k in ("tracking", "contact", "switched"):
            if getattr(self, k) is not None:
                return k
        return "model"

    @property
    def commands(self) -> tuple[str, ...]:
        """The commands this scene offers (see the module docstring; declared studies add ``study``)."""
        kind = self.kind
        if kind == "tracking":
            inverts = self.tracking is not None and self.tracking.reference is not None
            return ("analyze", "invert", "design", "simulate", "pipeline", "study") if inverts else ("analyze", "study")
        if kind == "contact":
            analyzes = any(r.command == "analyze" for r in self.reports)
            return ("analyze",) * analyzes + ("simulate", "pipeline", "study")
        if kind == "switched":
            return ("analyze", "simulate", "design", "pipeline", "study")
        return ("study",) if self.studies else ()

    def require(self, command: str) -> None:
        """Raise :class:`SceneError` unless the scene offers ``command`` (saying what it would need)."""
        if command in self.commands:
            return
        need = {
            "invert": "a model with outputs and tracking=Tracking(reference=...)",
            "design": "tracking=Tracking(reference=...) or switched=Switched()",
            "simulate": "tracking=Tracking(reference=...), contact=Contact(...) or switched=Switched()",
            "pipeline": "tracking=Tracking(reference=...), contact=Contact(...) or switched=Switched()",
            "analyze": "tracking=Tracking(...), switched=Switched() or an analyze Report",
            "study": "tracking, contact or switched",
        }.get(command, "a declaration for it")
        raise SceneError(f"scene {self.name!r} does not offer {command!r}; it offers: "
                         f"{', '.join(self.commands) or 'none'} ({command} needs {need})")

    # ------------------------------------------------------------- parameters
    def split(self, values: Mapping[str, float] | None, preset: str | None = None) -> tuple[dict, dict]:
        """Split ``--set`` values into (parameter overrides, full settings), checked; the values of
        the named ``preset`` (``--preset``) come first and ``values`` override them.

        Raises
        ------
        ParameterError
            Unknown preset or names, non-finite values, non-integers where integers are required,
            values that must be positive and are not, or what ``validate`` rejects.
        """
        if preset is not None:
            if preset not in self.presets:
                raise ParameterError(f"{self.name}: no preset {preset!r}; presets: "
                                     f"{', '.join(sorted(self.presets)) or 'none'}")
            values = {**self.presets[preset], **dict(values or {})}
        values = dict(values or {})
        unknown = sorted(set(values) - set(self.params) - set(self.settings) - set(self.choices))
        if unknown:
            raise ParameterError(
                f"{self.name}: unknown parameter(s) {unknown}; parameters: {sorted(self.params) or 'none'}; "
                f"settings: {sorted(self.settings) or 'none'}"
                + (f"; choices: {sorted(self.choices)}" if self.choices else ""))
        chosen = {k: self.check_choice(k, values.pop(k)) for k in list(values) if k in self.choices}
        for k, v in values.items():
            if isinstance(v, str):
                raise ParameterError(f"{self.name}: {k} = {v!r} is not a number")
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(float(v)):
                raise ParameterError(f"{self.name}: {k} = {v!r} is not a finite number")

        full: dict[str, Any] = {**self.params, **self.settings, **{k: float(v) for k, v in values.items()}, **chosen}
        self.check_values(full)
        params = {**{k: float(v) for k, v in values.items() if k in self.params}, **chosen}
        settings = {k: float(full[k]) for k in self.settings}
        return params, settings

    def check_choice(self, name: str, value) -> str:
        """``value`` if it is one of the words allowed for the choice ``name``, else a ParameterError."""
        allowed = self.choices[name]
        if not isinstance(value, str) or value.strip() not in allowed:
            raise ParameterError(f"{self.name}: {name} must be one of {', '.join(allowed)} "
                                 f"(default {allowed[0]}), got {value!r}")
        return value.strip()

    def check_values(self, full: Mapping[str, Any]) -> None:
        """Apply the magnitude range, ``integer``, ``positive``, ``ranges`` and ``validate`` to a full set of values
        (choices not in ``full`` take their defaults)."""
        full = {**{k: a[0] for k, a in self.choices.items()}, **full}
        for k in self.choices:
            full[k] = self.check_choice(k, full[k])
        for k, v in full.items():
            if k in self.choices:
                continue
            if v != 0 and not MAGNITUDE[0] <= abs(float(v)) <= MAGNITUDE[1]:
                raise ParameterError(f"{self.name}: {k} = {v!r} is outside [{MAGNITUDE[0]:g}, {MAGNITUDE[1]:g}] in "
                                     "magnitude: products of a few such values leave double precision (overflow or "
                                     "underflow to 0); use units in which the value is moderate")
        for k in self.integer:
            if k in full and float(full[k]) != round(float(full[k])):
                raise ParameterError(f"{self.name}: {k} must be an integer, got {full[k]!r}")
        for k in self.positive:
            if k in full and not float(full[k]) > 0:
                raise ParameterError(f"{self.name}: {k} must be positive, got {full[k]!r}")
        for k, (lo, hi) in self.ranges.items():
            if k in full and not lo <= float(full[k]) <= hi:
                raise ParameterError(f"{self.name}: {k} = {full[k]!r} is outside [{lo:g}, {hi:g}], the range the "
                                     "scene declares for it")
        if self.validate is not None:
            self.validate(dict(full))

    def model(self, params: Mapping[str, float] | None = None):
        """``build(**params)`` (parameter overrides only), with its return type checked."""
        values: dict[str, Any] = dict(params or {})
        unknown = sorted(set(values) - set(self.params) - set(self.choices))
        if unknown:
            raise ParameterError(f"{self.name}: unknown model parameter(s) {unknown}; known: {sorted(self.params)}"
                                 + (f"; choices: {sorted(self.choices)}" if self.choices else ""))
        values.update({k: self.check_choice(k, v) for k, v in values.items() if k in self.choices})
        try:
            obj = self._build(values)
        except ModelError as exc:
            if values and not isinstance(exc, DimensionError):
                self._blame(values, exc)
            raise
        self._check_model(obj)
        return obj

    def _build(self, values: dict):
        """``build(**values)``: the scene's own code, so anything it raises outside invctl's errors becomes a
        :class:`SceneError` naming the call and the line (the one boundary between invctl and ``build``)."""
        try:
            return self.build(**values)
        except InvctlError:
            raise
        except Exception as exc:  # noqa: BLE001 - the boundary to the scene's code (see the docstring)
            raise SceneError(f"scene {self.name!r}: build({', '.join(f'{k}={v!r}' for k, v in values.items())}) "
                             f"failed: {type(exc).__name__}: {exc}{_where(exc, self.source)}") from exc

    def _blame(self, params: dict, exc: ModelError) -> None:
        """Raise a :class:`ParameterError` naming the overrides without which ``build`` gives a valid
        model (``exc``: what the model check found); nothing when the defaults fail as well."""
        def fails(**values) -> bool:
            try:
                self._build(values)
            except ModelError:
                return True
            except InvctlError:  # another failure (the scene's code wrapped by _build) is not this check's
                return False
            return False

        if fails():
            return
        names = [k for k in params if fails(**{k: params[k]})] or sorted(params)
        given = ", ".join(f"{k} = {params[k]!r} (default {self.params.get(k, self.choices.get(k, ('?',))[0])!r})"
                          for k in names)
        raise ParameterError(f"{self.name}: the model is not valid with {given}: {exc}; use a value nearer the "
                             "default (units in which the values are moderate)",
                             diagnostics={"parameters": {k: params[k] for k in names}}) from exc

    def _check_model(self, obj) -> None:
        kind = self.kind
        at = _defined_at(self.build)
        if kind in ("tracking", "contact", "model"):
            from .model import Model

            if not isinstance(obj, Model):
                raise SceneError(f"scene {self.name!r}: build() returned {type(obj).__name__}; a {kind} scene "
                                 f"must return an invctl.model.Model{at}")
            if kind == "tracking" and self.tracking is not None and self.tracking.reference is not None \
                    and obj.ny == 0:
                raise SceneError(f"scene {self.name!r}: the model has no output h, but the scene declares a "
                                 f"reference; give Model(..., h=...){at}")
            if kind == "contact" and not obj.gaps:
                raise SceneError(f"scene {self.name!r}: a contact scene's model needs gaps "
                                 f"(Model(..., gaps=[...])){at}")
        elif kind == "switched" and not hasattr(obj, "error_system"):
            raise SceneError(f"scene {self.name!r}: build() returned {type(obj).__name__}; a switched scene "
                             f"must return an invctl.studies.switched.SwitchedProblem{at}")
        elif kind == "switched":
            wrist_params = [k for k in SWITCHED_PLANTS["compliant_wrist"] if k in obj.params]
            wrist = self.switched is not None and self.switched.wrist
            if wrist and len(wrist_params) < len(SWITCHED_PLANTS["compliant_wrist"]):
                raise SceneError(f"scene {self.name!r} declares plant='compliant_wrist', but its parameters lack "
                                 f"{sorted(set(SWITCHED_PLANTS['compliant_wrist']) - set(wrist_params))}{at}")
            if not wrist and wrist_params:
                raise SceneError(f"scene {self.name!r} declares plant='rigid_wall', but its parameters include "
                                 f"the wrist's {wrist_params}; declare Switched(plant='compliant_wrist'){at}")

    # ------------------------------------------------------------ the Python front door
    def bind(self, preset: str | None = None, **values) -> "Scene":
        """This scene with parameter/setting values (and a preset) used by its run methods below;
        ``load_scene(name, **values)`` is the short form. Checked now: unknown names or bad values raise
        :class:`~invctl.errors.ParameterError`."""
        self.split(values, preset=preset)
        bound = Scene(**{f.name: getattr(self, f.name) for f in fields(self)})
        object.__setattr__(bound, "_bound", (preset, dict(values)))
        return bound

    @property
    def values(self) -> dict:
        """The values bound by :meth:`bind` (``{}`` for the declared defaults)."""
        return dict(self.__dict__.get("_bound", (None, {}))[1])

    def run(self, command: str, **options) -> "CommandResult":
        """``invctl <command>`` on this scene with its bound values: the report (``text``, ``data``) and the
        typed ``result``. Options are the command's, as keywords (``N=200``, ``controller="C2"``, ...)."""
        from .studies.commands import run_command

        preset, values = self.__dict__.get("_bound", (None, {}))
        if preset is not None and options.get("preset") is None and command != "generate":
            options["preset"] = preset
        with remember_sigint():  # a Ctrl-C a compiled library swallowed is honoured here too, as on the CLI
            result = run_command(command, self, values, **options)
            check_interrupt("interrupted as the command finished; what it wrote is complete")
        return result

    def analyze(self, **options) -> "CommandResult":
        """The scene's analysis (``invctl analyze``): a report with ``text`` and ``data``."""
        return self.run("analyze", **options)

    def invert(self, *, throw: bool = True, **options):
        """The stable inverse (``invctl invert``) as an :class:`~invctl.inversion.Inverse`; with ``throw=False``
        a failed inversion returns its last iterate (``status`` FAILED) instead of raising."""
        return self._typed("invert", throw, options)

    def design(self, **options):
        """The feedback design (``invctl design``): the design object (tracking: the funnel design with
        ``describe()``), or the report for kinds whose design is a report."""
        res = self.run("design", **options)
        return res if res.result is None else res.result

    def simulate(self, controller: str | None = None, *, throw: bool = True, **options):
        """One run (``invctl simulate``) as a :class:`~invctl.results.Trajectory`; with ``throw=False`` an
        interrupted or failed run returns what was computed (its ``status`` says why)."""
        return self._typed("simulate", throw, {**options, "controller": controller})

    def pipeline(self, out_dir="invctl-out", *, throw: bool = True, **options) -> dict:
        """The scene's whole job (``invctl pipeline``) written to ``out_dir``: the runs by controller, each a
        :class:`~invctl.results.Trajectory` (the report is ``invctl.load(out_dir)`` for tracking scenes, or
        :meth:`run` ``("pipeline", ...)``)."""
        return self._typed("pipeline", throw, {**options, "out_dir": str(out_dir)})

    def _typed(self, command: str, throw: bool, options: dict):
        try:
            return self.run(command, **options).result
        except InvctlError as exc:
            partial = getattr(exc, "partial", None)
            if throw or partial is None:
                raise
            return partial


# ---------------------------------------------------------------- results
@dataclass
class CommandResult:
    """What a command returns: a readable report, JSON-able data (see :func:`jsonable`) and the typed result
    the command computed (an :class:`~invctl.inversion.Inverse`, a run's :class:`~invctl.results.Trajectory`, a
    pipeline's runs by controller, a design; ``None`` for reports that are text and data only)."""

    text: str
    data: dict[str, Any] = field(default_factory=dict)
    result: Any = field(default=None, repr=False, compare=False)


def jsonable(obj):
    """``obj`` with numpy scalars/arrays as Python numbers/lists, complex numbers as ``[re, im]``,
    non-finite floats as strings (``"inf"``, ``"nan"``: strict JSON has no such numbers) and
    anything else unknown as its ``str``."""
    import numpy as np

    if isinstance(obj, Mapping):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if np.isfinite(f) else str(f)
    if isinstance(obj, (complex, np.complexfloating)):
        return [jsonable(obj.real), jsonable(obj.imag)]
    if isinstance(obj, str) or obj is None:
        return obj
    return str(obj)


# ---------------------------------------------------------------- loading
def _shipped() -> ModuleType:
    """The shipped ``invctl_scenes`` package (installed next to ``invctl``), never a folder of that name that
    comes first on ``sys.path`` (``python -m invctl.cli`` puts the working directory there)."""
    here = Path(__file__).resolve().parents[1] / "invctl_scenes"
    mod = sys.modules.get("invctl_scenes")
    if mod is None and (here / "__init__.py").is_file():
        spec = importlib.util.spec_from_file_location("invctl_scenes", here / "__init__.py",
                                                      submodule_search_locations=[str(here)])
        assert spec is not None and spec.loader is not None  # a file location always has a spec and a loader
        mod = importlib.util.module_from_spec(spec)
        sys.modules["invctl_scenes"] = mod
        spec.loader.exec_module(mod)
    elif mod is None:
        mod = importlib.import_module("invctl_scenes")
    paths = [Path(p).resolve() for p in getattr(mod, "__path__", [])]
    if here.is_dir() and here not in paths:
        raise SceneError(f"a package 'invctl_scenes' in {', '.join(map(str, paths))} hides the shipped scenes in {here}; "
                         "rename that folder or run invctl from another one")
    return mod


def available_scenes() -> list[str]:
    """Names of the scenes shipped in ``invctl_scenes/``."""
    return sorted(m.name for m in pkgutil.iter_modules(_shipped().__path__) if not m.name.startswith("_"))


def _where(exc: BaseException, source: str) -> str:
    """`` (file:line)`` of the innermost frame of ``exc`` in the scene file, if any."""
    if not source:
        return ""
    for fs in reversed(traceback.extract_tb(exc.__traceback__)):
        if Path(fs.filename).resolve() == Path(source).resolve():
            return f" ({fs.filename}:{fs.lineno})"
    return ""


def _defined_at(fn) -> str:
    """`` (file:line)`` where a scene's function is defined, if known."""
    code = getattr(fn, "__code__", None)
    return f" ({code.co_filename}:{code.co_firstlineno})" if code is not None else ""


def _is_path(text: str) -> bool:
    return text.endswith(".py") or "/" in text or "\\" in text or text.startswith(".")


def load_scene(name_or_path, preset: str | None = None, **values) -> Scene:
    """The :class:`Scene` of a shipped scene (``"manipulator"``) or of a scene file (``"./mine.py"``), with
    ``values`` (and a ``preset``) bound for its run methods (:meth:`Scene.bind`)::

        scene = invctl.load_scene("cartpole", mp=0.25)
        inv = scene.invert(N=200)          # an Inverse
        run = scene.simulate("C1")         # a ClosedLoopResult (a Trajectory)
        run.plot()

    Raises
    ------
    SceneError
        No such scene or file; a file that does not import (syntax errors and exceptions are reported
        with file and line); a file without ``SCENE = Scene(...)``.
    """
    text = str(name_or_path)
    if _is_path(text):
        path = Path(text)
        if path.is_dir():
            raise SceneError(f"scene file {text!r} is a folder; give the path to a .py file that defines SCENE")
        if not path.is_file():
            raise SceneError(f"scene file {text!r} does not exist (a shipped scene is given by its name: "
                             f"{', '.join(available_scenes())})")
        module = _import_file(path)
        source = str(path)
    else:
        if not text.isidentifier():
            raise SceneError(f"{text!r} is neither a scene name nor a path to a .py file")
        _shipped()
        try:
            module = importlib.import_module(f"invctl_scenes.{text}")
        except ModuleNotFoundError as exc:
            if exc.name not in (f"invctl_scenes.{text}", "invctl_scenes"):
                raise SceneError(f"scene {text!r} imports a missing module {exc.name!r}") from None
            raise SceneError(f"no scene named {text!r}; shipped scenes: {', '.join(available_scenes())} "
                             "(or give a path to a scene file)") from None
        except (SceneError, URDFError):  # a robot description's own error names the file and the element
            raise
        except Exception as exc:  # noqa: BLE001 - the boundary to the scene file's code: anything it raises
            raise SceneError(f"shipped scene {text!r} failed to import: {type(exc).__name__}: {exc}") from None
        source = getattr(module, "__file__", "") or ""
    scene = scene_of(module, source)
    return scene.bind(preset, **values) if values or preset is not None else scene


@dataclass(frozen=True, eq=False)
class BoundScene:
    """A scene with one command's values checked (:func:`bind_scene`): the parameter overrides, the full
    settings, how to load the scene again (``reference``, recorded in saved results) and its model and
    drawing, each built once, on first use, and kept."""

    scene: Scene
    params: dict
    settings: dict
    reference: str

    @cached_property
    def model(self):
        return self.scene.model(self.params)

    @cached_property
    def drawing(self) -> "Drawing | None":
        """The scene's drawing of :attr:`model` (None: the scene declares none)."""
        return None if self.scene.drawing is None else self.scene.drawing(self.model)


def bind_scene(scene, command: str, values: Mapping | None = None, *, preset: str | None = None) -> BoundScene:
    """``scene`` (a :class:`Scene`, a name or a path) bound for ``command``: the scene offers it
    (:meth:`Scene.require`) and ``values`` (after the ``preset``) are checked (:meth:`Scene.split`)."""
    scene = scene if isinstance(scene, Scene) else load_scene(scene)
    scene.require(command)
    params, settings = scene.split(values, preset=preset)
    return BoundScene(scene, params, settings, scene_reference(scene))


def scene_reference(scene: Scene) -> str:
    """How to load ``scene`` again: its name when it is shipped in ``invctl_scenes/``, else its file path."""
    src = Path(scene.source) if scene.source else None
    shipped = _shipped().__file__
    if src is None or shipped is None or src.resolve().parent == Path(shipped).resolve().parent:
        return scene.name
    return str(src.resolve())


def scene_of(module: ModuleType, source: str = "") -> Scene:
    """The ``SCENE`` a module declares (checked)."""
    scene = getattr(module, "SCENE", None)
    where = source or getattr(module, "__name__", "?")
    if scene is None:
        raise SceneError(
            f"{where}: a scene file must define SCENE = invctl.Scene(name=..., build=..., params=...); "
            "see docs/write_your_own.md")
    if not isinstance(scene, Scene):
        raise SceneError(f"{where}: SCENE must be an invctl.Scene, got {type(scene).__name__}")
    if source and not scene.source:
        object.__setattr__(scene, "source", str(source))
    return scene


def _import_file(path: Path) -> ModuleType:
    resolved = path.resolve()
    # one module per file (not per file name): two scene files called scene.py in different folders
    # are different scenes
    modname = f"invctl_scene_{path.stem}_{hashlib.sha1(str(resolved).encode()).hexdigest()[:10]}"
    spec = importlib.util.spec_from_file_location(modname, resolved)
    if spec is None or spec.loader is None:
        raise SceneError(f"cannot import scene file {str(path)!r}")
    module = importlib.util.module_from_spec(spec)
    sys.modules[modname] = module
    try:
        spec.loader.exec_module(module)
    except BaseException as exc:  # the boundary to the scene file's code: anything it raises
        sys.modules.pop(modname, None)
        if isinstance(exc, SyntaxError):
            where = f"{exc.filename or resolved}" + (f":{exc.lineno}" if exc.lineno else "")
            raise SceneError(f"scene file {where}: syntax error: {exc.msg}"
                             + (f"\n    {exc.text.rstrip()}" if exc.text else "")) from None
        if isinstance(exc, SceneError) and _where(exc, str(resolved)):  # e.g. Scene(...) rejecting a declaration
            raise SceneError(f"{exc}{_where(exc, str(resolved))}") from None
        if isinstance(exc, (SceneError, URDFError)) or not isinstance(exc, Exception):
            raise  # a robot description's own error names the file and the element; Ctrl-C stays Ctrl-C
        raise SceneError(f"scene file {str(path)!r} failed to import: {type(exc).__name__}: {exc}"
                         f"{_where(exc, str(resolved))}") from None
    return module


