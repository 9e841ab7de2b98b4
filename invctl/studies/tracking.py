"""Feedforward + feedback tracking of any tracking scene (003 Sect. 4-6): setup, runs, comparison.

Controllers (the runs of 003 Sect. 6, for any scene):

``C1``      the paper's C1: feedforward ``u_ff`` (servo-constraint inverse of the reference model, causal
            part) plus the funnel controller (48) with the new reference (42) started at (43) - 003 (60)-(61)
            for the manipulator (its bounded solution; see :mod:`invctl.control.funnel_nmp`);
``C2``      the funnel controller alone (new reference (42));
``C3``      the feedforward alone;
``C1-inv``  invctl's extension: the same feedforward plus the funnel controller whose new reference is
            ``K_1 Psi(q_ff, v_ff)`` along the inverse's state trajectory (the derivative rules (46) applied to
            that trajectory), so that every error level vanishes when the plant follows the inverse.

(Before issue 12 the extension was called ``C1`` and the paper's C1 ``C1-42``; those names raise an error
that says so.)

The plant differs from the reference model by the scene's declared mismatch (``Tracking.plant``, e.g.
``m3 x 1.2``) and ``--plant-set`` overrides; it starts at rest at its equilibrium on ``y_ref(0)``.
Cumulative errors are ``int ||y - y_ref|| dt`` and the same for every declared signal.
"""
from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import (INTERRUPT_LIKE, CoordinateError, DimensionError, FunnelViolation, ModelError, OptionError,
                      ParameterError, RunInterrupted, SceneError, check_interrupt, is_interrupt)
from ..io import file_loader, read_json
from ..scenes import jsonable, scene_reference
from ..simulate.closed_loop import ClosedLoop, ClosedLoopResult


class _Names(dict):
    """Controller name -> description; lookups ignore case (``--controller c1-inv`` and ``C1-INV`` work)."""

    def _key(self, name):
        return next((k for k in self if isinstance(name, str) and k.lower() == name.lower()), name)

    def __getitem__(self, name):
        return dict.__getitem__(self, self._key(name))

    def __contains__(self, name):
        return dict.__contains__(self, self._key(name))

    def get(self, name, default=None):
        return dict.get(self, self._key(name), default)


CONTROLLERS = _Names({"C1": "ff + funnel, ref. (42)", "C2": "funnel only", "C3": "feedforward only",
                      "C1-inv": "ff + funnel, ref. inverse"})
#: controllers that need the servo-constraint inverse (feedforward or its state trajectory)
NEEDS_INVERSE = ("C1", "C3", "C1-inv")
#: names used before issue 12, with what they are called now
RENAMED = {"C1-42": "C1 (the paper's C1, new reference (42))"}


def check_controller(name: str) -> str:
    """The name of :data:`CONTROLLERS` that ``name`` spells (any case), else a :class:`SceneError` naming the
    choices (and the new name of a renamed controller)."""
    if name in CONTROLLERS:
        return CONTROLLERS._key(name)
    renamed = {k.lower(): k for k in RENAMED}
    if isinstance(name, str) and name.lower() in renamed:
        name = renamed[name.lower()]
        raise SceneError(f"controller {name!r} is now called {RENAMED[name]}; the former 'C1' (new reference "
                         "from the inverse's states) is 'C1-inv'")
    raise SceneError(f"unknown controller {name!r}: choose one of {sorted(CONTROLLERS)} "
                     f"({', '.join(f'{k}: {v}' for k, v in CONTROLLERS.items())})")


