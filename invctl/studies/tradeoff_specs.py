"""Speed-versus-accuracy specs for any scene (``invctl study tradeoff <scene> [--job JOB]``).

Jobs by scene kind, each sweeping the accuracy knob of the job against an independent, finely
resolved reference (a scene may add its own jobs in ``Scene.studies``):

* tracking, ``invert`` (default with a reference): collocation scheme and mesh size of the
  servo-constraint inversion; error = forward-check output error (a tight CVODES simulation of
  the model under ``u_ff`` that shares no code with the collocation equations), time = build + solve.
* tracking, ``simulate``: CVODES tolerance ``rtol`` (``atol = rtol / 100``) of the compiled C1 loop
  (C2 in smoke mode); error = max output deviation from the same loop at ``rtol = 1e-12``.
* tracking, ``analyze`` (default without a reference): the number of random region samples of
  ``invctl analyze --samples``; error = relative excess of the smallest singular value of Gamma
  found over the region's true minimum (dense sampling + multistart local optimisation).
* contact, ``rest`` (default when the scene declares ``Contact.exact_rest`` and ``exact_impacts``):
  the Moreau-Jean step ``h`` over the whole impact sequence to rest, against the closed-form rest time
  and impact times; ``simulate`` (default otherwise): the Moreau-Jean step ``h`` of the default
  controller against the same loop at a 16x finer step; ``impacts``: the first impact times and
  post-impact velocities against the event-driven simulation (DOP853, located events), or against
  the scene's closed form (``Contact.exact_impacts``).
* switched, ``simulate``: the sampling step ``h_max`` of the exact event-located propagation; the
  force RMS error against ``h_max = 1e-5`` (switch times and peak force are exact at every step).
"""
from __future__ import annotations

import itertools
import time
from typing import Any, Callable

import numpy as np

from ..errors import SceneError
from .tradeoff import TradeoffSpec


def fitted_order(knob, error) -> float:
    """Least-squares slope of ``log(error)`` against ``log(knob)`` (the convergence order)."""
    k, e = np.asarray(knob, float), np.asarray(error, float)
    ok = (e > 0) & np.isfinite(e)
    if ok.sum() < 2:
        return float("nan")
    return float(np.polyfit(np.log(k[ok]), np.log(e[ok]), 1)[0])


# ----------------------------------------------------------------- inversion
def tracking_invert(scene, params: dict, settings: dict, smoke: bool = False) -> TradeoffSpec:
    from ..inversion import forward_check
    from .tracking import invert_tracking, tracking_model

    model, ref = tracking_model(scene, params)
    values: list[dict[str, Any]]
    if smoke:
        values = [{"scheme": "hermite-simpson", "N": 40}, {"scheme": "hermite-simpson", "N": 80},
                  {"scheme": "radau3", "N": 20}]
    else:
        values = ([{"scheme": "hermite-simpson", "N": n} for n in (40, 80, 160, 320)]
                  + [{"scheme": "radau3", "N": n} for n in (20, 40, 80, 160)]
                  + [{"scheme": "legendre2", "N": n} for n in (40, 80, 160)])

    def run(value):
        inv = invert_tracking(scene, model, ref, N=int(value["N"]), scheme=value["scheme"])
        d = inv.diagnostics
        fc = forward_check(model, inv, ref)
        return {"error": float(fc["error"]), "time_s": float(d["build_s"] + d["solve_s"]),
                "build_s": float(d["build_s"]), "solve_s": float(d["solve_s"]),
                "iterations": int(d.get("iterations", -1)), "group": value["scheme"]}

    return TradeoffSpec(
        knob="scheme,N", values=values, run=run,
        reference="forward check (invctl.inversion.forward_check): the reference model simulated under u_ff by "
                  "CVODES (rtol = atol = 1e-12, windowed against the unstable internal mode) from the inverse "
                  "state at t0, no code shared with the collocation equations",
        error_name="forward-check output error max|y - y_ref|", repeat=False)


