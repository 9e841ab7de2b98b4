"""``invctl simulate`` handlers of the joint-clearance scenes (paper 000).

Every handler accepts all options of the ``simulate`` command
(``controller``, ``plant_set``, ``t_end``, ``out``, ``plot``) and raises
:class:`SceneError` for the ones its scene cannot honour.
"""
from __future__ import annotations

import time

import numpy as np

from ..errors import ParameterError, SceneError
from ..model.params import parse_assignments
from ..scenes import CommandResult
from ..simulate.timestepping import MoreauJean

_OPTIONS = {"controller", "plant_set", "t_end", "out", "plot"}


def _check_options(scene: str, options: dict):
    unknown = sorted(set(options) - _OPTIONS)
    if unknown:
        raise SceneError(f"{scene}: simulate does not take option(s) {unknown}")


def _finish(tr, options, text, data, title):
    if options.get("out"):
        data["out"] = str(tr.save(options["out"]))
        text += f"\ntrajectory written to {data['out']}"
    if options.get("plot"):
        from ..plot import close

        close(tr.plot(options["plot"], title=title))
        data["plot"] = options["plot"]
        text += f"\nfigure written to {options['plot']}"
    return CommandResult(text, data)


def _split(params: dict, defaults: dict, model_keys) -> tuple[dict, dict]:
    unknown = sorted(set(params) - set(defaults))
    if unknown:
        raise ParameterError(f"unknown parameter(s) {unknown}; known: {sorted(defaults)}")
    full = {**defaults, **params}
    return full, {k: full[k] for k in model_keys}


# ------------------------------------------------------------------ ball
def bouncing_ball_command(scene, params: dict, **options) -> CommandResult:
    """Drop the ball, compare impact times, post-impact velocities and the rest
    time with the closed form."""
    _check_options("bouncing_ball", options)
    if options.get("controller") not in (None, "none"):
        raise SceneError("bouncing_ball has no controller; drop --controller")
    if options.get("plant_set"):
        raise SceneError("bouncing_ball has no separate plant/controller models; use --set for parameters")
    p = scene.check_params(params)
    if options.get("t_end") is not None:
        p["t_end"] = float(options["t_end"])
    model = scene.build(**{k: p[k] for k in scene.MODEL_PARAMS})
    mj = MoreauJean(model, potential=scene.potential(model), projection=bool(p["projection"]))
    tr = mj.run([p["H"]], [0.0], p["t_end"], p["h"], theta=p["theta"])
    ti, _, pre, post, _ = tr.impacts()
    ex_t, ex_pre, ex_post, rest = scene.exact_impacts(p["H"], p["g"], p["e"], p["t_end"])
    k = min(len(ti), len(ex_t), 5)
    rest_num = tr.rest_time()
    E = tr.energy
    data = {
        "impact_times": ti[:50].tolist(),
        "impact_times_exact": ex_t[:50].tolist(),
        "impact_time_errors": (ti[:k] - ex_t[:k]).tolist(),
        "post_impact_velocities": post[:50].tolist(),
        "post_impact_velocity_errors": (post[:k] - ex_post[:k]).tolist(),
        "rest_time": rest_num, "rest_time_exact": rest,
        "max_gap_violation": tr.max_gap_violation,
        "max_energy_increase": float(np.max(np.diff(E), initial=0.0)),
        "max_V_increase": tr.max_V_increase,
        "steps_per_s": tr.stats["steps_per_s"], "backend": tr.stats["backend"], "steps": tr.stats["steps"],
        "params": p,
    }
    text = (f"bouncing ball: H = {p['H']} m, e = {p['e']}, h = {p['h']} s, theta = {p['theta']}\n"
            f"first impacts     {np.round(ti[:k], 5).tolist()}\n"
            f"closed form       {np.round(ex_t[:k], 5).tolist()}\n"
            f"rest time         {rest_num:.5g} s (closed form {rest:.5g} s)\n"
            f"max penetration   {tr.max_gap_violation:.3e} m\n"
            f"steps/s           {tr.stats['steps_per_s']:.3g} ({tr.stats['backend']})")
    return _finish(tr, options, text, data, "bouncing ball")