def tracking_model(scene, params=None, *, model=None):
    """``(model, reference)`` of a tracking scene with parameter overrides ``params`` (``model``: its model, built)."""
    scene.require("invert")
    model = scene.model(params) if model is None else model
    reference = scene.tracking.reference(model)
    from ..reference import Reference

    if not isinstance(reference, Reference):
        raise SceneError(f"scene {scene.name!r}: tracking.reference(model) returned {type(reference).__name__}, "
                         "expected an invctl.reference.Reference")
    if reference.m != model.ny:
        raise DimensionError(f"scene {scene.name!r}: tracking.reference(model) has {reference.m} components, but "
                             f"the model has {model.ny} outputs {model.y_names}; give the reference one component "
                             "per output")
    return model, reference


def equilibrium_configuration(scene, model, y, guess=None) -> np.ndarray:
    """The configuration ``q`` of the static equilibrium with ``h(q) = y`` (servo constraints at rest),
    continued from the scene's ``initial_configuration`` (or ``guess``)."""
    from ..inversion.cache import equilibrium_solver

    if guess is None and scene.tracking.initial_configuration is not None:
        guess = scene.tracking.initial_configuration(model)
    # the solver of the model's structure the inversion uses (built once), at this model's parameter values
    X, _ = equilibrium_solver(model).solve(np.asarray(y, float).ravel(), guess_q=guess, theta=model.theta_values,
                                           where=f" (scene {scene.name})")
    return X[:model.n]


def design_configuration(scene, model, reference=None) -> np.ndarray:
    """Where a tracking scene is analysed: the equilibrium at ``y_ref(t0)``, or the declared point."""
    t = scene.tracking
    if t.point is not None:
        q = np.asarray(t.point(model) if callable(t.point) else t.point, float).ravel()
        if q.size != model.n:
            raise DimensionError(f"scene {scene.name!r}: tracking.point has {q.size} entries, the model n = {model.n}")
        return q
    if reference is None:
        if t.initial_configuration is not None:
            return np.asarray(t.initial_configuration(model), float).ravel()
        return np.zeros(model.n)
    return equilibrium_configuration(scene, model, reference(reference.t0))


def output_structure(model, q):
    """The vector relative degree of the outputs at the configuration ``q`` (003 Sect. 2)."""
    from ..analysis import relative_degree

    return relative_degree(model, samples=0, points=[np.asarray(q, float).ravel()])


def tracking_linearization(scene, model, reference, *, samples: int = 200, internal=None):
    """The linearized internal dynamics (37)-(39) the scene's controllers use: internal coordinates
    of the scene (or the default ones of 003 Sect. 3), linearized at the equilibria of ``y_ref(t0)``
    and ``y_ref(tf)`` (mean of the Jacobians, as 003 Sect. 6) or at the start only.  ``None`` when the
    output is flat (no internal dynamics: the funnel controller then works on ``y`` alone)."""
    from ..analysis import internal_dynamics, is_position_output, linearize_internal

    t = scene.tracking
    q_start = design_configuration(scene, model, reference)
    if internal is None:
        rd = output_structure(model, q_start)
        if rd.r_bar == 2 * model.n:
            return None
        phi = t.internal_coordinates(model) if t.internal_coordinates is not None else None
        if rd.r_hat == 2 and is_position_output(model):
            internal = internal_dynamics(model, "sect3", phi, point=q_start, samples=samples)
        elif phi is None:
            raise CoordinateError(
                f"scene {scene.name!r}: the outputs have relative degree {rd.r_hat} > 2 and internal dynamics of "
                f"dimension {2 * model.n - rd.r_bar}; the default coordinates of 003 Sect. 3 need r_hat = 2: "
                "declare Tracking(internal_coordinates=lambda model: ...) (the eta of 003 (11), with L_K eta = 0)")
        else:
            internal = internal_dynamics(model, "sect2", phi, point=q_start, samples=samples)
    times = (reference.t0, reference.tf) if t.linearize_at == "ends" else (reference.t0,)
    points = []
    for tk in times:
        y = reference(tk).ravel()
        q = q_start if tk == reference.t0 else equilibrium_configuration(scene, model, y, guess=q_start)
        eta = np.array(internal.eta(q, np.zeros(model.n), model.theta_values)).ravel()
        points.append(([y] + [np.zeros(model.ny)] * (internal.r_hat - 1), eta))
    return linearize_internal(model, internal, points, combine="mean", split=t.split)


