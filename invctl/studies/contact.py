"""The commands of contact scenes (000): simulate, pipeline, analyze (declared reports).

A contact scene declares its model (with gaps), its controllers (``name -> law(model, settings)``)
and initial states; the run is the compiled Moreau-Jean time-stepping scheme with the scene's
settings ``h`` (step), ``theta`` (theta-method), ``t_end``, ``projection`` (0/1) and
``activation_tol``. What a run reports follows from the law:

* every law: impacts, largest gap violation, steps per second;
* laws with a Lyapunov function (000 (37), (50)): its largest increase at impacts and elsewhere;
* pre-loading laws (000 (13), ``info["active"]``): the multiplier ``P/h`` against ``beta`` and
  whether the pre-loaded contacts stayed closed;
* regulation laws (``info["idx"]``, PD (36)): the final error of the regulated coordinates and speed,
  and where the run ends in the set of equilibria (40)-(41) of the closed loop (Prop. 2);
* tracking laws (``info["q_d"]`` with ``info["idx"]`` or ``info["tracked"]``): the tracking error,
  and for PD+ (000 (48)) the desired-velocity conditions (52) at impacts and (54) in persistent
  contact (Prop. 3);
* juggling laws (``info["outputs"]``, 000 (25)): the final gap error;

plus the scene's own :class:`~invctl.scenes.Report` entries.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from typing import TYPE_CHECKING, Any

from ..errors import ContactError, DimensionError, ParameterError, RunInterrupted, SceneError, SimulationFailed
from ..plot import close
from ..scenes import CommandResult, scene_reference
from . import pipeline
from .pipeline import Step
from .reports import add_reports, run_reports, write_run

if TYPE_CHECKING:
    from ..control.pdplus import FeedbackLaw
    from ..model import Model
    from ..scenes import Contact, Scene
    from ..simulate.contact_record import ContactTrajectory

#: settings of the time-stepping scheme a scene may leave out
DEFAULT_SETTINGS = {"theta": 0.5, "projection": 0.0, "activation_tol": 1e-12}
#: samples a contact command (simulate, pipeline) records per run by default: a longer run keeps every
#: k-th step (its statistics and impact table stay exact); ``record_every=1`` (``--record-every 1``) keeps all
DEFAULT_SAMPLES = 20000


@dataclass
class ContactRun:
    """A contact run with everything needed to report and redo it."""

    scene: Scene
    model: Model
    plant: Model
    controller: str
    law: FeedbackLaw
    q0: np.ndarray
    v0: np.ndarray
    settings: dict
    params: dict
    trajectory: ContactTrajectory | None = None
    stats: dict = field(default_factory=dict)

    @property
    def result(self) -> ContactTrajectory:
        """The trajectory of :func:`run_contact` (an error before it ran)."""
        if self.trajectory is None:
            raise SimulationFailed(f"scene {self.scene.name!r}, controller {self.controller!r}: not simulated yet; "
                                   "call run_contact(run) first")
        return self.trajectory

    @property
    def contact(self) -> Contact:
        """The scene's contact declaration."""
        return _contact(self.scene)

    def meta(self) -> dict:
        return {"scene": scene_reference(self.scene), "params": dict(self.params),
                "settings": dict(self.settings), "controller": self.controller}


def _contact(scene) -> Contact:
    if scene.contact is None:
        raise SceneError(f"scene {scene.name!r} declares no contact (Scene(contact=Contact(...))): "
                         "it is not a contact scene")
    return scene.contact


def _setting(settings, name):
    if name in settings:
        return float(settings[name])
    if name in DEFAULT_SETTINGS:
        return DEFAULT_SETTINGS[name]
    raise SceneError(f"a contact scene needs the setting {name!r} (time step h, horizon t_end)")


def _values(scene, params, settings) -> dict:
    """Every parameter and setting of a run (the scene's defaults, then the given values)."""
    return {**scene.params, **scene.settings, **params, **settings}


