"""Speed-versus-accuracy specs of the shipped scenes (``invctl study tradeoff <scene>``).

A scene may define its own ``tradeoff_spec(params, smoke=False)``; the scenes
that do not get theirs from :data:`REGISTRY` here (scene name -> job -> spec
factory).  Every spec sweeps the accuracy knob of the scene's main job and
measures the error against an independent, finely resolved reference:

* ``manipulator`` (job ``invert``, default): collocation scheme and mesh size of
  the servo-constraint inversion; error = forward-check output error (a tight
  CVODES simulation of the model under ``u_ff`` that shares no code with the
  collocation equations), time = NLP build + solve.
* ``manipulator`` (job ``simulate``): CVODES tolerance ``rtol`` (``atol =
  rtol / 100``) of the compiled C1 closed loop (feedforward + funnel, m3 x 1.2
  plant); error = max output deviation from the same loop at ``rtol = 1e-12``.
* ``stiff_wall``, ``compliant_wrist``: the sampling step ``h_max`` of the exact
  event-located propagation.  Switch times and the peak force are exact at
  every step (reported as extra columns); what the step buys is the sampled
  output, scored by the force RMS error against ``h_max = 1e-5``.
* ``gear_backlash`` (pre-loading), ``slider_crank_clearance`` (PD regulation):
  the Moreau-Jean step ``h`` against the same loop at a 16x finer step
  (``bouncing_ball`` and ``prismatic_clearance`` bring their own specs: step
  against the closed form / the event-driven reference).
* ``cartpole``, ``two_link_arm``, ``knife_edge`` (analysis only): the number of
  random region samples of ``invctl analyze --samples``; error = relative excess
  of the smallest singular value of Gamma found over the region's true minimum
  (dense sampling + multistart local optimisation), averaged over seeds.
"""
from __future__ import annotations

import itertools
import time
from typing import Callable

import numpy as np

from ..errors import SceneError
from .tradeoff import TradeoffSpec

__all__ = ["REGISTRY", "spec_for", "fitted_order", "gamma_min_reference"]


def fitted_order(knob, error) -> float:
    """Least-squares slope of ``log(error)`` against ``log(knob)`` (the convergence order)."""
    k, e = np.asarray(knob, float), np.asarray(error, float)
    ok = (e > 0) & np.isfinite(e)
    if ok.sum() < 2:
        return float("nan")
    return float(np.polyfit(np.log(k[ok]), np.log(e[ok]), 1)[0])


# ----------------------------------------------------------------- inversion
def manipulator_invert(scene, params: dict, smoke: bool = False) -> TradeoffSpec:
    from ..inversion import forward_check, invert_scene

    model = scene.build(**params)
    ref = scene.reference(model)
    if smoke:
        values = [{"scheme": "hermite-simpson", "N": 40}, {"scheme": "hermite-simpson", "N": 80},
                  {"scheme": "radau3", "N": 20}]
    else:
        values = ([{"scheme": "hermite-simpson", "N": n} for n in (40, 80, 160, 320)]
                  + [{"scheme": "radau3", "N": n} for n in (20, 40, 80, 160)]
                  + [{"scheme": "legendre2", "N": n} for n in (40, 80, 160)])

    def run(value):
        inv = invert_scene(scene, model=model, reference=ref, N=int(value["N"]), scheme=value["scheme"])
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
        error_name="forward-check output error max|y - y_ref| [m, rad]", repeat=False)


# ---------------------------------------------------------------- closed loop
def manipulator_simulate(scene, params: dict, smoke: bool = False) -> TradeoffSpec:
    from ..simulate.closed_loop import ClosedLoop
    from .tracking import setup_tracking

    controller = "C2" if smoke else "C1"
    setup = setup_tracking(scene, params, invert=controller == "C1")
    uff = setup.u_ff_samples() if controller == "C1" else None
    ctrl = setup.c1_controller() if controller == "C1" else setup.controller

    def loop(rtol):
        return ClosedLoop(setup.plant, setup.reference, controller=ctrl, u_ff=uff,
                          endeffector=setup.endeffector, t_end=setup.t_end, dt=setup.dt, rtol=rtol,
                          atol=rtol * 1e-2, max_num_steps=10**6, name=controller)

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
def switched(scene, params: dict, smoke: bool = False) -> TradeoffSpec:
    s = scene.build(**params)
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