def plant_of(scene, model, plant_params=None, plant_factors=None):
    """The simulated plant: the scene's mismatch factors (or ``plant_factors``), then overrides."""
    factors = dict(scene.tracking.plant if plant_factors is None else plant_factors)
    plant_params = dict(plant_params or {})
    unknown = sorted(set(plant_params) - set(model.values)) + sorted(set(factors) - set(model.values))
    if unknown:
        raise ParameterError(f"--plant-set: unknown plant parameter(s) {unknown}; known: {sorted(model.values)}")
    plant = model.scaled(**{k: v for k, v in factors.items() if k not in plant_params})
    plant = plant.with_params(**plant_params) if plant_params else plant
    if plant_params:
        full = {k: plant.values[k] for k in scene.params if k in plant.values}
        scene.check_values({**scene.params, **scene.settings, **full})
        validate_plant(plant, plant_params)
    return plant


def validate_plant(plant, plant_params: dict) -> None:
    """``plant.validate()``; a failure is a :class:`ParameterError` naming the ``--plant-set`` values."""
    try:
        plant.validate()
    except ModelError as exc:
        given = " ".join(f"{k}={v!r}" for k, v in plant_params.items())
        raise ParameterError(f"--plant-set {given}: the plant model is not valid with these values: {exc}; use "
                             "values nearer the model's", diagnostics={"plant_params": dict(plant_params)}) from exc


#: options of :func:`invctl.inversion.invert_normal_form` (the servo route takes those of ``invert``)
NORMAL_FORM_OPTIONS = ("tol", "N", "T0", "Tf", "phi", "q_guess", "max_horizon", "neutral", "residual_tol",
                       "max_nodes", "samples")


def inversion_method(model, q) -> str:
    """``"servo"`` (servo constraints 003 (35), jerk-level index reduction) when the outputs are
    position outputs of relative degree 2, else ``"normal-form"`` (003 Sect. 2, any relative degree)."""
    from ..analysis import is_position_output

    return "servo" if output_structure(model, q).r_hat == 2 and is_position_output(model) else "normal-form"


def invert_tracking(scene, model, reference, *, progress=False, **options):
    """The stable inverse of the scene's reference model: the automatic setup with the scene's declared
    overrides (``Tracking.inversion``), then ``options``.  ``method`` (``"auto"`` by default) picks the
    servo-constraint route (:func:`invctl.inversion.invert`) or the normal form
    (:func:`invctl.inversion.invert_normal_form`, outputs of relative degree above 2, flat outputs).
    ``bounds``/``objective`` go to :func:`~invctl.inversion.invert`; ``minimum_time={"energy": w,
    "duration": (lo, hi)}`` calls :func:`~invctl.inversion.minimum_time` instead."""
    from ..inversion import invert, invert_normal_form, minimum_time

    cfg = dict(scene.tracking.inversion)
    if "q_guess" not in options and scene.tracking.initial_configuration is not None:
        options["q_guess"] = scene.tracking.initial_configuration(model)
    cfg.update({k: v for k, v in options.items() if v is not None})
    method = cfg.pop("method", "auto")
    free_time = cfg.pop("minimum_time", None)
    if method == "auto":
        method = inversion_method(model, design_configuration(scene, model, reference))
    if method == "servo" and free_time is not None:
        # the horizon of the reference's duration does not fit a free one: minimum_time derives its own
        # (a tol the scene declares is for the square inversion; one the caller gives refines this one)
        drop = {"T0", "Tf"} | ({"tol"} if options.get("tol") is None else set())
        cfg = {k: v for k, v in cfg.items() if k not in drop}
        return minimum_time(model, reference, progress=progress, **free_time, **cfg)
    if method == "servo":
        return invert(model, reference, progress=progress, **cfg)
    if free_time is not None:
        cfg["minimum_time"] = free_time  # reported below as not applicable to the normal form
    if method != "normal-form":
        raise ParameterError(f"inversion method must be 'auto', 'servo' or 'normal-form', got {method!r}")
    bad = sorted(set(cfg) - set(NORMAL_FORM_OPTIONS))
    if bad:
        raise ParameterError(f"scene {scene.name!r}: {bad} apply to the servo-constraint route only; this output "
                             f"is inverted through the normal form (options: {', '.join(NORMAL_FORM_OPTIONS)})")
    if "phi" not in cfg and scene.tracking.internal_coordinates is not None:
        cfg["phi"] = scene.tracking.internal_coordinates(model)
    return invert_normal_form(model, reference, **cfg)