def contact_setup(scene, params=None, settings=None, *, controller=None, plant_params=None, model=None) -> ContactRun:
    """Model (``model``: already built from ``params``), plant, law and initial state of a contact scene's run."""
    from ..control.pdplus import zero_input
    from .tracking import plant_of

    params, settings = dict(params or {}), dict(settings or {})
    model = scene.model(params) if model is None else model
    plant = plant_of(scene, model, plant_params, plant_factors={})
    c = _contact(scene)
    name = c.controller_for(model, settings, controller)
    why = c.unmet(name, _values(scene, params, settings))
    if why:
        raise SceneError(f"scene {scene.name!r}: {why}")
    potential = c.potential(model) if c.potential is not None else None
    law = zero_input(potential) if name == "none" else c.controllers[name](model, settings)
    assert c.initial_state is not None  # required: Contact checks it when the scene is declared
    q0, v0 = c.initial_state(model, settings, name)
    q0, v0 = np.asarray(q0, float).ravel(), np.asarray(v0, float).ravel()
    if q0.size != model.n or v0.size != model.n:
        raise DimensionError(f"scene {scene.name!r}: initial_state returned q0, v0 of lengths {q0.size}, {v0.size}; "
                             f"the model has n = {model.n}")
    return ContactRun(scene, model, plant, name, law, q0, v0, settings, params)


def run_contact(run: ContactRun, *, t_end=None, progress=None, record_every: int | None = 1,
                record: str = "steps") -> ContactRun:
    """Simulate ``run`` with the compiled Moreau-Jean scheme; fills ``run.trajectory`` (``record_every``,
    ``record="events"``: a reduced record, the statistics exact; ``record_every=None``: every k-th step,
    at most :data:`DEFAULT_SAMPLES` samples of a step record)."""
    from ..simulate.timestepping import MoreauJean

    s = run.settings
    t_end = _setting(s, "t_end") if t_end is None else float(t_end)
    h = _setting(s, "h")
    if not (t_end > 0 and h > 0):
        raise ParameterError(f"need t_end > 0 and h > 0, got t_end = {t_end}, h = {h}")
    if record_every is None:
        steps = math.ceil(t_end / h - 1e-9)
        record_every = 1 if record == "events" else max(1, math.ceil(steps / DEFAULT_SAMPLES))
    potential = run.contact.potential(run.model) if run.contact.potential is not None else None
    mj = MoreauJean(run.model, run.law, potential=potential, projection=bool(_setting(s, "projection")))
    tic = time.perf_counter()
    run.trajectory = mj.run(run.q0, run.v0, t_end, h, theta=_setting(s, "theta"), params=run.plant.theta_values,
                            ctrl_params=run.model.theta_values, activation_tol=_setting(s, "activation_tol"),
                            progress=progress, record_every=int(record_every), record=record)
    run.stats["wall_s"] = time.perf_counter() - tic
    return run


def _qd_function(q_d, k):
    t = ca.SX.sym("t")
    qd = ca.SX(q_d(t))
    if qd.shape[0] != k:
        raise DimensionError(f"the desired trajectory q_d(t) has {qd.shape[0]} entries, expected {k}")
    return ca.Function("qd", [t], [qd, ca.jacobian(qd, t)])


