"""000 mechanisms beyond the six-bar and the chain: the pivot with gear backlash (Fig. 2(a)), the
four-bar driven through its motor shaft (Fig. 6(b)), the recursive juggling design (29)-(33) on the
prismatic joint (Fig. 2(b)); the linkage builder and the subsystem analysis on their own; every new
scene through the generic commands with JSON and a figure."""
import json
import math

import numpy as np
import pytest

import invctl_scenes.backlash_pivot as bp
import invctl_scenes.fourbar_backlash as fb
import invctl_scenes.prismatic_clearance as pc
from invctl.contact.equilibria import static_equilibrium
from invctl.contact.linkage import GROUND, Joint, Linkage, bar
from invctl.contact.structure import open_structure
from invctl_scenes._juggling_design import (Juggler, JugglerState, design, design_cycle, juggling_plan_law,
                                            plan_vs_run)
from invctl.errors import JugglingInfeasible, ModelError, ParameterError
from invctl.model import ParamSet
from invctl.scenes import load_scene
from invctl.simulate.event_driven import simulate_event_driven
from invctl.studies.contact import contact_setup, run_contact


def _run(name, values, controller=None):
    scene = load_scene(name)
    params, settings = scene.split(values)
    return run_contact(contact_setup(scene, params, settings, controller=controller), progress=False)


# ----------------------------------------------------------------- pivot with gear backlash (Fig. 2(a))
def test_backlash_pivot_converges_to_the_closed_form_rest_point():
    """PD (36) on the shaft: V (37) never increases, the two flanks are never closed together, and the
    run ends at the rest point whose closed form (scalar root on flank f1) Newton on (40) reproduces
    to 1e-12.  The run rests 6e-7 rad away: the penetration left by the unprojected step (h = 1e-4)."""
    run = _run("backlash_pivot", {})
    tr, model, s = run.trajectory, run.model, run.settings
    assert tr.max_V_increase <= 1e-12 * abs(tr.V[0])
    assert not np.any((tr.gaps[0] <= 1e-9) & (tr.gaps[1] <= 1e-9))
    np.testing.assert_allclose(tr.gaps.sum(axis=0), 2 * model.values["alpha"], atol=1e-12)
    cf = bp.closed_form_equilibrium(model.values, s["Kp"], model.values["N"] * s["link_d"])
    assert cf["flank"] == "f1" and cf["lam"] > 0
    from invctl.contact.equilibria import static_force
    import casadi as ca

    u, _, kap = run.law.symbolic(model, ca.SX.sym("t"))
    e = static_equilibrium(model, ca.substitute(static_force(model, u), kap, ca.DM(run.law.kappa_values)), tr.q[:, -1])
    np.testing.assert_allclose(e.q, [cf["theta_m"], cf["theta_l"]], atol=1e-12)
    np.testing.assert_allclose(e.lam, [cf["lam"], 0.0], atol=1e-12)
    assert np.abs(tr.q[:, -1] - e.q).max() < 2e-6 and np.abs(tr.v[:, -1]).max() < 1e-9


def _backlash_pivot_impacts(p, Kp, Kv, theta_md, count, h=1e-5):
    """The first ``count`` impacts on flank f1 from rest at 0, computed without invctl: between impacts
    the shaft under PD (36) is a damped linear oscillator in closed form and the link a pendulum
    integrated by classical RK4 (step ``h``); the gap's sign change is bracketed on the RK4 grid and
    located by brentq on a partial RK4 step; Newton's law with the generalized impulse along
    W = grad f1 = (-1/N, 1). Returns (t, U-, U+) per impact."""
    from scipy.optimize import brentq

    Jm, N, ml, ll, a, e, g = (p[k] for k in ("Jm", "N", "ml", "ll", "alpha", "e", "g"))
    inertia = ml * ll**2 / 3
    sig = Kv / (2 * Jm)
    wd = math.sqrt(Kp / Jm - sig**2)

    def shaft(x0, w0):
        A, B = x0 - theta_md, (w0 + sig * (x0 - theta_md)) / wd

        def at(s):
            E, c, sn = math.exp(-sig * s), math.cos(wd * s), math.sin(wd * s)
            return theta_md + E * (A * c + B * sn), E * (-sig * (A * c + B * sn) + wd * (-A * sn + B * c))
        return at

    def link(th, om, s):
        def f(th, om):
            return om, -ml * g * 0.5 * ll * math.sin(th) / inertia
        k1 = f(th, om)
        k2 = f(th + s / 2 * k1[0], om + s / 2 * k1[1])
        k3 = f(th + s / 2 * k2[0], om + s / 2 * k2[1])
        k4 = f(th + s * k3[0], om + s * k3[1])
        return (th + s / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0]),
                om + s / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1]))

    t, xm, wm, th, om, out = 0.0, 0.0, 0.0, 0.0, 0.0, []
    W, Minv = np.array([-1 / N, 1.0]), np.array([1 / Jm, 1 / inertia])
    for _ in range(count):
        sh = shaft(xm, wm)

        def gap(s, thl):
            return a + thl - sh(s)[0] / N
        s, thk, omk = 0.0, th, om
        while gap(s + h, link(thk, omk, h)[0]) >= 0:
            thk, omk = link(thk, omk, h)
            s += h
        r = brentq(lambda d: gap(s + d, link(thk, omk, d)[0]), 0.0, h, xtol=1e-18, rtol=1e-15)
        th, om = link(thk, omk, r)
        xm, wm = sh(s + r)
        t += s + r
        U = W @ [wm, om]
        P = -(1 + e) * U / (W @ (Minv * W))
        wm, om = wm + Minv[0] * W[0] * P, om + Minv[1] * W[1] * P
        out.append((t, U, W @ [wm, om]))
    return np.array(out)