# ---------------------------------------------------------------- closed loop
def tracking_simulate(scene, params: dict, settings: dict, smoke: bool = False) -> TradeoffSpec:
    from ..simulate.closed_loop import ClosedLoop
    from .tracking import setup_tracking

    controller = "C2" if smoke else "C1"
    setup = setup_tracking(scene, params, invert=controller == "C1")
    uff = setup.u_ff_samples() if controller == "C1" else None

    def loop(rtol):
        return ClosedLoop(setup.plant, setup.reference, controller=setup.controller, u_ff=uff,
                          signals=setup.signals, t_end=setup.t_end, dt=setup.dt, rtol=rtol, atol=rtol * 1e-2,
                          max_num_steps=10**6, name=controller)

    ref = loop(1e-12).run(setup.q0, controller_label=controller)
    values = [1e-3, 1e-5, 1e-7] if smoke else [1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-10]

    def run(rtol):
        res = loop(float(rtol)).run(setup.q0, controller_label=controller)
        return {"error": float(np.max(np.abs(res.y - ref.y))), "time_s": float(res.wall_s),
                "cumulative_output_error": res.cumulative_output_error,
                "max_funnel_ratio": res.max_funnel_ratio}

    return TradeoffSpec(
        knob="rtol", values=values, run=run,
        reference=f"the same compiled {controller} loop (CVODES BDF) at rtol = 1e-12, atol = 1e-14",
        error_name=f"max |y - y_tight| over the {setup.t_end:g} s {controller} run")


# ------------------------------------------------------------ switched contact
def switched(scene, params: dict, settings: dict, smoke: bool = False) -> TradeoffSpec:
    s = scene.model(params)
    ref = s.simulate(h_max=2e-5 if smoke else 1e-5, samples_per_period=4)
    values = [5e-4, 2.5e-4, 1.25e-4] if smoke else [2e-3, 1e-3, 5e-4, 2.5e-4, 1.25e-4, 6.25e-5, 3.125e-5]

    def run(h):
        tic = time.perf_counter()
        sim = s.simulate(h_max=float(h), samples_per_period=4)
        wall = time.perf_counter() - tic
        same = sim.event_t.size == ref.event_t.size
        return {"error": abs(sim.force_rms_error - ref.force_rms_error) / max(ref.force_rms_error, 1e-12),
                "time_s": wall, "samples": int(sim.t.size),
                "event_time_error": float(np.max(np.abs(sim.event_t - ref.event_t), initial=0.0)) if same
                else float("inf"),
                "peak_force_error": abs(sim.peak_force - ref.peak_force) / max(abs(ref.peak_force), 1e-12)}

    return TradeoffSpec(
        knob="h_max", values=values, run=run,
        reference="the same exact (matrix-exponential, event-located) propagation sampled at h_max = 1e-5 s",
        error_name="relative error of the force RMS error (sampled quadrature)")


# ------------------------------------------------------------------ contact
def contact_fine_step(scene, params: dict, settings: dict, smoke: bool = False) -> TradeoffSpec:
    from ..simulate.timestepping import MoreauJean
    from .contact import _setting, contact_setup

    run0 = contact_setup(scene, params, settings)
    model, law, q0, v0 = run0.model, run0.law, run0.q0, run0.v0
    mj = MoreauJean(model, law, projection=bool(_setting(run0.settings, "projection")))
    t_end = min(0.5, _setting(run0.settings, "t_end"))
    values = [1e-3, 2.5e-4, 6.25e-5] if smoke else [1e-3, 5e-4, 2.5e-4, 1.25e-4, 6.25e-5, 3.125e-5]
    h_ref = min(values) / 16
    ref = mj.run(q0, v0, t_end, h_ref)
    grid = np.linspace(0.0, t_end, 501)
    # the coordinates the controller acts on (all when it names none)
    idx = list(law.info.get("idx", range(model.n)))
    q_ref = np.array([np.interp(grid, ref.t, ref.q[i]) for i in idx])  # q: (n, len(t))

    def run(h):
        tr = mj.run(q0, v0, t_end, float(h))
        q = np.array([np.interp(grid, tr.t, tr.q[i]) for i in idx])
        return {"error": float(np.max(np.abs(q - q_ref))), "time_s": float(tr.stats["wall_s"]),
                "steps_per_s": float(tr.stats["steps_per_s"]), "max_gap_violation": float(tr.max_gap_violation)}

    return TradeoffSpec(
        knob="h", values=values, run=run,
        reference=f"the same Moreau-Jean loop (controller {run0.controller}) at h = {h_ref:.3g} s (16x the finest "
                  "step)",
        error_name=f"max deviation of {', '.join(model.q_names[i] for i in idx)} from the fine-step run over "
                   f"[0, {t_end:g}] s")