#: CVODES settings of the closed loop (keywords of :class:`~invctl.simulate.closed_loop.ClosedLoop`) with
#: their CLI options
INTEGRATOR_OPTIONS = {"rtol": "--rtol", "atol": "--atol", "max_num_steps": "--max-steps"}


def check_integrator_options(integrator) -> dict:
    """``integrator`` as a dict of :data:`INTEGRATOR_OPTIONS` (positive numbers; ``max_num_steps`` an
    integer), ``None`` entries dropped; else a :class:`ParameterError` naming the known ones."""
    out = {k: v for k, v in dict(integrator or {}).items() if v is not None}
    bad = sorted(set(out) - set(INTEGRATOR_OPTIONS))
    if bad:
        raise OptionError(f"integrator: unknown setting(s) {bad}; known: {', '.join(INTEGRATOR_OPTIONS)}")
    for k, v in out.items():
        ok = isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) and v > 0
        if not ok or (k == "max_num_steps" and int(v) != v):
            raise OptionError(f"integrator: {k} must be a positive {'integer' if k == 'max_num_steps' else 'number'}"
                                 f", got {v!r}")
    return {k: int(v) if k == "max_num_steps" else float(v) for k, v in out.items()}


def _signals(scene, model) -> dict:
    return {name: make(model) for name, make in scene.tracking.signals.items()}


def feedback_design(scene, model, lin, reference, *, q0=None, overrides=None, t_end=2.0):
    """The funnel controller's parameters: the automatic design of
    :func:`invctl.control.funnel_design.design_funnel_feedback` with the scene's declared feedback
    (``Tracking.feedback``) and ``overrides`` used as given; ``"levels"`` in them replaces the scene's
    ``Tracking.funnel_levels``."""
    from ..control.funnel_design import design_funnel_feedback

    cfg = {**scene.tracking.feedback, **dict(overrides or {})}
    levels = cfg.pop("levels", scene.tracking.funnel_levels)
    return design_funnel_feedback(model, lin, reference, q0=q0, expected_error=scene.tracking.expected_error,
                                  controller_options={"t_end": t_end}, levels=levels, **cfg)