def test_backlash_pivot_impacts_against_an_independent_computation():
    """Three computations of the first impacts of the backlash pivot: the event-driven reference agrees
    with the closed-form shaft + RK4 link + Newton's law (impact times to 1e-12 s, approach velocities to
    1e-9 relative; RK4 steps 1e-5 and 2e-6 agree to 1e-14 s), and the compiled Moreau-Jean run with
    them to first order (error below 3 h at h = 1e-4)."""
    scene = load_scene("backlash_pivot")
    params, settings = scene.split({"t_end": 0.03})
    run = run_contact(contact_setup(scene, params, settings), progress=False)
    s = bp.SETTINGS
    ind = _backlash_pivot_impacts(bp.PARAMS, s["Kp"], s["Kv"], bp.PARAMS["N"] * s["link_d"], 3)
    fine = _backlash_pivot_impacts(bp.PARAMS, s["Kp"], s["Kv"], bp.PARAMS["N"] * s["link_d"], 3, h=2e-6)
    assert np.abs(ind[:, 0] - fine[:, 0]).max() < 1e-14
    ref = simulate_event_driven(run.model, run.q0, run.v0, 0.03, law=run.law, max_impacts=3)
    t_ref = np.asarray(ref.stats["impact_t"])
    assert t_ref.size == 3
    assert np.abs(t_ref - ind[:, 0]).max() < 1e-12
    assert np.abs(ref.stats["impact_pre"] / ind[:, 1] - 1).max() < 1e-9
    assert np.abs(ref.stats["impact_post"] / ind[:, 2] - 1).max() < 1e-9
    t_ts = run.trajectory.impact_times[:3]
    assert np.abs(t_ts - ind[:, 0]).max() < 3e-4


def test_event_driven_impacts_do_not_depend_on_round_off():
    """Right after an impact the gap is zero up to round-off; its sign must not decide whether the next
    impact is seen when the whole flight fits in one integrator step (it did: perturbations of the initial
    state of 1e-13, a machine's floating point, lost the third impact at rtol 1e-12 and 1e-10). Each
    perturbed run finds the same three impacts."""
    scene = load_scene("backlash_pivot")
    params, settings = scene.split({"t_end": 0.03})
    run = run_contact(contact_setup(scene, params, settings), progress=False)
    s = bp.SETTINGS
    ind = _backlash_pivot_impacts(bp.PARAMS, s["Kp"], s["Kv"], bp.PARAMS["N"] * s["link_d"], 3)
    rng = np.random.default_rng(0)
    for k in range(12):
        dq, dv = rng.normal(size=2) * 1e-13, rng.normal(size=2) * 1e-13
        tol = (1e-12, 1e-10)[k % 2]
        ref = simulate_event_driven(run.model, run.q0 + dq, run.v0 + dv, 0.03, law=run.law, max_impacts=3,
                                    rtol=tol, atol=tol)
        t_ref = np.asarray(ref.stats["impact_t"])
        assert t_ref.size == 3, (k, t_ref)
        assert np.abs(t_ref - ind[:, 0]).max() < (1e-12 if tol == 1e-12 else 1e-9)