def contact_impacts(scene, params: dict, settings: dict, smoke: bool = False) -> TradeoffSpec:
    from ..simulate.event_driven import simulate_event_driven
    from ..simulate.timestepping import MoreauJean
    from .contact import _setting, contact_setup

    run0 = contact_setup(scene, params, settings)
    model, law, q0, v0 = run0.model, run0.law, run0.q0, run0.v0
    potential = scene.contact.potential(model) if scene.contact.potential is not None else None
    exact = scene.contact.exact_impacts
    horizon = min(_setting(run0.settings, "t_end"), 10.0)
    if exact is not None:
        rt, rp = (np.asarray(a, float) for a in exact(model, run0.settings, horizon))
        reference = "the scene's closed-form impact times and post-impact velocities"
    else:
        ev = simulate_event_driven(model, q0, v0, horizon, law=law, potential=potential, max_impacts=3)
        rt, rp = np.asarray(ev.stats["impact_t"], float), np.asarray(ev.stats["impact_post"], float)
        reference = "event-driven simulation (DOP853, rtol = atol = 1e-12, located events)"
    if rt.size < 1:
        raise SceneError(f"scene {scene.name!r}: no impact before t = {horizon:g} s; the impacts study needs one")
    k = min(3, rt.size)
    t_end = min(horizon, float(rt[k - 1]) + 0.05)
    mj = MoreauJean(model, law, potential=potential)

    def run(h):
        tr = mj.run(q0, v0, t_end, float(h), theta=_setting(run0.settings, "theta"))
        ti, _, _, post, _ = tr.impacts()
        kk = min(k, ti.size)
        if kk < k:
            return {"error": float("inf"), "time_s": tr.stats["wall_s"]}
        return {"error": float(max(np.max(np.abs(ti[:k] - rt[:k])), np.max(np.abs(post[:k] - rp[:k])))),
                "time_s": tr.stats["wall_s"], "steps_per_s": tr.stats["steps_per_s"]}

    values = [1e-3, 2.5e-4, 6.25e-5] if smoke else [1e-3, 5e-4, 2.5e-4, 1.25e-4, 6.25e-5, 3.125e-5, 1.5625e-5]
    return TradeoffSpec(knob="h", values=values, run=run, reference=reference,
                        error_name=f"max error of the first {k} impact times [s] and post-impact velocities")