@dataclass
class TrackingSetup:
    """Everything a run needs: models, reference, linearization, controller, inverse, start state."""

    scene: Any
    model: Any
    plant: Any
    reference: Any
    lin: Any
    controller: Any
    inverse: Any
    design: Any
    q0: np.ndarray
    t_end: float
    dt: float
    signals: dict
    params: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    integrator: dict = field(default_factory=dict)
    _loops: dict = field(default_factory=dict)
    _c1: Any = None

    def inverse_reference_controller(self):
        """The funnel controller of ``C1-inv`` (invctl's extension): new reference
        ``y^_ref,1 = K_1 Psi(q_ff(t), v_ff(t))`` along the state trajectory of the servo-constraint inverse
        (the derivative rules (46) applied to that trajectory), so that every error level vanishes when the
        plant follows the inverse."""
        if self._c1 is None:
            self._require_inverse("C1-inv")
            t = self._inverse_grid(5e-4)
            q, v = self.inverse.q(t), self.inverse.v(t)
            psi = self.lin.psi_function().map(t.size)
            w = np.array(psi(q, v, np.tile(self.model.theta_values[:, None], (1, t.size))))
            c = self.controller
            if c.k == 0:  # minimum phase: y_new = K y, no new reference to replace
                self._c1 = c
                return c
            self._c1 = type(c)(self.model, self.lin, self.reference, K=c.K, k_i=c.k_i, rho=c.rho,
                               pairing=c.pairing, funnels=c.levels.phi, kappa=c.levels.kappa,
                               kappa_bar=c.kappa_bar, phi_bar=c.phi_bar, eta2_source=c.eta2_source,
                               t_end=self.t_end, eta2_ref_samples=(t, w))
        return self._c1

    def controller_for(self, name: str):
        """The feedback of controller ``name`` (None for the feedforward alone): the paper's C1 (003 (60)-(61))
        and C2 share :attr:`controller` (new reference (42) with (43); C1 adds the feedforward)."""
        name = check_controller(name)
        if name == "C1-inv":
            return self.inverse_reference_controller()
        return None if name == "C3" else self.controller

    def _require_inverse(self, name: str) -> None:
        """Invert the reference model now if ``name`` needs the inverse and none was given."""
        if self.inverse is None:
            t0 = time.perf_counter()
            self.inverse = invert_tracking(self.scene, self.model, self.reference)
            self.timings["inversion"] = time.perf_counter() - t0

    def _inverse_grid(self, step):
        """Sample times on ``[0, min(t_end, Tf)]`` (at least 4): the inverse rests after its horizon ``Tf`` and
        the sampled signals hold their last value, so the grid does not grow with ``t_end``."""
        stop = min(self.t_end, max(float(self.inverse.Tf), 0.0))
        return np.linspace(0.0, max(stop, 3 * step), max(int(round(stop / step)), 3) + 1)

    def u_ff_samples(self):
        if self.inverse is None:
            raise ParameterError("no feedforward: pass inverse= or let setup_tracking invert the reference model")
        t = self._inverse_grid(min(self.dt, 1e-3))
        u = np.asarray(self.inverse.u_causal(t), float).reshape(self.model.m, t.size)
        if not np.all(np.isfinite(u)):
            raise ParameterError("the feedforward u_causal(t) has non-finite values")
        return t, u

    def loop(self, name: str) -> ClosedLoop:
        name = check_controller(name)
        if name not in self._loops:
            if name in NEEDS_INVERSE:
                self._require_inverse(name)
            t0 = time.perf_counter()
            ctrl = self.controller_for(name)
            uff = self.u_ff_samples() if name in NEEDS_INVERSE else None
            self._loops[name] = ClosedLoop(self.plant, self.reference, controller=ctrl, u_ff=uff,
                                           signals=self.signals, t_end=self.t_end, dt=self.dt, name=name,
                                           **self.integrator)
            self.timings[f"build_{name}"] = time.perf_counter() - t0
        return self._loops[name]

    def meta(self) -> dict:
        """Where a run comes from (for files and ``invctl animate``)."""
        scene = self.scene
        return {"scene": scene_reference(scene), "params": dict(self.params),
                "plant": {k: v for k, v in self.plant.values.items() if v != self.model.values.get(k)},
                "units": dict(scene.tracking.units)}