# ----------------------------------------------------------------- four-bar with motor shaft (Fig. 6(b))
def test_fourbar_closed_form_loop():
    """The closed-form position analysis closes the loop: |C - B| = c, |C - D| = d for every crank angle."""
    v = fb.PARAMS
    for th in np.linspace(0, 2 * math.pi, 37):
        (Bx, By), (Cx, Cy) = fb.fourbar_points(th, v["a"], v["b"], v["c"], v["d"])
        assert abs(math.hypot(Cx - Bx, Cy - By) - v["c"]) < 1e-14
        assert abs(math.hypot(Cx - v["a"], Cy) - v["d"]) < 1e-14


def test_fourbar_rests_on_a_flank_with_the_gravity_torque():
    """PD (36) at J11 (shaft measurement only): V never increases, the crank changes flank on its way,
    and at rest the flank's multiplier equals the four-bar's gravity torque about J1 by virtual work
    (central differences of numpy positions, error O(1e-10)); the shaft balances lam / N."""
    run = _run("fourbar_backlash", {})
    tr, s = run.trajectory, run.settings
    assert tr.max_V_increase <= 1e-12 * abs(tr.V[0])
    from invctl_scenes.fourbar_backlash import rest_report

    class Ctx:
        result, model, settings = tr, run.model, s

    rep = rest_report(Ctx)
    assert rep["changes of the flank in contact"] >= 1 and not rep["both flanks closed at some step"]
    assert rep["|lam - sign dU/dtheta_1|"] < 1e-8
    assert abs(rep["shaft: K_p (theta_ms - theta_msd) + lam_1/N - lam_2/N"]) < 1e-10
    assert np.abs(tr.v[:, -1]).max() < 1e-8


def test_fourbar_rejects_a_non_grashof_linkage():
    scene = load_scene("fourbar_backlash")
    with pytest.raises(ParameterError, match="Grashof"):
        scene.split({"b": 0.35})


# ----------------------------------------------------------------- juggling design (29)-(33)
J = Juggler(1.0, 0.5, 0.05, 0.11, 0.5)


def test_step2_closed_form_and_impact_maps():
    """One cycle: the designed end state is the target, the approach speeds are negative, and the
    maps (28) conserve momentum and restore e times the approach speed at each impact."""
    st = JugglerState(0.0, 0.0, 0.0, 0.05, 0.3)
    c = design_cycle(J, st, 0.1, 0.2)
    assert c.A < 0 and c.B < 0 and abs(c.end.q2 - 0.1) < 1e-15 and abs(c.end.v2 - 0.2) < 1e-15
    t1, q2, v2p, q1, v1p = c.impact1
    v2m, v1m = st.v2, st.v2 + c.A                      # body 2 flies freely; y2' = v1 - v2 = A before
    assert abs(J.m1 * v1p + J.m2 * v2p - (J.m1 * v1m + J.m2 * v2m)) < 1e-15
    assert abs((v1p - v2p) + J.e * c.A) < 1e-15        # Newton: y2'(t1+) = -e y2'(t1-)
    assert abs(q1 - q2 + J.L - J.l) < 1e-15            # y2(t1) = 0
    assert abs(c.end.q2 - c.end.q1 - J.l) < 1e-15      # y1(t2) = 0
    assert abs((c.end.v2 - c.end.v1) + J.e * c.B) < 1e-15


def test_step2_failure_is_reported():
    """Body 2 leaving the first wall backwards cannot be brought ahead of its start within one cycle:
    step 2 fails and says so; in a sequence the failing cycle is named and the plan before it kept."""
    with pytest.raises(JugglingInfeasible, match="step 2 fails") as exc:
        design_cycle(J, JugglerState(0.0, 0.0, -0.5, 0.05, -0.2), 0.15, 0.2)
    assert exc.value.diagnostics["step2"] == exc.value.diagnostics["pairs"]
    with pytest.raises(JugglingInfeasible, match="cycle 2 of 2") as exc:
        design(J, JugglerState(0.0, 0.0, 0.0, 0.05, 0.3), [(0.1, -0.2), (0.3, 0.2)])
    assert len(exc.value.partial.cycles) == 1
    with pytest.raises(ParameterError, match="follow an impact on y1"):
        design_cycle(J, JugglerState(0.0, 0.0, 0.5, 0.05, 0.3), 0.1, 0.2)