def contact_rest(scene, params: dict, settings: dict, smoke: bool = False) -> TradeoffSpec:
    """The whole impact sequence to rest against the scene's closed form (``Contact.exact_rest`` and
    ``exact_impacts``): error = the larger of the rest-time error and the largest impact-time error over
    the impacts every setting resolves (closed-form flight before them longer than 10 coarsest steps)."""
    from ..simulate.timestepping import MoreauJean
    from .contact import _setting, contact_setup

    run0 = contact_setup(scene, params, settings)
    model, law, q0, v0 = run0.model, run0.law, run0.q0, run0.v0
    rest = float(scene.contact.exact_rest(model, run0.settings))
    if not (np.isfinite(rest) and rest > 0):
        raise SceneError(f"scene {scene.name!r}: the closed-form rest time is {rest:g}: the run never comes to rest "
                         "(e.g. restitution e = 1); use --job impacts")
    values = [1e-3, 2.5e-4, 6.25e-5] if smoke else [1e-3, 2.5e-4, 6.25e-5, 1.5625e-5]
    rt, _ = (np.asarray(a, float) for a in scene.contact.exact_impacts(model, run0.settings, rest))
    flights = np.diff(np.r_[0.0, rt])
    k = int(np.argmin(flights > 10 * max(values))) if np.any(flights <= 10 * max(values)) else rt.size
    if k < 1:
        raise SceneError(f"scene {scene.name!r}: no impact is resolved by h = {max(values):g}; the rest study "
                         "needs one")
    t_end = 1.25 * rest
    potential = scene.contact.potential(model) if scene.contact.potential is not None else None
    mj = MoreauJean(model, law, potential=potential)

    def run(h):
        tr = mj.run(q0, v0, t_end, float(h), theta=_setting(run0.settings, "theta"))
        ti = tr.impacts()[0]
        t_rest = tr.rest_time()
        imp = float(np.max(np.abs(ti[:k] - rt[:k]))) if ti.size >= k else float("inf")
        rest_err = abs(t_rest - rest) if np.isfinite(t_rest) else float("inf")
        return {"error": max(imp, rest_err), "time_s": float(tr.stats["wall_s"]), "steps": int(tr.stats["steps"]),
                "impact_time_error": imp, "rest_time_error": rest_err, "rest_time": float(t_rest),
                "impacts": int(ti.size)}

    return TradeoffSpec(
        knob="h", values=values, run=run,
        reference=f"the scene's closed form: rest (accumulation) time {rest:.6g} s and the first {k} impact times "
                  f"(those with a flight longer than 10 h of the coarsest step); each run covers [0, {t_end:.4g}] s",
        error_name="max(|rest time error|, max impact time error) [s]")


# --------------------------------------------------------------- analysis only
def _region_box(model):
    reg = model.region
    lo, hi = np.asarray(reg.q_lower, float), np.asarray(reg.q_upper, float)
    if reg.sample_bounds is not None:
        lo = np.maximum(lo, np.asarray(reg.sample_bounds[0], float))
        hi = np.minimum(hi, np.asarray(reg.sample_bounds[1], float))
    n = model.n
    vlo, vhi = -reg.v_scale * np.ones(n), reg.v_scale * np.ones(n)
    return np.concatenate([lo, vlo]), np.concatenate([hi, vhi])


def gamma_min_reference(model, gamma, *, dense: int = 20000, starts: int = 6, seed: int = 12345) -> dict:
    """Smallest singular value of Gamma on the (closed) operating region: dense sampling,
    then SLSQP from the best ``starts`` samples within the box and the region's constraints."""
    from scipy.optimize import minimize

    reg = model.region
    th = model.theta_values
    n = model.n
    qs, vs = reg.sample(dense, rng=seed)
    G = np.array(gamma.map(qs.shape[0])(qs.T, vs.T, np.tile(th[:, None], (1, qs.shape[0]))))
    k = int(gamma.size1_out(0))
    Gs = G.reshape(k, qs.shape[0], k).transpose(1, 0, 2)
    smin = np.linalg.svd(Gs, compute_uv=False)[:, -1]
    lo, hi = _region_box(model)

    def f(z):
        return float(np.linalg.svd(np.array(gamma(z[:n], z[n:], th)), compute_uv=False)[-1])

    cons = [{"type": "ineq", "fun": (lambda z, c=c: float(c(z[:n])))} for c in reg.constraints]
    best = float(smin.min())
    where = np.concatenate([qs[int(np.argmin(smin))], vs[int(np.argmin(smin))]])
    for i in np.argsort(smin)[:starts]:
        z0 = np.concatenate([qs[i], vs[i]])
        res = minimize(f, z0, method="SLSQP", bounds=list(zip(lo, hi)), constraints=cons,
                       options={"ftol": 1e-14, "maxiter": 200})
        z = np.clip(res.x, lo, hi)
        if all(c(z[:n]) >= 0 for c in reg.constraints) and f(z) < best:
            best, where = f(z), z
    return {"sigma_min": best, "point": where, "dense_min": float(smin.min())}