# ------------------------------------------------------- clearances (fine step)
def _clearance_setup(scene, name, params):
    from ..control.pdplus import pd_gravity
    from .contact_commands import _split

    full, mp = _split(params, scene.PARAMS, scene.MODEL_PARAMS)
    if name == "gear_backlash":
        from ..control.preload import preload_law

        model = scene.build(c4=full["c4"], **mp)
        q0 = scene.preloaded_configuration(model)
        law = preload_law(model, [0, 3], beta=np.array([full["beta1"], full["beta2"]]), Kp=full["Kp"],
                          Kv=full["Kv"], y_d=q0 + full["qd"])
        return model, law, q0, "pre-loading (13) of f1, f4 with a collocated PD", slice(None), "q"
    model = scene.build(**mp)
    law = pd_gravity(model, Kp=full["Kp"], Kv=full["Kv"], q_d=full["theta_d"], idx=[0])
    return (model, law, scene.centered_configuration(model, full["theta0"]), "PD (36) regulation of the crank",
            slice(0, 1), "crank angle theta")


def clearance_fine_step(scene, params: dict, smoke: bool = False) -> TradeoffSpec:
    from ..simulate.timestepping import MoreauJean

    name = scene.__name__.rsplit(".", 1)[-1]
    model, law, q0, what, idx, qname = _clearance_setup(scene, name, params)
    mj = MoreauJean(model, law)
    t_end = 0.5
    values = [1e-3, 2.5e-4, 6.25e-5] if smoke else [1e-3, 5e-4, 2.5e-4, 1.25e-4, 6.25e-5, 3.125e-5]
    h_ref = min(values) / 16
    ref = mj.run(q0, np.zeros(model.n), t_end, h_ref)
    grid = np.linspace(0.0, t_end, 501)
    q_ref = np.array([np.interp(grid, ref.t, ref.q[:, i]) for i in range(model.n)])[idx]

    def run(h):
        tr = mj.run(q0, np.zeros(model.n), t_end, float(h))
        q = np.array([np.interp(grid, tr.t, tr.q[:, i]) for i in range(model.n)])[idx]
        return {"error": float(np.max(np.abs(q - q_ref))), "time_s": float(tr.stats["wall_s"]),
                "steps_per_s": float(tr.stats["steps_per_s"]), "max_gap_violation": float(tr.max_gap_violation)}

    return TradeoffSpec(
        knob="h", values=values, run=run,
        reference=f"the same Moreau-Jean loop ({what}) at h = {h_ref:.3g} s (16x the finest step)",
        error_name=f"max deviation of {qname} from the fine-step run over [0, {t_end:g}] s")


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


def analysis(scene, params: dict, smoke: bool = False) -> TradeoffSpec:
    from ..analysis import relative_degree

    model = scene.build(**params)
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


#: scene name -> {job: spec factory(scene_module, params, smoke)}; the first job is the default
REGISTRY: dict[str, dict[str, Callable[..., TradeoffSpec]]] = {
    "manipulator": {"invert": manipulator_invert, "simulate": manipulator_simulate},
    "stiff_wall": {"simulate": switched},
    "compliant_wrist": {"simulate": switched},
    "cartpole": {"analyze": analysis},
    "two_link_arm": {"analyze": analysis},
    "knife_edge": {"analyze": analysis},
    "gear_backlash": {"simulate": clearance_fine_step},
    "slider_crank_clearance": {"simulate": clearance_fine_step},
}


def spec_for(scene_module, name: str, params: dict, *, smoke: bool = False, job: str | None = None) -> TradeoffSpec:
    """The trade-off spec of a scene: its own ``tradeoff_spec`` (when ``job`` is not given)
    or the registry entry for its name."""
    own = getattr(scene_module, "tradeoff_spec", None)
    entry = REGISTRY.get(name, {})
    if own is not None and (job is None or job not in entry):
        if job is not None and job != "simulate":
            raise SceneError(f"scene {name!r} offers its trade-off for its simulation only, not job {job!r}")
        return own(params, smoke=smoke)
    if not entry:
        raise SceneError(f"scene {name!r} offers no speed-versus-accuracy study (no tradeoff_spec, and "
                         f"invctl knows none for it); scenes with one: {sorted(REGISTRY)}")
    job = job or next(iter(entry))
    if job not in entry:
        raise SceneError(f"scene {name!r}: no trade-off study for job {job!r}; choose one of {sorted(entry)}")
    spec = entry[job](scene_module, params, smoke)
    spec.scene = spec.scene or (name if job == next(iter(entry)) else f"{name}_{job}")
    return spec