def test_plan_reproduced_by_the_event_driven_simulation():
    """The plan's law (step 3) driving the model in the event-driven simulator (impacts located exactly)
    hits body 2 at the planned times with the planned states, to 1e-9: an independent check of the
    impact maps (28), the flights and the fictitious inputs of step 2."""
    scene = load_scene("prismatic_clearance")
    params, settings = scene.split({})
    model = scene.model(params)
    plan = design(J, JugglerState(0.0, 0.0, 0.0, 0.05, 0.3), [(0.1, 0.2)])
    law = juggling_plan_law(model, plan, Kp=settings["Kp"], Kv=settings["Kv"])
    tr = simulate_event_driven(model, [0.0, 0.05], [0.0, 0.3], plan.t_end + 0.02, law=law)
    rep = plan_vs_run(plan, tr)
    assert rep["realized impacts"] == 2
    assert rep["max |t_run - t_plan|"] < 1e-9 and rep["max |q2_run - q2_plan| at the impacts"] < 1e-9
    assert rep["max |q2'_run - q2'_plan| after the impacts"] < 1e-9


def test_juggling_design_controller_converges_with_h():
    """The scene's controller under the compiled Moreau-Jean scheme: three cycles, six impacts, and the
    state errors at the planned impacts shrink about linearly with h (event capturing is first order)."""
    errs = []
    for h in (4e-4, 1e-4):
        run = _run("prismatic_clearance", {"h": h}, controller="juggling_design")
        plan = pc.juggling_plan(run.model, run.settings)
        rep = plan_vs_run(plan, run.trajectory)
        assert rep["realized impacts"] == rep["planned impacts"] == 6
        errs.append(rep["max |q2'_run - q2'_plan| after the impacts"])
    assert errs[1] < 0.5 * errs[0] and errs[1] < 2e-3


def test_juggling_design_needs_one_actuator():
    from invctl.errors import SceneError

    scene = load_scene("prismatic_clearance")
    params, settings = scene.split({"actuators": 2})
    with pytest.raises(SceneError, match="actuators=1"):
        contact_setup(scene, params, settings, controller="juggling_design")


# ----------------------------------------------------------------- builder and structure on their own
def test_linkage_rejects_loops_and_bad_points():
    P = ParamSet(["l"])
    bars = [bar("A", P["l"], 1.0), bar("B", P["l"], 1.0)]
    loop = [Joint("J1", "revolute", GROUND, (0.0, 0.0), "A", "start"),
            Joint("J2", "revolute", "A", "end", "B", "start"),
            Joint("J3", "revolute", GROUND, (1.0, 0.0), "B", "end")]
    with pytest.raises(ModelError, match="closes a loop"):
        Linkage(bars, loop)
    with pytest.raises(ModelError, match="has no point 'tip'"):
        Linkage(bars, [Joint("J1", "revolute", GROUND, (0.0, 0.0), "A", "tip")])


def test_linkage_coordinates_round_trip():
    """Poses -> open coordinates -> poses (prismatic joint, floating body, relative angles)."""
    import casadi as ca

    import invctl_scenes.chain14 as ch

    m = ch.build()
    link = m.linkage
    poses = ch.nominal_poses()
    ev = ca.Function("p", [m.q], [ca.vertcat(*[ca.vertcat(link.poses[b][0], link.poses[b][1]) for b in poses])])
    got = np.array(ev(link.nominal)).reshape(-1, 3)
    np.testing.assert_allclose(got, np.array([poses[b] for b in poses]), atol=1e-14)


def test_structure_of_existing_scenes():
    """The generic analysis on scenes written by hand: the slider-crank with a journal clearance between
    crank and rod (000 Fig. 4(a); not Example 5, whose slider-crank has play in the prismatic joint J4:
    ``slider_crank_prismatic_play``) has the crank and the rod-slider as subsystems, the prismatic joint
    two bodies."""
    import invctl_scenes.slider_crank_clearance as sc

    st = open_structure(sc.build())
    assert st.n_ind == 2 and [s.q_names for s in st.subsystems] == [("theta",), ("s", "phi")]
    assert st.subsystems[1].status == "unactuated" and st.contacts[0][1] == "S1-S2"
    st = open_structure(pc.build(actuators=1))
    assert [s.status for s in st.subsystems] == ["fully actuated", "unactuated"]