def analysis(scene, params: dict, settings: dict, smoke: bool = False) -> TradeoffSpec:
    from ..analysis import relative_degree

    model = scene.model(params)
    if model.region is None:
        raise SceneError(f"scene {model.name!r} has no operating region to sample")
    warm = relative_degree(model, samples=2, rng=0)  # the Lie chain once; the knob is the sampling
    ref = gamma_min_reference(model, warm.gamma)
    smin_true = ref["sigma_min"]
    seeds = range(1, 6)
    values = [10, 100, 1000] if smoke else [10, 30, 100, 300, 1000, 3000, 10000]

    calls = itertools.count()

    def run(samples):
        errs, wall = [], 0.0
        base = 10**6 * next(calls) + 1000 * int(samples)  # fresh points per call: no cache hits
        for s in seeds:
            tic = time.perf_counter()
            rd = relative_degree(model, samples=int(samples), rng=base + s)
            wall += time.perf_counter() - tic
            errs.append((rd.min_singular_value - smin_true) / smin_true)
        return {"error": float(np.mean(errs)), "time_s": wall / len(seeds), "worst_seed_error": float(max(errs))}

    return TradeoffSpec(
        knob="samples", values=values, run=run,
        reference=(f"smallest singular value of Gamma on the region = {smin_true:.6g} at z = "
                   f"{np.round(ref['point'], 4).tolist()} (20000 samples + SLSQP from the best 6)"),
        error_name="relative excess of the sampled min singular value of Gamma (mean of 5 seeds)")


#: scene kind -> {job: spec factory(scene, params, settings, smoke)}
def tracking_jobs(scene) -> dict[str, Callable[..., TradeoffSpec]]:
    """A tracking scene's jobs: inversion, closed loop and analysis (analysis alone without a reference)."""
    if scene.tracking.reference is None:
        return {"analyze": analysis}
    return {"invert": tracking_invert, "simulate": tracking_simulate, "analyze": analysis}


def contact_jobs(scene) -> dict[str, Callable[..., TradeoffSpec]]:
    """A contact scene's jobs: the whole sequence to rest first when the scene gives it in closed form."""
    jobs: dict[str, Callable[..., TradeoffSpec]] = {"simulate": contact_fine_step, "impacts": contact_impacts}
    if scene.contact.exact_rest is not None and scene.contact.exact_impacts is not None:
        jobs = {"rest": contact_rest, **jobs}
    return jobs


def switched_jobs(scene) -> dict[str, Callable[..., TradeoffSpec]]:
    return {"simulate": switched}


def jobs_of(scene) -> dict:
    """The trade-off jobs a scene offers (its own ``studies`` first), default first; the kind's jobs come from
    its workflow (:data:`invctl.studies.workflow.WORKFLOWS`)."""
    from .workflow import WORKFLOWS

    wf = WORKFLOWS.get(scene.kind)
    jobs = wf.tradeoff_jobs(scene) if wf is not None else {}
    return {**dict(scene.studies), **jobs}


def spec_for(scene, params: dict, settings: dict, *, smoke: bool = False, job: str | None = None) -> TradeoffSpec:
    """The trade-off spec of ``scene`` for ``job`` (default: the scene's first job)."""
    jobs = jobs_of(scene)
    if not jobs:
        raise SceneError(f"scene {scene.name!r} offers no speed-versus-accuracy study")
    default = next(iter(jobs))
    job = job or default
    if job not in jobs:
        raise SceneError(f"scene {scene.name!r}: no trade-off study for job {job!r}; choose one of {sorted(jobs)}")
    spec = jobs[job](scene, dict(params), dict(settings), smoke)
    if not isinstance(spec, TradeoffSpec):
        raise SceneError(f"scene {scene.name!r}: study {job!r} returned {type(spec).__name__}, not a TradeoffSpec")
    spec.scene = spec.scene or (scene.name if job == default else f"{scene.name}_{job}")
    return spec