def setup_tracking(scene, params=None, plant_params=None, *, inverse=None, invert=True, t_end=None, dt=1e-3,
                   feedback=None, plant_factors=None, q0=None, reference=None, progress=False,
                   inversion_options=None, integrator=None, model=None) -> TrackingSetup:
    """Build the reference model (``params``), the plant (declared mismatch, then ``plant_params``),
    the linearization, the funnel controller (declared feedback updated by ``feedback``) and, if
    ``invert`` and no ``inverse`` is given, the servo-constraint inverse of the reference model.
    ``reference`` (a Reference or ``model -> Reference``) replaces the scene's reference; ``dt`` is the
    output step of the runs and ``integrator`` their CVODES settings (:data:`INTEGRATOR_OPTIONS`); ``model``: the
    model of ``params``, already built."""
    integrator = check_integrator_options(integrator)
    if not (isinstance(dt, (int, float)) and np.isfinite(dt) and dt > 0):
        raise OptionError(f"dt (output step of the closed loop) must be a positive number of seconds, got {dt!r}")
    timings = {}
    t0 = time.perf_counter()
    params = dict(params or {})
    model, ref = tracking_model(scene, params, model=model)
    if reference is not None:
        ref = reference(model) if callable(reference) and not hasattr(reference, "expr") else reference
    if ref.t0 < 0:
        raise SceneError(f"scene {scene.name!r}: closed-loop runs start at t = 0, but the reference's "
                         f"transition starts at t0 = {ref.t0} < 0")
    plant = plant_of(scene, model, plant_params, plant_factors)
    lin = tracking_linearization(scene, model, ref)
    timings["analysis"] = time.perf_counter() - t0
    t_end = float(scene.tracking.t_end or (ref.tf + (ref.tf - ref.t0))) if t_end is None else float(t_end)
    if not t_end > 0:
        raise ParameterError(f"t_end must be positive, got {t_end}")
    if q0 is None:
        q0 = equilibrium_configuration(scene, plant, ref(0.0))
    q0 = np.asarray(q0, float).ravel()
    t0 = time.perf_counter()
    from ..control.funnel_nmp import NMPFunnelController

    design = feedback_design(scene, model, lin, ref, q0=q0, overrides=feedback, t_end=t_end)
    ctrl = NMPFunnelController(model, lin, ref, t_end=t_end, **design.controller_options())
    timings["controller"] = time.perf_counter() - t0
    if inverse is None and invert:
        t0 = time.perf_counter()
        if progress:
            print("inverting the reference model (servo constraints) ...", file=sys.stderr)
        inverse = invert_tracking(scene, model, ref, **dict(inversion_options or {}))
        from ..scenes import scene_reference

        inverse.meta = {"scene": scene_reference(scene), "params": dict(params)}
        timings["inversion"] = time.perf_counter() - t0
    return TrackingSetup(scene, model, plant, ref, lin, ctrl, inverse, design, q0, t_end, float(dt),
                         _signals(scene, model), params, timings, integrator)


def a1_along(setup: TrackingSetup, res: ClosedLoopResult, stride: int = 10) -> dict:
    """(A1) along a run: smallest eigenvalue of the symmetric part of ``rho [stacked K] S~(q, v) E`` at every
    ``stride``-th grid point (> 0 required), the time of the minimum and the fraction where it holds."""
    from ..control.new_output import a1_margin_along

    sl = slice(None, None, stride)
    return a1_margin_along(setup.controller, setup.model, res.q[:, sl], res.v[:, sl], t=res.t[sl]).to_dict()


def run_controller(setup: TrackingSetup, name: str, *, raise_on_violation=True, v0=None) -> ClosedLoopResult:
    """One closed-loop run of controller ``name`` on ``setup`` (its ``meta`` records the scene)."""
    name = check_controller(name)
    try:
        res = setup.loop(name).run(setup.q0, v0, controller_label=name, raise_on_violation=raise_on_violation)
    except FunnelViolation as exc:
        exc.partial.meta = {**setup.meta(), "controller": name}
        raise
    res.meta = {**setup.meta(), "controller": name}
    return res