# ----------------------------------------------------------------- every new scene through the commands
@pytest.mark.parametrize("name, values, controller", [
    ("sixbar_pd", {"t_end": 0.05}, None), ("sixbar_tracking", {"t_end": 0.05}, "pdplus_violating"),
    ("sixbar", {"t_end": 0.05, "structure": 3}, None), ("chain14", {"t_end": 0.05}, None),
    ("backlash_pivot", {"t_end": 0.2}, None), ("fourbar_backlash", {"t_end": 0.2}, None),
    ("prismatic_clearance", {"t_end": 0.3}, "juggling_design")])
def test_scene_commands_json_and_figure(name, values, controller, tmp_path, capsys):
    from invctl.cli import main

    args = ["simulate", name, "--json", "--plot", str(tmp_path / "run.png")]
    for k, v in values.items():
        args += ["--set", f"{k}={v}"]
    if controller:
        args += ["--controller", controller]
    assert main(args) == 0
    d = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert d["steps"] > 0 and (tmp_path / "run.png").stat().st_size > 0
    assert main(["analyze", name, "--json"]) == 0
    d = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert d["reports"]


class _LoopModel:
    """Two coordinates tied by the closure q1 = q2 (one clearance-free DoF along (1, 1)), input matrix B."""

    def __init__(self, B):
        from types import SimpleNamespace

        import casadi as ca

        self.q, self.theta, self.theta_values = ca.SX.sym("q", 2), ca.SX.sym("th", 0), np.zeros(0)
        self.linkage = SimpleNamespace(closure=self.q[0] - self.q[1])
        self.n, self.m, self._B = 2, B.shape[1], B

    def function(self, name):
        import casadi as ca

        return ca.Function(name, [self.q, self.theta], [ca.DM(self._B)])


@pytest.mark.parametrize("B, kind, rank", [(np.eye(2), "overactuated", 1),           # 2 inputs, 1 DoF
                                           (np.array([[1.0], [-1.0]]), "underactuated", 0),  # acts across it
                                           (np.array([[1.0], [0.0]]), "fully actuated", 1)])
def test_clearance_free_degree_of_actuation(B, kind, rank):
    """000 Assumption 1 on the clearance-free system: E = N^T B with N = (1, 1)/sqrt 2 spanning its tangent
    space; p = m inputs against dim q_wc = 1 and rank E."""
    from invctl.contact.structure import _clearance_free

    out = _clearance_free(_LoopModel(B), np.zeros(2))
    assert out["clearance-free DoFs (dim q_wc)"] == 1 and out["rank E_wc"] == rank
    assert out["clearance-free system (000 Assumption 1)"].startswith(kind + " (")


def test_joints_are_immutable():
    from dataclasses import FrozenInstanceError

    from invctl.contact.linkage import GROUND, Joint

    joint = Joint("J1", "revolute", GROUND, (0.0, 0.0), "A", "start")
    with pytest.raises(FrozenInstanceError):
        joint.clearance = 1e-3


def test_plan_vs_run_reports_absolute_differences():
    """Two planned impacts (t, wall, q2, q2'): (1, 1, 0.5, -0.2) and (2, 2, 0.7, 0.3); the run hits wall 1
    early at 0.9 and wall 2 late at 2.05, with q2 = t / 2 and post-impact q2' = -0.25 and 0.35: the largest
    differences are |0.9 - 1| = 0.1 in time (the early one), |1.025 - 0.7| in q2 and 0.05 in q2'."""
    from types import SimpleNamespace

    from invctl_scenes._juggling_design import plan_vs_run

    plan = SimpleNamespace(impact_table=lambda: [(1.0, 1, 0.5, -0.2), (2.0, 2, 0.7, 0.3)])
    t = np.linspace(0.0, 3.0, 301)
    tr = SimpleNamespace(t=t, q=np.vstack([0 * t, t / 2]),
                         stats={"impact_t": [0.9, 2.05], "impact_contact": [0, 1],
                                "impact_v_plus": [[0.0, -0.25], [0.0, 0.35]]})
    out = plan_vs_run(plan, tr)
    assert out["planned impacts"] == 2 and out["realized impacts"] == 2
    assert out["max |t_run - t_plan|"] == pytest.approx(0.1, abs=1e-12)
    assert out["max |q2_run - q2_plan| at the impacts"] == pytest.approx(max(abs(0.45 - 0.5), abs(1.025 - 0.7)))
    assert out["max |q2'_run - q2'_plan| after the impacts"] == pytest.approx(0.05, abs=1e-12)
