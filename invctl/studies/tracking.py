"""Feedforward + feedback tracking study of 003 Sect. 6 (controllers C1, C2, C3, Figs. 5-9).

C1: ``u = u_ff + u_fb`` (causal feedforward from the servo-constraint inverse of the reference
model plus the funnel controller (48)); C2: ``u = u_fb``; C3: ``u = u_ff``.  The plant differs from
the reference model (by default ``PLANT_FACTORS`` of the scene: m3 x 1.2).  Cumulative errors are
``int_0^T ||y - y_ref|| dt`` and ``int_0^T ||r_app - r_app,ref|| dt``; the paper reports that C1 reduces
C2's by 40 % (y) and 50 % (end effector).
"""
from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import FunnelViolation, ParameterError, SceneError
from ..simulate.closed_loop import ClosedLoop, ClosedLoopResult

__all__ = ["CONTROLLERS", "TrackingSetup", "TrackingStudy", "a1_along", "setup_tracking", "run_controller",
           "run_tracking_study"]

CONTROLLERS = {"C1": "feedforward + funnel", "C2": "funnel only", "C3": "feedforward only",
               "C1-42": "ff + funnel, ref. (42)"}


@dataclass
class TrackingSetup:
    """Everything a run needs: models, reference, linearization, controller, inverse, start state."""

    scene: object
    model: object
    plant: object
    reference: object
    lin: object
    controller: object
    inverse: object
    q0: np.ndarray
    t_end: float
    dt: float
    endeffector: object
    timings: dict = field(default_factory=dict)
    _loops: dict = field(default_factory=dict)
    _c1: object = None

    def c1_controller(self):
        """The funnel controller of C1: new reference ``y^_ref,1 = K_1 Psi(q_ff(t), v_ff(t))`` along the state
        trajectory of the servo-constraint inverse (the derivative rules (46) applied to that trajectory),
        so that every error level vanishes when the plant follows the inverse; "C1-42" uses (42) instead."""
        if self._c1 is None:
            if self.inverse is None:
                raise ParameterError("C1 needs the inverse (feedforward and its state trajectory)")
            t = np.linspace(0.0, self.t_end, int(round(self.t_end / 5e-4)) + 1)
            q, v = self.inverse.q(t), self.inverse.v(t)
            psi = self.lin.psi_function().map(t.size)
            w = np.array(psi(q, v, np.tile(self.model.theta_values[:, None], (1, t.size))))
            c = self.controller
            self._c1 = type(c)(self.model, self.lin, self.reference, K=c.K, k_i=c.k_i, rho=c.rho,
                               funnels=c.levels.phi, kappa=c.levels.kappa, kappa_bar=c.kappa_bar,
                               phi_bar=c.phi_bar, eta2_source=c.eta2_source, t_end=self.t_end,
                               eta2_ref_samples=(t, w))
        return self._c1

    def u_ff_samples(self):
        if self.inverse is None:
            raise ParameterError("no feedforward: pass inverse= or let setup_tracking invert the reference model")
        t = np.linspace(0.0, self.t_end, int(round(self.t_end / min(self.dt, 1e-3))) + 1)
        u = np.asarray(self.inverse.u_causal(t), float).reshape(self.model.m, t.size)
        if not np.all(np.isfinite(u)):
            raise ParameterError("the feedforward u_causal(t) has non-finite values")
        return t, u

    def loop(self, name: str) -> ClosedLoop:
        if name not in CONTROLLERS:
            raise SceneError(f"unknown controller {name!r}: choose one of {sorted(CONTROLLERS)} "
                             f"({', '.join(f'{k}: {v}' for k, v in CONTROLLERS.items())})")
        if name not in self._loops:
            t0 = time.perf_counter()
            ctrl = {"C1": self.c1_controller, "C2": lambda: self.controller, "C1-42": lambda: self.controller,
                    "C3": lambda: None}[name]()
            uff = self.u_ff_samples() if name in ("C1", "C3", "C1-42") else None
            self._loops[name] = ClosedLoop(self.plant, self.reference, controller=ctrl, u_ff=uff,
                                           endeffector=self.endeffector, t_end=self.t_end, dt=self.dt, name=name)
            self.timings[f"build_{name}"] = time.perf_counter() - t0
        return self._loops[name]