@dataclass
class TrackingStudy:
    """Runs of the controllers with the comparison of 003 Sect. 6."""

    runs: dict
    info: dict = field(default_factory=dict)
    setup: Any = field(default=None, repr=False, compare=False)

    def reduction(self, kind: str = "output", a: str = "C1", b: str = "C2") -> float:
        """``1 - E_a / E_b`` for the cumulative error of ``kind`` (``"output"`` or a declared signal)."""
        return 1.0 - self.runs[a].cumulative_errors[kind] / self.runs[b].cumulative_errors[kind]

    @property
    def error_kinds(self) -> list:
        first = next(iter(self.runs.values()), None)
        return list(first.cumulative_errors) if first is not None else []

    @property
    def reductions(self) -> dict:
        """The paper's comparison: how much C1 reduces C2's cumulative errors (003 Sect. 6)."""
        if not {"C1", "C2"} <= set(self.runs):
            return {}
        return {k: self.reduction(k) for k in self.error_kinds}

    @property
    def extension_reductions(self) -> dict:
        """The same for invctl's extension ``C1-inv`` against C2."""
        if not {"C1-inv", "C2"} <= set(self.runs):
            return {}
        return {k: self.reduction(k, "C1-inv") for k in self.error_kinds}

    def table(self) -> str:
        kinds = self.error_kinds
        m = max((r.u.shape[0] for r in self.runs.values()), default=0)
        head = (f"{'':6s} {'controller':25s} " + " ".join(f"{('cum. ' + k)[:15]:>15s}" for k in kinds)
                + f" {'final |e_y|':>12s} {'max phi|e|':>11s} {'margin':>8s} "
                + " ".join(f"{f'|u{i + 1}|max':>9s}" for i in range(m)) + f" {'drift':>9s} {'wall s':>7s}")
        lines = [head, "-" * len(head)]
        for name, r in self.runs.items():
            ratio = f"{r.max_funnel_ratio:11.4f}" if r.ratios.size else f"{'-':>11s}"
            margin = f"{r.funnel_margin:8.4f}" if r.ratios.size else f"{'-':>8s}"
            pk = r.input_peaks
            status = "" if r.success else f"  ({r.status}: {r.message})"
            lines.append(f"{name:6s} {CONTROLLERS.get(name, ''):25s} "
                         + " ".join(f"{r.cumulative_errors[k]:15.6g}" for k in kinds)
                         + f" {r.output_error[-1]:12.4g} {ratio} {margin} "
                         + " ".join(f"{x:9.3g}" for x in pk) + f" {r.max_constraint_drift:9.2g} {r.wall_s:7.3f}"
                         + status)
        red = self.reductions
        if red:
            printed = dict(self.info.get("printed_reduction") or {})
            parts = [f"{100 * v:.1f} % ({k})" for k, v in red.items()]
            line = "C1 reduces C2's cumulative error by " + ", ".join(parts)
            if printed:
                line += "; paper: " + ", ".join(f"{100 * float(v):.0f} % ({k})" for k, v in printed.items())
            lines.append(line + self._departed_note("C1", "C2"))
        ext = self.extension_reductions
        if ext:
            lines.append("C1-inv (invctl's extension) reduces C2's cumulative error by "
                         + ", ".join(f"{100 * v:.1f} % ({k})" for k, v in ext.items())
                         + self._departed_note("C1-inv", "C2"))
        if self.runs:
            lines += ["", "what the feedforward buys:", self.comparison().table()]
        return "\n".join(lines)

    def comparison(self):
        """:class:`~invctl.studies.compare.Comparison` of the runs (C1 against C2)."""
        from .compare import compare_runs

        kb = self.info.get("kappa_bar") or {}
        return compare_runs(self.runs, kappa_bar={k: v for k, v in kb.items() if v is not None},
                            move_end=self.info.get("move_end"), units=self.info.get("units"))

    def _departed_note(self, *names) -> str:
        deps = [(n, self.runs[n].departure) for n in names]
        parts = [f"{n} {d[1]} at t = {d[0]:.3g} s" for n, d in deps if d is not None]
        return f" (not comparable: {', '.join(parts)})" if parts else ""

    def to_dict(self) -> dict:
        return {"runs": {k: r.summary() for k, r in self.runs.items()}, "reductions": self.reductions,
                "extension_reductions": self.extension_reductions, "info": self.info,
                "comparison": self.comparison().to_dict() if self.runs else {}}

    def save(self, directory, meta: dict | None = None, *, runs: bool = True) -> Path:
        """Write ``study.json`` (the summary) and, with ``runs``, ``run_<name>.npz`` to ``directory``; returns
        the path of ``study.json``."""
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        for name, r in self.runs.items() if runs else ():
            r.to_npz(d / f"run_{name}.npz", meta=meta)
        (d / "study.json").write_text(json.dumps(jsonable(self.to_dict()), indent=1))
        return d / "study.json"

    @classmethod
    @file_loader
    def load(cls, directory) -> "TrackingStudy":
        d = Path(directory)
        meta = read_json(d / "study.json", "study summary")
        runs = {name: ClosedLoopResult.load(d / f"run_{name}.npz") for name in meta["runs"]}
        return cls(runs, meta.get("info", {}))

    def plot(self, out_dir=None, fmt="png"):
        """Figures matching 003 Figs. 5-9 (for any scene); written to ``out_dir`` if given. Returns the figures."""
        from ..plot.tracking import plot_study

        return plot_study(self, out_dir, fmt, captions=self.info.get("figure_captions"))