def bouncing_ball_tradeoff(scene, params: dict, smoke: bool = False):
    """Trade-off spec (for ``invctl study tradeoff bouncing_ball``): error of the
    first impact times against the closed form versus h."""
    from .tradeoff import TradeoffSpec

    p = scene.check_params(params)
    model = scene.build(**{k: p[k] for k in scene.MODEL_PARAMS})
    mj = MoreauJean(model, potential=scene.potential(model))
    ex_t = scene.exact_impacts(p["H"], p["g"], p["e"], 10.0)[0]
    t_end = min(ex_t[2] + 0.05, 10.0)

    def run(h):
        tic = time.perf_counter()
        tr = mj.run([p["H"]], [0.0], t_end, float(h), theta=p["theta"])
        wall = time.perf_counter() - tic
        ti = tr.impacts()[0][:3]
        return {"error": float(np.max(np.abs(ti - ex_t[:len(ti)]))), "time_s": wall}

    values = [1e-2, 3e-3, 1e-3] if smoke else [1e-2, 3e-3, 1e-3, 3e-4, 1e-4, 3e-5]
    return TradeoffSpec(knob="h", values=values, run=run, reference="closed-form impact times",
                        error_name="max error of the first three impact times [s]")


# ------------------------------------------------------------- prismatic
def prismatic_command(scene, params: dict, **options) -> CommandResult:
    """Pre-loading (both actuated), PD regulation or the Remark 4 switching
    strategy (body 1 only) on the prismatic clearance."""
    _check_options("prismatic_clearance", options)
    full, mp = _split(params, scene.PARAMS, scene.MODEL_PARAMS)
    act = int(full["actuators"])
    controller = options.get("controller") or ("pd" if act == 1 else "preload")
    if options.get("t_end") is not None:
        full["t_end"] = float(options["t_end"])
    model = scene.build(actuators=act, **mp)
    plant_over = parse_assignments(options.get("plant_set"), option="--plant-set")
    bad = sorted(set(plant_over) - set(scene.MODEL_PARAMS))
    if bad:
        raise SceneError(f"--plant-set accepts model parameters {list(scene.MODEL_PARAMS)}, got {bad}")
    plant = model.with_params(**plant_over)
    l, L = full["l"], full["L"]
    data: dict = {"controller": controller}
    if controller == "pd":
        if act != 1:
            raise SceneError("controller 'pd' acts on body 1 only: use --set actuators=1")
        from ..control.pdplus import pd_gravity

        law = pd_gravity(model, Kp=full["Kp"], Kv=full["Kv"], q_d=full["qd"], idx=[0])
        q0, v0 = [0.0, l + 0.5 * (L - 2 * l)], [0.0, full["v20"]]
    elif controller == "preload":
        from ..control.preload import preload_check, preload_law

        q0, v0 = [0.0, l], [0.0, 0.0]
        chk = preload_check(model, q0, v0, [0])
        Kp = full["Kp"] if act == 2 else 0.0
        Kv = full["Kv"] if act == 2 else 0.0
        law = preload_law(model, [0], beta=full["beta"], Kp=Kp, Kv=Kv,
                          y_d=[full["qd"], full["qd"] + l][:act])
        data["E_hat"] = chk.E_hat.tolist()
    elif controller == "switching":
        if act != 1:
            raise SceneError("controller 'switching' (Remark 4) drives body 1 only: use --set actuators=1")
        law = scene.switching_law(model, Kp=full["Kp"], Kv=full["Kv"], amp=full["amp"], period=full["period"])
        q0, v0 = [0.0, l], [0.0, 0.0]
    elif controller == "juggling":
        if act != 2:
            raise SceneError("controller 'juggling' (I/O linearization (25) of y = f1) needs --set actuators=2")
        from ..control.juggling import io_decoupling_check, juggling_law

        q0, v0 = [0.0, l + 0.5 * (L - 2 * l)], [0.0, full["v20"]]
        io_decoupling_check(model, q0, [0])
        y_d = 0.25 * (L - 2 * l)
        law = juggling_law(model, [0], Ky=full["Kp"], Dy=full["Kv"], y_d=y_d)
        data["y_d"] = y_d
    elif controller == "none":
        from ..control.pdplus import zero_input

        law = zero_input()
        q0, v0 = [0.0, l + 0.5 * (L - 2 * l)], [0.0, full["v20"]]
    else:
        raise SceneError(f"prismatic_clearance: unknown controller {controller!r}; "
                         "choose pd, preload, switching, juggling, none")
    mj = MoreauJean(model, law, projection=bool(full["projection"]))
    tr = mj.run(q0, v0, full["t_end"], full["h"], theta=full["theta"], params=plant.theta_values,
                ctrl_params=model.theta_values, activation_tol=full["activation_tol"])
    data.update({
        "impact_times": tr.impact_times[:100].tolist(),
        "n_impacts": int(tr.impact_times.size),
        "max_gap_violation": tr.max_gap_violation,
        "max_V_increase": tr.max_V_increase if law.info.get("lyapunov", True) else None,
        "steps_per_s": tr.stats["steps_per_s"], "backend": tr.stats["backend"], "steps": tr.stats["steps"],
        "q_final": tr.q[-1].tolist(), "v_final": tr.v[-1].tolist(),
    })
    text = f"prismatic clearance, controller {controller}, {act} actuator(s), h = {full['h']} s\n"
    if controller == "preload":
        lam = tr.P[:, 0] / full["h"]
        err = float(np.max(np.abs(lam - full["beta"])))
        data["multiplier_error"] = err
        data["contact_kept"] = bool(np.all(tr.active[:, 0]))
        data["max_f1"] = float(np.max(np.abs(tr.gaps[:, 0])))
        text += (f"multiplier P/h vs beta = {full['beta']}: max error {err:.3e}; contact kept: "
                 f"{data['contact_kept']}; max |f1| = {data['max_f1']:.2e}\n")
    if controller == "pd":
        data["q1_error_final"] = float(tr.q[-1, 0] - full["qd"])
    if controller == "juggling":
        data["gap_error_final"] = float(tr.gaps[-1, 0] - data["y_d"])
        text += f"gap f1 -> {tr.gaps[-1, 0]:.4e} m (y_d = {data['y_d']:.4e} m), impacts {tr.impact_times.size}\n"
    if controller == "switching":
        w = 2 * np.pi / full["period"]
        xd = l + full["amp"] * np.sin(w * tr.t)
        data["q2_tracking_error_max_last_half"] = float(np.max(np.abs(tr.q[len(tr.t) // 2:, 1] - xd[len(tr.t) // 2:])))
        modes = np.where(tr.gaps[:, 0] <= 1e-9, 1, np.where(tr.gaps[:, 1] <= 1e-9, 2, 0))
        data["mode_switches"] = int(np.count_nonzero(np.diff(modes)))
        text += f"body-2 tracking error (last half) {data['q2_tracking_error_max_last_half']:.3e} m\n"
    text += (f"impacts {data['n_impacts']}, max gap violation {tr.max_gap_violation:.2e}, "
             f"max V increase {data['max_V_increase']}, steps/s {tr.stats['steps_per_s']:.3g} ({tr.stats['backend']})")
    return _finish(tr, options, text, data, f"prismatic clearance ({controller})")


# ------------------------------------------------------------------ gears
def gear_ehat(scene, c4: float, J: float = 1.0):
    """``(D, E_hat)`` of 000 Example 4 at ``f1 = f4 = 0`` for equal inertias ``J``."""
    from ..control.preload import preload_check

    model = scene.build(c4=c4, J1=J, J2=J, J3=J)
    q = scene.preloaded_configuration(model)
    chk = preload_check(model, q, np.zeros(3), [0, 3])
    from ..contact.mechanics import ContactSystem

    D = ContactSystem(model).delassus(q, [0, 3])
    return D, chk.E_hat


def gear_analyze(scene, params: dict, **options) -> CommandResult:
    """E_hat of Example 4 computed for both f4 variants, compared with the
    printed matrix; the printed persistent-contact conditions are tested on
    ``samples`` random torques."""
    unknown = sorted(set(options) - {"samples"})
    if unknown:
        raise SceneError(f"gear_backlash analyze does not take option(s) {unknown}")
    full, _ = _split(params, scene.PARAMS, scene.MODEL_PARAMS)
    J = full["J1"]
    if not (full["J1"] == full["J2"] == full["J3"]):
        raise SceneError("the printed matrices of Example 4 assume J1 = J2 = J3; set equal inertias")
    out = {}
    for label, c4 in (("printed_f4", -1.0), ("mesh_f4", 1.0)):
        D, E = gear_ehat(scene, c4, J)
        out[label] = {"D_times_J": (D * J).tolist(), "E_hat": E.tolist(),
                      "E_hat_error_vs_printed": float(np.max(np.abs(E - scene.PRINTED_E_HAT))),
                      "D_error_vs_printed": float(np.max(np.abs(D * J - scene.PRINTED_D_TIMES_J)))}
    rng = np.random.default_rng(0)
    n = int(options.get("samples") or 200)
    tau = rng.normal(size=(n, 3))
    lhs = np.all(tau @ scene.PRINTED_E_HAT.T < 0, axis=1)
    rhs = (2 * tau[:, 0] > tau[:, 1] + tau[:, 2]) & (tau[:, 0] > -tau[:, 1] + 2 * tau[:, 2])
    out["printed_conditions_agree"] = bool(np.all(lhs == rhs))
    out["samples"] = n
    text = ("000 Example 4 (J1 = J2 = J3):\n"
            f"  printed E_hat          {np.round(scene.PRINTED_E_HAT * 3, 6).tolist()} / 3\n"
            f"  ours, f4 as printed    {np.round(np.array(out['printed_f4']['E_hat']) * 3, 6).tolist()} / 3 "
            f"(max diff {out['printed_f4']['E_hat_error_vs_printed']:.3g})\n"
            f"  ours, f4 = th3 - th2 + a4 {np.round(np.array(out['mesh_f4']['E_hat']) * 3, 6).tolist()} / 3 "
            f"(max diff {out['mesh_f4']['E_hat_error_vs_printed']:.3g})\n"
            f"  D*J (both variants)    {np.round(out['mesh_f4']['D_times_J'], 6).tolist()} (printed [[2,-1],[-1,2]])\n"
            f"  printed conditions 2t1 > t2 + t3, t1 > -t2 + 2t3 <=> E_hat t < 0 on {n} samples: "
            f"{out['printed_conditions_agree']}")
    return CommandResult(text, out)


def gear_command(scene, params: dict, **options) -> CommandResult:
    """Pre-load f1 and f4 (law (13)) while a collocated PD moves the train."""
    _check_options("gear_backlash", options)
    full, mp = _split(params, scene.PARAMS, scene.MODEL_PARAMS)
    controller = options.get("controller") or "preload"
    if controller != "preload":
        raise SceneError(f"gear_backlash offers controller 'preload' only, got {controller!r}")
    if options.get("t_end") is not None:
        full["t_end"] = float(options["t_end"])
    model = scene.build(c4=full["c4"], **mp)
    plant_over = parse_assignments(options.get("plant_set"), option="--plant-set")
    bad = sorted(set(plant_over) - set(scene.MODEL_PARAMS))
    if bad:
        raise SceneError(f"--plant-set accepts model parameters {list(scene.MODEL_PARAMS)}, got {bad}")
    plant = model.with_params(**plant_over)
    from ..control.preload import preload_check, preload_law

    q0 = scene.preloaded_configuration(model)
    chk = preload_check(model, q0, np.zeros(3), [0, 3])
    beta = np.array([full["beta1"], full["beta2"]])
    law = preload_law(model, [0, 3], beta=beta, Kp=full["Kp"], Kv=full["Kv"], y_d=q0 + full["qd"])
    mj = MoreauJean(model, law)
    tr = mj.run(q0, np.zeros(3), full["t_end"], full["h"], theta=full["theta"], params=plant.theta_values,
                ctrl_params=model.theta_values, activation_tol=full["activation_tol"])
    lam = tr.P[:, [0, 3]] / full["h"]
    err = float(np.max(np.abs(lam - beta)))
    data = {"E_hat": chk.E_hat.tolist(), "rank": chk.rank, "multiplier_error": err,
            "contacts_kept": bool(np.all(tr.active[:, [0, 3]])),
            "max_gap_f1_f4": float(np.max(np.abs(tr.gaps[:, [0, 3]]))),
            "impact_times": tr.impact_times[:100].tolist(), "max_gap_violation": tr.max_gap_violation,
            "max_V_increase": None, "steps_per_s": tr.stats["steps_per_s"], "backend": tr.stats["backend"],
            "q_final": tr.q[-1].tolist()}
    text = (f"gear backlash, pre-loading f1 = f4 = 0 with beta = {beta.tolist()}\n"
            f"E_hat = {np.round(chk.E_hat, 6).tolist()} (rank {chk.rank})\n"
            f"multiplier error {err:.3e}, contacts kept: {data['contacts_kept']}, "
            f"max |f1|,|f4| = {data['max_gap_f1_f4']:.2e}, steps/s {tr.stats['steps_per_s']:.3g}")
    return _finish(tr, options, text, data, "gear backlash (pre-loading)")


# ------------------------------------------------------------ slider-crank
def slider_crank_command(scene, params: dict, **options) -> CommandResult:
    """PD (36) regulation (Prop. 2) or PD+ (57) tracking of the crank with a
    revolute-joint clearance; V (37)/(50) monitored with its impact jumps."""
    from ..control.pdplus import pd_gravity, pd_plus_tracking
    from ..stability.lyapunov import lyapunov_report

    _check_options("slider_crank_clearance", options)
    full, mp = _split(params, scene.PARAMS, scene.MODEL_PARAMS)
    controller = options.get("controller") or "pd"
    if options.get("t_end") is not None:
        full["t_end"] = float(options["t_end"])
    model = scene.build(**mp)
    plant_over = parse_assignments(options.get("plant_set"), option="--plant-set")
    bad = sorted(set(plant_over) - set(scene.MODEL_PARAMS))
    if bad:
        raise SceneError(f"--plant-set accepts model parameters {list(scene.MODEL_PARAMS)}, got {bad}")
    plant = model.with_params(**plant_over)
    q0 = scene.centered_configuration(model, full["theta0"])
    if controller == "pd":
        law = pd_gravity(model, Kp=full["Kp"], Kv=full["Kv"], q_d=full["theta_d"], idx=[0])
    elif controller == "pdplus":
        import casadi as ca

        th0, amp, per = full["theta0"], full["amp"], full["period"]
        law = pd_plus_tracking(model, Kp=full["Kp"], Kv=full["Kv"],
                               q_d=lambda t: th0 + amp * ca.sin(2 * np.pi * t / per), idx=[0])
    else:
        raise SceneError(f"slider_crank_clearance: unknown controller {controller!r}; choose pd or pdplus")
    mj = MoreauJean(model, law, projection=bool(full["projection"]))
    tr = mj.run(q0, np.zeros(3), full["t_end"], full["h"], theta=full["theta"], params=plant.theta_values,
                ctrl_params=model.theta_values, activation_tol=full["activation_tol"])
    rep = lyapunov_report(tr)
    cond = _condition_52_at_impacts(tr, model, full, controller)
    data = {"controller": controller, **cond, "impact_times": tr.impact_times[:200].tolist(),
            "n_impacts": int(tr.impact_times.size), "max_gap_violation": tr.max_gap_violation,
            "max_V_increase": rep.max_increase, "max_V_increase_impacts": rep.max_increase_impacts,
            "max_V_increase_smooth": rep.max_increase_smooth, "V0": rep.V0, "V_end": rep.V_end,
            "steps_per_s": tr.stats["steps_per_s"], "backend": tr.stats["backend"],
            "q_final": tr.q[-1].tolist(), "v_final": tr.v[-1].tolist(),
            "contact_fraction": float(np.mean(tr.active[:, 0]))}
    if controller == "pd":
        data["crank_error_final"] = float(tr.q[-1, 0] - full["theta_d"])
        data["speed_final"] = float(np.max(np.abs(tr.v[-1])))
    else:
        w = 2 * np.pi / full["period"]
        err = tr.q[:, 0] - (full["theta0"] + full["amp"] * np.sin(w * tr.t))
        data["tracking_error_max"] = float(np.max(np.abs(err)))
        data["tracking_error_last_period"] = float(np.max(np.abs(err[tr.t >= tr.t[-1] - full["period"]])))
    text = (f"slider-crank with journal clearance c = {full['c']} m, controller {controller}\n"
            f"impacts {data['n_impacts']}, contact fraction {data['contact_fraction']:.2f}, "
            f"max gap violation {tr.max_gap_violation:.2e}\n"
            f"V: {rep.V0:.4g} -> {rep.V_end:.4g}, max increase {rep.max_increase:.2e} "
            f"(impacts {rep.max_increase_impacts:.2e}, elsewhere {rep.max_increase_smooth:.2e})\n")
    if controller == "pd":
        text += f"crank error {data['crank_error_final']:.2e} rad, max |v| {data['speed_final']:.2e} (Prop. 2)"
    else:
        text += (f"(52) violated at {cond['impacts_violating_52']} of {data['n_impacts']} impacts; largest V jump "
                 f"where (52) holds {cond['max_V_jump_where_52_holds']:.2e}, where violated "
                 f"{cond['max_V_jump_where_52_violated']:.2e}; (54) violated on {cond['persistent_steps_violating_54']} "
                 f"of {cond['persistent_steps']} persistent-contact steps\n")
        text += (f"tracking error max {data['tracking_error_max']:.3e} rad, last period "
                 f"{data['tracking_error_last_period']:.3e} rad")
    return _finish(tr, options, text, data, f"slider-crank clearance ({controller})")


def _condition_52_at_impacts(tr, model, full, controller):
    """Condition (52) at the impact steps: grad f_i^T qd_dot >= 0 on the contacts that
    carry an impulse (for those, Newton's law makes grad f_i^T w = 0), with the V jumps."""
    imp = tr.impact_mask()
    k, i = np.nonzero(imp)
    if controller != "pdplus" or k.size == 0:
        return {"impacts_violating_52": 0, "max_V_jump_where_52_holds": 0.0, "max_V_jump_where_52_violated": 0.0,
                "persistent_steps": 0, "persistent_steps_violating_54": 0}
    from ..contact.mechanics import ContactSystem

    cs = ContactSystem(model)
    w = 2 * np.pi / full["period"]
    t_imp = tr.t[k] + 0.5 * tr.h
    qd_dot = np.zeros((k.size, model.n))
    qd_dot[:, 0] = full["amp"] * w * np.cos(w * t_imp)
    margins = np.array([cs.gradients(tr.q[kk + 1])[:, ii] @ qd for kk, ii, qd in zip(k, i, qd_dot)])
    dV = tr.V[k + 1] - tr.V[k]
    ok = margins >= 0
    # (54) along persistent contact: loaded in consecutive steps, w = v
    pers = (tr.P[1:, 0] > 0) & (tr.P[:-1, 0] > 0)
    kp = np.flatnonzero(pers) + 1
    qdp = full["amp"] * w * np.cos(w * tr.t[kp])
    m54 = np.array([cs.gradients(tr.q[kk])[0, 0] * qq for kk, qq in zip(kp, qdp)])
    return {"persistent_steps": int(kp.size), "persistent_steps_violating_54": int(np.count_nonzero(m54 < 0)),
            "impacts_violating_52": int(np.count_nonzero(~ok)),
            "max_V_jump_where_52_holds": float(np.max(dV[ok], initial=-np.inf)) if ok.any() else 0.0,
            "max_V_jump_where_52_violated": float(np.max(dV[~ok], initial=-np.inf)) if (~ok).any() else 0.0}


def prismatic_tradeoff(scene, params: dict, smoke: bool = False):
    """Trade-off spec (``invctl study tradeoff prismatic_clearance``): 2-DoF clearance
    under PD (36) on body 1; error of the first three impact times and post-impact
    velocities against the event-driven reference versus h."""
    from ..control.pdplus import pd_gravity
    from .tradeoff import TradeoffSpec
    from ..simulate.event_driven import simulate_event_driven

    full, mp = _split(params, scene.PARAMS, scene.MODEL_PARAMS)
    model = scene.build(actuators=1, **mp)
    law = pd_gravity(model, Kp=full["Kp"], Kv=full["Kv"], q_d=full["qd"], idx=[0])
    l, L = full["l"], full["L"]
    q0, v0 = [0.0, l + 0.5 * (L - 2 * l)], [0.0, full["v20"]]
    ref = simulate_event_driven(model, q0, v0, 0.3, law=law)
    rt, rp = ref.stats["impact_t"][:3], ref.stats["impact_post"][:3]
    mj = MoreauJean(model, law)

    def run(h):
        tr = mj.run(q0, v0, 0.3, float(h))
        ti, _, _, post, _ = tr.impacts()
        k = min(3, ti.size)
        return {"error": float(max(np.max(np.abs(ti[:k] - rt[:k])), np.max(np.abs(post[:k] - rp[:k])))),
                "time_s": tr.stats["wall_s"], "steps_per_s": tr.stats["steps_per_s"]}

    values = [1e-3, 2.5e-4, 6.25e-5] if smoke else [1e-3, 5e-4, 2.5e-4, 1.25e-4, 6.25e-5, 3.125e-5, 1.5625e-5]
    return TradeoffSpec(knob="h", values=values, run=run,
                        reference="event-driven simulation (DOP853, rtol = atol = 1e-12, located events)",
                        error_name="max error of first 3 impact times [s] and post-impact velocities [m/s]")