def _plant(scene, model, plant_params, plant_factors):
    factors = dict(getattr(scene, "PLANT_FACTORS", {}) if plant_factors is None else plant_factors)
    plant_params = dict(plant_params or {})
    unknown = sorted(set(plant_params) - set(model.values)) + sorted(set(factors) - set(model.values))
    if unknown:
        raise SceneError(f"--plant-set: unknown parameter(s) {unknown}; known: {sorted(model.values)}")
    plant = model.scaled(**{k: v for k, v in factors.items() if k not in plant_params})
    return plant.with_params(**plant_params) if plant_params else plant


def setup_tracking(scene, params=None, plant_params=None, *, inverse=None, invert=True, t_end=2.0, dt=1e-3,
                   feedback=None, plant_factors=None, q0=None, reference=None, progress=False) -> TrackingSetup:
    """Build the reference model (``params``), the plant (``PLANT_FACTORS`` then ``plant_params``),
    the linearization, the funnel controller (the scene's ``FEEDBACK`` updated by ``feedback``) and,
    if ``invert`` and no ``inverse`` is given, the servo-constraint inverse of the reference model.
    ``reference`` (a Reference or ``model -> Reference``) replaces the scene's reference."""
    timings = {}
    t0 = time.perf_counter()
    params = dict(params or {})
    model = scene.build(**params)
    plant = _plant(scene, model, plant_params, plant_factors)
    ref = scene.reference(model) if reference is None else (reference(model) if callable(reference) and not
                                                                 hasattr(reference, "expr") else reference)
    lin = scene.manipulator_linearization(model, ref) if hasattr(scene, "manipulator_linearization") else None
    timings["analysis"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    ctrl = scene.funnel_controller(model, ref, lin, t_end=t_end, **dict(feedback or {}))
    timings["controller"] = time.perf_counter() - t0
    if inverse is None and invert:
        t0 = time.perf_counter()
        if progress:
            print("inverting the reference model (servo constraints) ...", file=sys.stderr)
        from ..inversion import invert_scene

        inverse = invert_scene(scene, params, model=model, reference=ref)
        timings["inversion"] = time.perf_counter() - t0
    q0 = scene.initial_configuration(plant) if q0 is None else np.asarray(q0, float)
    return TrackingSetup(scene, model, plant, ref, lin, ctrl, inverse, q0, float(t_end), float(dt),
                         scene.end_effector_expr(model), timings)


def a1_along(setup: TrackingSetup, res: ClosedLoopResult, stride: int = 10) -> dict:
    """(A1) along a trajectory: smallest eigenvalue of the symmetric part of
    ``rho [K_1 Q~^(k_1-1) P~; ...; K_m] S~(q, v)`` at every ``stride``-th grid point (> 0 required)."""
    from ..analysis import schur_complement

    ctrl = setup.controller
    rows = [ctrl.K[i] @ np.linalg.matrix_power(ctrl.Qt, ctrl.k_i[i] - 1) @ ctrl.Pt for i in range(ctrl.q_rows)]
    rows += [ctrl.K[i] for i in range(ctrl.q_rows, len(ctrl.K))]
    Kmat = ctrl.rho * np.vstack(rows)
    idx = np.arange(0, res.t.size, stride)
    S = schur_complement(setup.model).map(idx.size)
    th = np.tile(setup.model.theta_values[:, None], (1, idx.size))
    Ss = np.array(S(res.q[:, idx], res.v[:, idx], th)).reshape(Kmat.shape[1], idx.size, -1).transpose(1, 0, 2)
    KS = np.einsum("ij,njk->nik", Kmat, Ss)
    ev = np.linalg.eigvalsh(0.5 * (KS + KS.transpose(0, 2, 1)))[:, 0]
    return {"min_eig": float(ev.min()), "t_min": float(res.t[idx][np.argmin(ev)]),
            "fraction_positive": float(np.mean(ev > 0))}


def run_controller(setup: TrackingSetup, name: str, *, raise_on_violation=True, v0=None) -> ClosedLoopResult:
    """One closed-loop run of controller ``name`` on ``setup``."""
    return setup.loop(name).run(setup.q0, v0, controller_label=name, raise_on_violation=raise_on_violation)


@dataclass
class TrackingStudy:
    """Runs of C1/C2/C3 with the comparison of 003 Sect. 6."""

    runs: dict
    info: dict = field(default_factory=dict)
    setup: object = field(default=None, repr=False, compare=False)

    def reduction(self, kind: str = "output", a: str = "C1", b: str = "C2") -> float:
        """``1 - E_a / E_b`` for the cumulative ``kind`` ("output" or "endeffector") error."""
        key = f"cumulative_{kind}_error"
        return 1.0 - getattr(self.runs[a], key) / getattr(self.runs[b], key)

    @property
    def reductions(self) -> dict:
        if not {"C1", "C2"} <= set(self.runs):
            return {}
        return {"output": self.reduction("output"), "endeffector": self.reduction("endeffector")}

    def table(self) -> str:
        head = (f"{'':4s} {'controller':22s} {'cum. |y-y_ref|':>15s} {'cum. |r-r_ref|':>15s} {'final |e_y|':>12s} "
                f"{'max phi|e|':>11s} {'margin':>8s} {'|u1|max':>9s} {'|u2|max':>9s} {'drift':>9s} {'wall s':>7s}")
        lines = [head, "-" * len(head)]
        for name, r in self.runs.items():
            ratio = f"{r.max_funnel_ratio:11.4f}" if r.ratios.size else f"{'-':>11s}"
            margin = f"{r.funnel_margin:8.4f}" if r.ratios.size else f"{'-':>8s}"
            pk = r.input_peaks
            lines.append(f"{name:4s} {CONTROLLERS.get(name, ''):22s} {r.cumulative_output_error:15.6g} "
                         f"{r.cumulative_endeffector_error:15.6g} {r.output_error[-1]:12.4g} {ratio} {margin} "
                         f"{pk[0]:9.3g} {pk[1]:9.3g} {r.max_constraint_drift:9.2g} {r.wall_s:7.3f}")
        red = self.reductions
        if red:
            lines.append(f"C1 reduces C2's cumulative error by {100 * red['output']:.1f} % (y) and "
                         f"{100 * red['endeffector']:.1f} % (end effector); paper: 40 % and 50 %")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {"runs": {k: r.summary() for k, r in self.runs.items()}, "reductions": self.reductions,
                "info": self.info}

    def save(self, directory) -> None:
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        for name, r in self.runs.items():
            r.save(d / f"run_{name}.npz")
        (d / "study.json").write_text(json.dumps(self.to_dict(), indent=1, default=float))

    @classmethod
    def load(cls, directory) -> "TrackingStudy":
        d = Path(directory)
        meta = json.loads((d / "study.json").read_text())
        runs = {name: ClosedLoopResult.load(d / f"run_{name}.npz") for name in meta["runs"]}
        return cls(runs, meta.get("info", {}))

    def plot(self, out_dir=None, fmt="png"):
        """Figures matching 003 Figs. 5-9; written to ``out_dir`` if given. Returns the figures."""
        from ..plot.tracking import plot_study

        return plot_study(self, out_dir, fmt)


def run_tracking_study(scene, params=None, plant_params=None, *, controllers=("C1", "C2", "C3"), setup=None,
                       progress=True, **setup_options) -> TrackingStudy:
    """Simulate the controllers on the mismatched plant and compare (003 Sect. 6).

    A run that leaves its funnel is kept (``status == "funnel_violation"``, truncated) and reported.
    """
    setup = setup if setup is not None else setup_tracking(scene, params, plant_params, progress=progress,
                                                           invert=bool({"C1", "C3", "C1-42"} & set(controllers)),
                                                           **setup_options)
    runs = {}
    for name in controllers:
        if progress:
            print(f"simulating {name} ({CONTROLLERS.get(name, '?')}) ...", file=sys.stderr)
        try:
            runs[name] = run_controller(setup, name)
        except FunnelViolation as exc:
            runs[name] = exc.partial
    a1 = {name: a1_along(setup, r) for name, r in runs.items() if r.t.size > 1}
    info = {"a1_along_trajectory": a1, "params": dict(params or {}), "plant": {k: v for k, v in setup.plant.values.items()
                                                    if v != setup.model.values.get(k)},
            "timings": dict(setup.timings), "t_end": setup.t_end, "dt": setup.dt}
    return TrackingStudy(runs, info, setup)