def run_tracking_study(scene, params=None, plant_params=None, *, controllers=None, setup=None,
                       progress=True, **setup_options) -> TrackingStudy:
    """Simulate the controllers on the mismatched plant and compare (003 Sect. 6).

    A run that leaves its funnel is kept (``status == "funnel_violation"``, truncated) and reported.
    """
    controllers = tuple(controllers or scene.tracking.controllers)
    controllers = tuple(check_controller(c) for c in controllers)
    setup = setup if setup is not None else setup_tracking(scene, params, plant_params, progress=progress,
                                                           invert=bool(set(NEEDS_INVERSE) & set(controllers)),
                                                           **setup_options)
    runs = {}
    try:
        for name in controllers:
            check_interrupt()
            if progress:
                print(f"simulating {name} ({CONTROLLERS.get(name, '?')}) ...", file=sys.stderr)
            runs[name] = run_controller(setup, name, raise_on_violation=False)
    except INTERRUPT_LIKE as _exc:  # keep the complete runs
        if not is_interrupt(_exc):
            raise
        note = f"interrupted; complete runs: {', '.join(runs) or 'none'} of {', '.join(controllers)}"
        raise RunInterrupted(note, partial=TrackingStudy(runs, {"scene": scene.name, "partial": note}, setup)) from None
    return compare_runs(scene, params, setup, runs)


def compare_runs(scene, params, setup: TrackingSetup, runs: dict) -> TrackingStudy:
    """The comparison of 003 Sect. 6 of ``runs`` (controller name -> run) made on ``setup``, with (A1) along
    every run and what the scene's paper printed."""
    a1 = {name: a1_along(setup, r) for name, r in runs.items() if r.t.size > 1}
    info = {"a1_along_trajectory": a1, "params": dict(params or {}),
            "plant": {k: v for k, v in setup.plant.values.items() if v != setup.model.values.get(k)},
            "timings": dict(setup.timings), "t_end": setup.t_end, "dt": setup.dt,
            "printed_reduction": dict(scene.tracking.printed.get("reduction", {})), "scene": scene.name,
            "figure_captions": dict(scene.tracking.printed.get("figures", {})),
            "kappa_bar": {n: getattr(setup.controller_for(n), "kappa_bar", None) for n in runs},
            "move_end": float(setup.reference.tf) if np.isfinite(setup.reference.tf) else None,
            "units": dict(scene.tracking.units), "funnel_levels": setup.design.levels}
    return TrackingStudy(runs, info, setup)