def law_report(run: ContactRun) -> tuple[list, dict]:
    """The report lines and data that follow from the law of a contact run (module docstring)."""
    from ..stability.lyapunov import lyapunov_report

    tr, law = run.result, run.law
    info = dict(law.info)
    kap = dict(zip(law.kappa_names, law.kappa_values))
    h = tr.h
    lines: list[str] = []
    data: dict[str, Any] = {}
    if info.get("lyapunov", True) and law.name != "open_loop":
        rep = lyapunov_report(tr)
        data.update({"V0": rep.V0, "V_end": rep.V_end, "max_V_increase": rep.max_increase,
                     "max_V_increase_impacts": rep.max_increase_impacts,
                     "max_V_increase_smooth": rep.max_increase_smooth})
        lines.append(f"V: {rep.V0:.4g} -> {rep.V_end:.4g}, max increase {rep.max_increase:.2e} "
                     f"(impacts {rep.max_increase_impacts:.2e}, elsewhere {rep.max_increase_smooth:.2e})")
    if law.name == "open_loop":
        dE = max(0.0, tr.max_energy_increase)
        data["max_energy_increase"] = dE
        lines.append(f"mechanical energy {tr.energy[0]:.6g} -> {tr.energy[-1]:.6g}, largest one-step increase "
                     f"{dE:.2e}")
    if "active" in info:
        act = list(info["active"])
        beta = np.array([kap[f"beta{i + 1}"] for i in range(len(act))])
        lam = tr.P[act] / h  # (contacts, steps): time along the last axis
        err = float(np.max(np.abs(lam - beta[:, None])))
        kept = bool(np.all(tr.active[act]))
        gap = float(np.max(np.abs(tr.gaps[act])))
        from ..control.preload import preload_check

        chk = preload_check(run.model, run.q0, run.v0, act)
        data.update({"preloaded_contacts": act, "beta": beta.tolist(), "multiplier_error": err,
                     "contacts_kept": kept, "max_preloaded_gap": gap, "E_hat": chk.E_hat, "rank": chk.rank})
        lines.append(f"pre-loading contacts {act} (000 Lemma 1 at the start: E_hat = "
                     f"{np.round(chk.E_hat, 6).tolist()}, rank {chk.rank}): multiplier P/h vs beta = {beta.tolist()}: "
                     f"max error {err:.3e}; kept closed: {kept}; max |gap| {gap:.2e}")
    if "outputs" in info:
        outs = list(info["outputs"])
        yd = np.array([kap[f"yd{i + 1}"] for i in range(len(outs))])
        err = (tr.gaps[outs, -1] - yd).tolist()
        data.update({"juggled_gaps": outs, "gap_target": yd.tolist(), "gap_error_final": err})
        lines.append(f"gaps {outs} -> {np.round(tr.gaps[outs, -1], 8).tolist()} (target "
                     f"{np.round(yd, 12).tolist()})")
    tracked = info.get("tracked") or ((info["idx"], info["q_d"]) if "q_d" in info and "idx" in info else None)
    if tracked is not None:
        idx, q_d = list(tracked[0]), tracked[1]
        qd, dqd = (np.array(a) for a in _qd_function(q_d, len(idx)).map(tr.t.size)(tr.t[None, :]))
        err = tr.q[idx] - qd
        half = tr.t >= 0.5 * tr.t[-1]
        data.update({"tracking_error_max": float(np.max(np.abs(err))),
                     "tracking_error_last_half": float(np.max(np.abs(err[:, half])))})
        lines.append(f"tracking error of {[run.model.q_names[i] for i in idx]}: max {data['tracking_error_max']:.3e}, "
                     f"last half {data['tracking_error_last_half']:.3e}")
        if law.name == "pd_plus" and not tr.complete:
            lines.append("(52)/(54) not checked: they need every step (--record-every 1)")
        elif law.name == "pd_plus":
            data.update(_prop3_conditions(run, idx, q_d))
            lines.append(f"(52) violated at {data['impacts_violating_52']} of {data['impacts_checked']} impacts "
                         f"(largest V jump where it holds {data['max_V_jump_where_52_holds']:.2e}, where violated "
                         f"{data['max_V_jump_where_52_violated']:.2e}); (54) violated on "
                         f"{data['persistent_steps_violating_54']} of {data['persistent_steps']} persistent-contact steps")
    elif "idx" in info:
        idx = list(info["idx"])
        qd = np.array([kap[f"qd{j + 1}"] for j in range(len(idx))])
        err = (tr.q[idx, -1] - qd).tolist()
        speed = float(np.max(np.abs(tr.v[:, -1])))
        data.update({"regulation_error_final": err, "speed_final": speed})
        lines.append(f"regulation of {[run.model.q_names[i] for i in idx]} to {qd.tolist()}: final error "
                     f"{np.round(err, 10).tolist()}, final max |v| {speed:.2e} (000 Prop. 2)")
        eq_lines, eq_data = _equilibrium_report(run)
        lines += eq_lines
        data.update(eq_data)
    return lines, data


def _equilibrium_report(run: ContactRun) -> tuple[list, dict]:
    """Where a regulation run ends in the set of equilibria E of the closed loop (000 (40)-(41), Prop. 2):
    the equilibrium next to the final state (:func:`invctl.contact.equilibria.static_equilibrium`), the
    distance to it, the local dimension of E there and the residual of (40) at the final state with the
    multipliers of its last step (``P/h``).  Time-varying laws have no equilibria: nothing is reported."""
    from ..contact.equilibria import static_equilibrium, static_force

    tr, law, model = run.result, run.law, run.model
    t = ca.SX.sym("t")
    u, _, kappa = law.symbolic(model, t)
    if ca.depends_on(u, t):
        return [], {}
    # the law sees the nominal parameters (as in the run), the plant its own
    u = ca.substitute(ca.substitute(u, kappa, ca.DM(law.kappa_values)), model.theta, ca.DM(model.theta_values))
    F = static_force(model, u)
    th = run.plant.theta_values
    q_end = tr.q[:, -1]
    Fn = ca.Function("F", [model.q, model.theta], [F, ca.jacobian(ca.vertcat(*[g.expr for g in model.gaps]),
                                                                    model.q).T])
    F_end, W_end = (np.array(a) for a in Fn(q_end, th))
    lam_end = tr.P[:, -1] / tr.h if tr.P.shape[1] else np.zeros(len(model.gaps))
    res_end = float(np.max(np.abs(F_end.ravel() + W_end @ lam_end)))
    data: dict[str, Any] = {"equilibrium_residual_final": res_end, "static_force_scale": float(np.max(np.abs(F_end)))}
    try:
        e = static_equilibrium(model, F, q_end, theta=th)
    except ContactError as exc:
        data["equilibrium_error"] = str(exc)
        return [f"set of equilibria E (000 (40)): none found next to the final state ({exc})"], data
    data.update({"equilibrium_distance": e.distance, "equilibrium_dimension": e.dimension,
                 "equilibrium_q": e.q.tolist(), "equilibrium_multipliers": e.lam.tolist(),
                 "equilibrium_active": e.active.tolist()})
    return [f"set of equilibria E (000 (40)-(41)): the final state is {e.distance:.2e} from the equilibrium q* "
            f"next to it (E has local dimension {e.dimension} there; multipliers {np.round(e.lam, 6).tolist()}); "
            f"residual of (40) at the final state with lam = P/h: {res_end:.2e} (static force scale "
            f"{data['static_force_scale']:.3g})"], data


def _prop3_conditions(run: ContactRun, idx, q_d) -> dict:
    """000 (52) at the impact steps (``grad f_i^T qd_dot >= 0`` on the contacts that carry an impulse)
    and (54) along persistent contact, with the V jumps."""
    from ..contact.mechanics import ContactSystem

    tr, model = run.result, run.model
    imp = tr.impact_mask()  # (contacts, steps)
    k, i = np.nonzero(imp.T)  # ordered by step, then contact
    out = {"impacts_checked": int(k.size), "impacts_violating_52": 0, "max_V_jump_where_52_holds": 0.0,
           "max_V_jump_where_52_violated": 0.0, "persistent_steps": 0, "persistent_steps_violating_54": 0}
    fn = _qd_function(q_d, len(idx))
    cs = ContactSystem(model)
    th = model.theta_values

    def margins(steps, contacts, q_cols, times):
        """``grad f_i(q_k)^T qd_dot(t_k)`` for the (step, contact) pairs (``q_cols``: ``(n, pairs)``),
        through mapped Functions."""
        if not steps.size:
            return np.zeros(0)
        W = np.array(cs.f_W.map(steps.size)(q_cols, th)).reshape(model.n, cs.m_u, steps.size, order="F")
        dqd = np.zeros((model.n, steps.size))
        dqd[idx] = np.array(fn.map(steps.size)(times[None, :])[1]).reshape(len(idx), steps.size)
        return np.einsum("nk,nk->k", W[:, contacts, np.arange(steps.size)], dqd)

    if k.size:
        ok = margins(k, i, tr.q[:, k + 1], tr.t[k] + 0.5 * tr.h) >= 0
        dV = tr.V[k + 1] - tr.V[k]
        out.update({"impacts_violating_52": int(np.count_nonzero(~ok)),
                    "max_V_jump_where_52_holds": float(np.max(dV[ok])) if ok.any() else 0.0,
                    "max_V_jump_where_52_violated": float(np.max(dV[~ok])) if (~ok).any() else 0.0})
    loaded = tr.P > 0
    pers = loaded[:, 1:] & loaded[:, :-1]
    kp, ip = np.nonzero(pers.T)  # ordered by step, then contact
    kp = kp + 1
    if kp.size:
        m54 = margins(kp, ip, tr.q[:, kp], tr.t[kp])
        out.update({"persistent_steps": int(kp.size), "persistent_steps_violating_54": int(np.count_nonzero(m54 < 0))})
    return out


def _summary(run: ContactRun) -> tuple[list, dict]:
    """Report lines and data of a run: statistics, the law's report and the scene's declared reports."""
    tr = run.result
    ti = tr.impact_times
    lines = [f"{run.scene.name}: controller {run.controller}, h = {tr.h:g} s, t_end = {tr.t[-1]:.6g} s",
             f"impacts {ti.size}" + (f" (first: {np.round(ti[:5], 6).tolist()})" if ti.size else "")
             + f", max gap violation {tr.max_gap_violation:.2e}, steps/s {tr.stats['steps_per_s']:.3g} "
             f"({tr.stats['backend']})"]
    data = {"controller": run.controller, "h": tr.h, "n_impacts": int(ti.size), "impact_times": ti[:200].tolist(),
            "max_gap_violation": tr.max_gap_violation, "initial_gaps": tr.gaps[:, 0].tolist(),
            "clearance": (float(run.contact.clearance(run.model, run.settings))
                          if run.contact.clearance is not None else None),
            "steps_per_s": tr.stats["steps_per_s"],
            "backend": tr.stats["backend"], "steps": tr.stats["steps"], "q_final": tr.q[:, -1].tolist(),
            "v_final": tr.v[:, -1].tolist(), "settings": dict(run.settings),
            "record": tr.stats.get("record", "steps"), "record_every": int(tr.stats.get("record_every", 1)),
            "samples": int(tr.t.size)}
    if not tr.complete:
        lines.append(f"recorded {tr.t.size} of {tr.stats['steps'] + 1} steps ({data['record']}, every "
                     f"{data['record_every']}; statistics and impacts exact; --record-every 1 records all)")
    law_lines, law_data = law_report(run)
    lines, data = lines + law_lines, {**data, **law_data}
    if rdata := add_reports(lines, run.scene, run.model, run.params, run.settings, "simulate", result=run.trajectory,
                            controller=run.controller):
        data["reports"] = rdata
    return lines, data


def simulate(bound, *, controller=None, plant_params=None, t_end=None, out=None, plot=None, quiet=False,
             record_every: int | None = None, record: str = "steps") -> CommandResult:
    """Run one controller of a contact scene and report (module docstring); a long run is recorded
    decimated unless ``record_every`` is given (:data:`DEFAULT_SAMPLES`)."""
    scene, params = bound.scene, bound.params
    run = run_contact(contact_setup(scene, params, bound.settings, controller=controller, plant_params=plant_params,
                                    model=bound.model),
                      t_end=t_end, progress=None if not quiet else False, record_every=record_every, record=record)
    lines, data = _summary(run)
    write_run(lines, data, run.result, out=out, meta=run.meta(), plot=plot, what="trajectory", indent="",
              draw=lambda p: run.result.plot(p, title=f"{scene.name} ({run.controller})"))
    return CommandResult("\n".join(lines), data, run.trajectory)


class Session(pipeline.Session):
    """The contact pipeline's session (:mod:`.pipeline`): every declared controller that fits the given values
    (``Contact.requires``; the others are listed as skipped, with the reason), each with its own setup and
    report, figure and animation."""

    def __init__(self, bound, *, t_end=None, plant_params=None, quiet=False, record_every: int | None = None,
                 record: str = "steps"):
        self.bound, self.scene, self.params, self.settings = bound, bound.scene, bound.params, bound.settings
        scene = self.scene
        self.options = {"t_end": t_end, "record_every": record_every, "record": record}
        self.plant_params = plant_params
        contact = _contact(scene)
        names = list(contact.controllers) or ["none"]
        values = _values(scene, self.params, self.settings)
        self.skipped = {k: why for k in names if (why := contact.unmet(k, values))}
        self.controllers = [k for k in names if k not in self.skipped]
        if not self.controllers:
            raise SceneError(f"scene {scene.name!r}: no controller fits these values: "
                             + "; ".join(self.skipped.values()))
        self._runs: dict[str, ContactRun] = {}

    def head(self, out):
        lines = [f"skipped {why}" for why in self.skipped.values()] + ([""] if self.skipped else [])
        return lines, {"skipped": self.skipped}

    def run(self, name):
        setup = contact_setup(self.scene, self.params, self.settings, controller=name, plant_params=self.plant_params,
                              model=self.bound.model)
        try:
            run = run_contact(setup, progress=False, **self.options)
        except RunInterrupted as exc:
            if exc.partial is not None:
                exc.partial.meta = {**exc.partial.meta, **setup.meta()}
            raise
        self._runs[name] = run
        lines, data = _summary(run)
        return Step(run.trajectory, lines + [""], data)

    def meta(self, name):
        return self._runs[name].meta()

    def figure(self, name, step, out):
        close(step.trajectory.plot(out / f"run_{name}.png", title=f"{self.scene.name} ({name})"))

    def animation(self, name):
        return {"fps": 20, "title": f"{self.scene.name} ({name})"}



def analyze(bound, *, samples: int = 200) -> CommandResult:
    """The scene's declared analysis reports (e.g. pre-loading conditions against printed matrices)."""
    scene, params, model = bound.scene, bound.params, bound.model
    full = {**scene.settings, **bound.settings, "samples": float(samples)}
    text, data = run_reports(scene, model, params, full, "analyze")
    head = f"invctl analyze {scene.name}: n = {model.n}, gaps: {', '.join(g.name for g in model.gaps)}"
    return CommandResult(head + ("\n" + text if text else ""), {"scene": scene.name, "reports": data})


# ------------------------------------------------------------- after a run
#: a contact run warns when it penetrates more than this share of the clearance, and fails beyond 1
GAP_WARN = 0.1


def _check_contact_data(name: str, d: dict) -> tuple[str | None, str | None]:
    """(warning, failure) texts for one contact run's data: its largest penetration against the
    clearance the scene declares (``Contact.clearance``) or, by default, the largest gap at the start
    (the free room of a joint started in its clearance, the drop height of a ball; the largest gap seen
    later would count the penetration of one side of a joint as room on the other).  A run that starts
    with every contact closed and declares no clearance gives no scale: not judged."""
    viol, gaps0 = d.get("max_gap_violation"), d.get("initial_gaps")
    if viol is None or not gaps0:
        return None, None
    room = d.get("clearance") or max(gaps0)
    if d.get("clearance") is None and room <= 1e-12:
        return None, None
    ratio = viol / room if room > 0 else (math.inf if viol > 0 else 0.0)
    d["clearance_scale"], d["gap_violation_ratio"] = room, ratio
    source = "the clearance the scene declares" if d.get("clearance") else "the largest gap at the start"
    what = f"{name}: the largest penetration {viol:.3g} is {ratio:.3g} times the clearance scale ({source}, {room:.3g})"
    fix = "use a smaller step (--set h=...), the projection (--set projection=1) or a larger clearance"
    if not ratio <= 1.0:
        return None, f"{what}: the contacts of this run are not resolved; {fix}"
    if ratio > GAP_WARN:
        return f"warning: {what}; {fix}", None
    return None, None


def check_contact_result(scene: Scene, result: CommandResult) -> CommandResult:
    """Warn about, or fail on, the penetration of the runs in ``result`` (simulate or pipeline)."""
    runs = result.data["runs"] if "runs" in result.data else {result.data.get("controller", scene.name): result.data}
    warnings, failures = [], []
    for name, d in runs.items():
        w, f = _check_contact_data(f"{scene.name} ({name})", d)
        warnings += [w] if w else []
        failures += [f] if f else []
    if failures:
        written = result.data.get("out") or result.data.get("out_dir")
        raise SimulationFailed("; ".join(failures) + (f" (the run was written to {written})" if written else ""),
                               partial=result, diagnostics={"runs": {k: {kk: v.get(kk) for kk in (
                                   "max_gap_violation", "clearance_scale", "gap_violation_ratio")}
                                   for k, v in runs.items()}})
    if warnings:
        result.data.setdefault("warnings", []).extend(warnings)
        result.text = result.text + "\n" + "\n".join(warnings)
    return result
