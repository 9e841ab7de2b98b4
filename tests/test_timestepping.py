"""Moreau-Jean time-stepping: compiled loop vs numpy, closed forms, event-driven reference,
energy, penetration/projection, activation tolerance, extremes."""
import importlib.util
import json
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

import invctl_scenes.bouncing_ball as bb
import invctl_scenes.prismatic_clearance as prism
from invctl.control.pdplus import pd_gravity
from invctl.errors import ParameterError, RecordingError
from invctl.model import Gap, Model, ParamSet
from invctl.simulate.event_driven import simulate_event_driven
from invctl.simulate.timestepping import MONITORS, MoreauJean, c_compiler

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def ball():
    m = bb.build()
    return MoreauJean(m, potential=bb.potential(m), backend="vm")


@pytest.fixture(scope="module")
def ball_proj():
    m = bb.build()
    return MoreauJean(m, potential=bb.potential(m), backend="vm", projection=True)


@pytest.fixture(scope="module")
def prism_pd():
    model = prism.build(actuators=1)
    p = prism.PARAMS
    law = pd_gravity(model, Kp=p["Kp"], Kv=p["Kv"], q_d=p["qd"], idx=[0])
    return model, law, MoreauJean(model, law, backend="vm")


def _slope(h, err):
    return float(np.polyfit(np.log(h), np.log(err), 1)[0])


def test_compiled_loop_matches_numpy_loop(prism_pd):
    spec = importlib.util.spec_from_file_location("bench", ROOT / "benchmarks" / "bench_timestepping.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    model, law, mj = prism_pd
    p = prism.PARAMS
    q0, v0 = [0.0, 0.055], [0.0, 0.3]
    tr = mj.run(q0, v0, 0.5, 1e-4)
    ref = bench.numpy_loop(np.array(q0), np.array(v0), 5000, 1e-4, p["m1"], p["m2"], p["l"], p["L"], p["e"],
                           p["Kp"], p["Kv"], p["qd"])
    assert tr.impact_times.size >= 3
    np.testing.assert_allclose(tr.q[:, 1:], ref[:, :2].T, atol=1e-13)
    np.testing.assert_allclose(tr.v[:, 1:], ref[:, 2:].T, atol=1e-11)


@pytest.mark.skipif(c_compiler() is None, reason="no C compiler on this machine")
def test_c_backend_equals_vm(prism_pd):
    model, law, mj = prism_pd
    mc = MoreauJean(model, law, backend="c")
    a = mj.run([0.0, 0.055], [0.0, 0.3], 0.3, 1e-4)
    b = mc.run([0.0, 0.055], [0.0, 0.3], 0.3, 1e-4)
    assert b.stats["backend"] == "c"
    np.testing.assert_allclose(a.q, b.q, atol=1e-14)


def test_parameters_enter_without_retracing(prism_pd):
    """New gains/parameters reuse the compiled loop and equal a fresh build with those values."""
    model, law, mj = prism_pd
    mj.run([0.0, 0.055], [0.0, 0.3], 0.1, 1e-4)
    loops = dict(mj._loops)
    g = law.values(Kp1=250.0, Kv1=35.0, qd1=0.1)
    th = [1.0, 0.3, 0.05, 0.11, 0.7]
    a = mj.run([0.0, 0.055], [0.0, 0.3], 0.1, 1e-4, gains=g, params=th)
    assert mj._loops.keys() == loops.keys() and all(mj._loops[k] is loops[k] for k in loops)
    model2 = prism.build(actuators=1, m2=0.3, e=0.7)
    law2 = pd_gravity(model2, Kp=250.0, Kv=35.0, q_d=0.1, idx=[0])
    b = MoreauJean(model2, law2, backend="vm").run([0.0, 0.055], [0.0, 0.3], 0.1, 1e-4)
    np.testing.assert_allclose(a.q, b.q, atol=1e-14)


def test_bouncing_ball_first_order_vs_closed_form(ball):
    """Impact times and post-impact velocities converge at first order (fitted slope)."""
    ex_t, _, ex_post, _ = bb.exact_impacts(1.0, 9.81, 0.8, 2.0)
    hs = np.array([4e-3, 2e-3, 1e-3, 5e-4, 2.5e-4, 1.25e-4, 6.25e-5])
    et, ev = [], []
    for h in hs:
        tr = ball.run([1.0], [0.0], 2.0, h)
        ti, _, _, post, _ = tr.impacts()
        et.append(np.max(np.abs(ti[:3] - ex_t[:3])))
        ev.append(np.max(np.abs(post[:3] - ex_post[:3])))
        assert et[-1] <= 3 * h  # O(h) with a modest constant
    st_, sv = _slope(hs, et), _slope(hs, ev)
    assert 0.8 <= st_ <= 1.6, st_
    assert 0.8 <= sv <= 1.6, sv


def test_bouncing_ball_rest_time(ball):
    """Zeno accumulation: the time-stepping settles; rest time -> t1 (1+e)/(1-e)."""
    rest = bb.exact_impacts(1.0, 9.81, 0.8, 10.0)[3]
    errs = []
    for h in (1e-3, 1e-4):
        tr = ball.run([1.0], [0.0], 5.0, h)
        errs.append(abs(tr.rest_time() - rest))
    assert errs[1] < errs[0] and errs[1] < 0.01


def test_first_order_vs_event_driven_reference(prism_pd):
    """2-DoF clearance under PD: impact times and post-impact velocities against the
    exact event-driven reference, fitted slope about 1."""
    model, law, mj = prism_pd
    q0, v0 = [0.0, 0.055], [0.0, 0.3]
    ref = simulate_event_driven(model, q0, v0, 0.3, law=law)
    rt, rpost = ref.stats["impact_t"][:3], ref.stats["impact_post"][:3]
    hs = np.array([1e-3, 5e-4, 2.5e-4, 1.25e-4, 6.25e-5, 3.125e-5, 1.5625e-5])
    et, ev = [], []
    for h in hs:
        ti, ii, _, post, _ = mj.run(q0, v0, 0.3, h).impacts()
        np.testing.assert_array_equal(ii[:3], ref.stats["impact_contact"][:3])
        et.append(np.max(np.abs(ti[:3] - rt)))
        ev.append(np.max(np.abs(post[:3] - rpost)))
    assert 0.8 <= _slope(hs, et) <= 1.6
    assert 0.8 <= _slope(hs, ev) <= 1.6


def test_event_driven_ball_matches_closed_form():
    ref = simulate_event_driven(bb.build(), [1.0], [0.0], 3.0)
    ex_t, _, ex_post, _ = bb.exact_impacts(1.0, 9.81, 0.8, 3.0)
    np.testing.assert_allclose(ref.stats["impact_t"][:6], ex_t[:6], rtol=1e-10)
    np.testing.assert_allclose(ref.stats["impact_post"][:6], ex_post[:6], rtol=1e-10)


def _oscillator(e=1.0):
    """Linear spring-mass hitting a wall at q = -d: M = m, f = -k q, gap q + d >= 0."""
    P = ParamSet(["m", "k", "d", "e"])
    q, v = ca.SX.sym("q", 1), ca.SX.sym("v", 1)
    model = Model("osc", q, v, P, {"m": 1.0, "k": 40.0, "d": 0.05, "e": e}, M=ca.reshape(P["m"], 1, 1),
                  f=-P["k"] * q, B=ca.SX.zeros(1, 0), gaps=[Gap("wall", q[0] + P["d"], "e")])
    return model, 0.5 * P["k"] * q[0] ** 2


@pytest.mark.parametrize("which", ["ball", "oscillator"])
def test_energy_conserved_theta_half_elastic(which):
    """e = 1, linear conservative forces, theta = 1/2: energy conserved to 1e-12 through impacts."""
    if which == "ball":
        model = bb.build(e=1.0)
        U = bb.potential(model)
        q0, t_end = [1.0], 3.0
    else:
        model, U = _oscillator()
        q0, t_end = [0.2], 3.0
    tr = MoreauJean(model, potential=U, backend="vm").run(q0, [0.0], t_end, 1e-3)
    assert tr.impact_times.size >= 3
    E = tr.energy
    assert np.max(np.abs(E - E[0])) <= 1e-12 * abs(E[0])


def test_impulse_energy_balance_at_impact_steps(ball):
    """theta = 1/2: the energy change of an impact step is (1-e)/2 P U_k <= 0, the
    discrete counterpart of (39); checked to 1e-12."""
    tr = ball.run([1.0], [0.0], 2.0, 1e-3)
    Un = tr.stats["Un"][0]
    k = np.flatnonzero((tr.P[0] > 0) & (Un[:-1] < -1e-8))
    dE = tr.energy[k + 1] - tr.energy[k]
    pred = 0.5 * (1 - 0.8) * tr.P[0, k] * Un[k]
    np.testing.assert_allclose(dE, pred, rtol=1e-10, atol=1e-12 * tr.energy[0])
    assert np.all(dE < 0)


def test_penetration_order_h_and_projection(ball, ball_proj):
    """Plain Moreau-Jean: penetration O(h) (max over drop heights), never corrected
    while resting; with the position projection every gap stays >= -1e-10 whatever h."""
    hs = np.array([1e-2, 1e-3, 1e-4])
    pens = []
    for h in hs:
        worst = 0.0
        for H in np.linspace(0.5, 1.5, 7):
            worst = max(worst, ball.run([H], [0.0], 1.2, h).max_gap_violation)
            assert ball_proj.run([H], [0.0], 1.2, h).max_gap_violation <= 1e-10
        pens.append(worst)
    pens = np.array(pens)
    assert np.all(pens > 0)
    assert np.all(pens <= 2 * np.sqrt(2 * 9.81 * 1.5) * hs)
    assert 0.7 <= _slope(hs, pens) <= 1.3
    rest = ball.run([1.0], [0.0], 6.0, 1e-3)
    tail = rest.gaps[0, rest.t > 5.0]
    assert tail.min() < 0 and np.ptp(tail) == 0.0  # resting inside the ground, never corrected
    restp = ball_proj.run([1.0], [0.0], 6.0, 1e-3)
    assert restp.gaps[0, restp.t > 5.0].min() >= -1e-10


def test_activation_tolerance_keeps_preloaded_contact():
    """A strict active-set test drops the pre-loaded contact by round-off and the gap
    drifts; the default tolerance 1e-12 keeps it below 1e-14 with exact multipliers."""
    from invctl.control.preload import preload_law

    model = prism.build(actuators=2)
    law = preload_law(model, [0], beta=1.0, Kp=100.0, Kv=20.0, y_d=[0.2, 0.25])
    mj = MoreauJean(model, law, backend="vm")
    strict = mj.run([0.0, 0.05], [0.0, 0.0], 0.5, 1e-4, activation_tol=0.0)
    tol = mj.run([0.0, 0.05], [0.0, 0.0], 0.5, 1e-4)
    assert np.max(np.abs(strict.gaps[0])) > 1e-9 and not np.all(strict.active[0])
    assert np.max(np.abs(tol.gaps[0])) < 1e-14
    assert np.all(tol.active[0])
    assert np.max(np.abs(tol.P[0] / 1e-4 - 1.0)) < 1e-9


def test_bilateral_constraint_in_stepper():
    """Point mass on the line x = y (bilateral) dropped onto y >= 0: effective gravity g/2,
    first impact at sqrt(4 H / g) (closed form), post-impact speed e times pre-impact."""
    P = ParamSet(["m", "e"])
    q, v = ca.SX.sym("q", 2), ca.SX.sym("v", 2)
    model = Model("line", q, v, P, {"m": 1.0, "e": 0.5}, M=P["m"] * ca.SX.eye(2), f=ca.vertcat(0, -9.81 * P["m"]),
                  B=ca.SX.zeros(2, 0), g=q[0] - q[1], gaps=[Gap("ground", q[1], "e")])
    tr = MoreauJean(model, backend="vm").run([1.0, 1.0], [0.0, 0.0], 1.0, 1e-5)
    t1 = np.sqrt(4 * 1.0 / 9.81)
    ti, _, pre, post, vp = tr.impacts()
    assert abs(ti[0] - t1) < 2e-5
    assert abs(post[0] + 0.5 * pre[0]) < 1e-3
    np.testing.assert_allclose(tr.v[0], tr.v[1], atol=1e-12)
    from invctl.contact.mechanics import ContactSystem

    cs = ContactSystem(model)
    np.testing.assert_allclose(cs.delassus([0.0, 0.0]), [[0.5]], rtol=1e-14)  # (8): W^T (M^-1 - ...) W
    cf = cs.contact_forces([0.0, 0.0], [0.0, 0.0])
    np.testing.assert_allclose(cf.lam, [9.81], rtol=1e-13)
    np.testing.assert_allclose(cf.acceleration, 0.0, atol=1e-13)


# ------------------------------------------------------------------ extremes
@pytest.mark.parametrize("e", [0.0, 1.0, 0.01, 0.99])
def test_restitution_extremes_and_zeno(e):
    model = bb.build(e=e)
    mj = MoreauJean(model, potential=bb.potential(model), backend="vm")
    h = 1e-3
    tr = mj.run([1.0], [0.0], 6.0, h)
    assert np.all(np.isfinite(tr.q)) and np.all(np.isfinite(tr.v))
    assert tr.max_gap_violation <= 2 * np.sqrt(2 * 9.81) * h
    Un = tr.stats["Un"][0]
    k = np.flatnonzero((tr.P[0] > 0) & (Un[:-1] < -1e-8))
    assert np.all(tr.energy[k + 1] - tr.energy[k] <= 1e-12 * tr.energy[0])
    t1 = np.sqrt(2 / 9.81)
    if e == 0.0:
        assert abs(tr.impacts()[3][0]) < 1e-12
        assert abs(tr.rest_time() - t1) < 2 * h
    if e == 1.0:
        assert np.isnan(tr.rest_time()) and tr.impact_times.size == 7  # period 2 t1


@settings(max_examples=25, deadline=None)
@given(st.floats(0.0, 1.0), st.floats(0.1, 3.0), st.sampled_from([3e-3, 1e-3, 3e-4]))
def test_energy_never_created_by_an_impact(e, H, h):
    model = bb.build()
    mj = _ball_stepper()
    tr = mj.run([H], [0.0], 2.0, h, params=[1.0, 9.81, e])
    Un = tr.stats["Un"][0]
    k = np.flatnonzero((tr.P[0] > 0) & (Un[:-1] < -1e-8))
    assert np.all(tr.energy[k + 1] - tr.energy[k] <= 1e-12 * tr.energy[0])
    assert tr.max_gap_violation <= 2 * np.sqrt(2 * 9.81 * H) * h + 1e-15
    assert model.n == 1


_BALL = {}


def _ball_stepper():
    if "mj" not in _BALL:
        m = bb.build()
        _BALL["mj"] = MoreauJean(m, potential=bb.potential(m), backend="vm")
    return _BALL["mj"]


@pytest.mark.parametrize("ratio", [1e-4, 1e4])
def test_mass_ratio_extremes(ratio):
    model = prism.build(actuators=1, m2=ratio)
    law = pd_gravity(model, Kp=100.0, Kv=20.0, q_d=0.2, idx=[0])
    tr = MoreauJean(model, law, backend="vm").run([0.0, 0.055], [0.0, 0.3], 1.0, 1e-4)
    assert np.all(np.isfinite(tr.q))
    assert tr.max_gap_violation <= 0.3 * 1e-4 * 3
    assert tr.max_V_increase <= 1e-9 * max(tr.V[0], 1e-12) + 1e-15


@pytest.mark.parametrize("projection", [False, True])
def test_tiny_clearance(projection):
    """Clearance L - 2 l = 1e-9 m: no blow-up; with projection gaps >= -1e-10."""
    l = 0.05
    model = prism.build(actuators=1, l=l, L=2 * l + 1e-9)
    law = pd_gravity(model, Kp=100.0, Kv=20.0, q_d=0.2, idx=[0])
    mj = MoreauJean(model, law, backend="vm", projection=projection)
    tr = mj.run([0.0, l + 0.5e-9], [0.0, 0.0], 1.0, 1e-4)
    assert np.all(np.isfinite(tr.q))
    assert abs(tr.q[0, -1] - 0.2) < 1e-3
    if projection:
        assert tr.max_gap_violation <= 1e-10
    else:
        assert tr.max_gap_violation <= 1e-4 * 1.0


def test_simultaneous_impacts_in_time_stepping():
    """A point mass thrown into a corner hits both walls in the same step: Moreau's law
    reflects both normal components by -e."""
    P = ParamSet(["m", "e"])
    q, v = ca.SX.sym("q", 2), ca.SX.sym("v", 2)
    model = Model("corner", q, v, P, {"m": 1.0, "e": 0.5}, M=P["m"] * ca.SX.eye(2), f=ca.SX.zeros(2),
                  B=ca.SX.zeros(2, 0), gaps=[Gap("x", q[0], "e"), Gap("y", q[1], "e")])
    tr = MoreauJean(model, backend="vm").run([0.1, 0.2], [-1.0, -2.0], 0.2, 1e-3)
    ti, ii, pre, post, vp = tr.impacts()
    assert set(ii.tolist()) == {0, 1} and np.ptp(ti) == 0
    np.testing.assert_allclose(tr.v[:, -1], [0.5, 1.0], atol=1e-14)


def test_save_load_and_plot(tmp_path, ball):
    tr = ball.run([1.0], [0.0], 1.0, 1e-3)
    path = tr.to_npz(tmp_path / "ball.npz")
    tr2 = type(tr).load(path)
    np.testing.assert_array_equal(tr.q, tr2.q)
    np.testing.assert_array_equal(tr.impact_times, tr2.impact_times)
    fig = tr2.plot(tmp_path / "ball.png")
    assert (tmp_path / "ball.png").exists() and fig is not None


def test_cli_simulate_json(capsys, tmp_path):
    from invctl.cli import main

    assert main(["simulate", "bouncing_ball", "--set", "e=0.5", "--set", "h=1e-3", "--json",
                 "--out", str(tmp_path / "b.npz")]) == 0
    d = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for key in ("impact_times", "max_gap_violation", "max_energy_increase", "steps_per_s"):
        assert key in d
    closed = d["reports"]["closed form (Newton's law, free fall)"]["values"]
    assert abs(closed["rest time"] - closed["rest time, closed form"]) < 0.01
    # event capturing locates each impact within a step h = 1e-3; the errors add up over the 5 impacts compared
    assert max(abs(x) for x in closed["impact time errors"]) <= 5e-3
    assert main(["simulate", "bouncing_ball", "--controller", "pd", "--json"]) == 2
    capsys.readouterr()
    assert main(["simulate", "prismatic_clearance", "--set", "actuators=2", "--controller", "preload",
                 "--t-end", "0.5", "--json"]) == 0
    d = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert d["multiplier_error"] < 1e-9 and d["contacts_kept"]
    assert main(["simulate", "prismatic_clearance", "--controller", "preload", "--set", "actuators=1",
                 "--plant-set", "zz=1", "--json"]) == 2


def test_persistent_contact_phase_vs_event_driven():
    """Pre-loaded persistent contact: the event-driven reference keeps the gap at 0 with no event;
    Moreau-Jean converges to it (first order, error halves with h)."""
    from invctl.control.preload import preload_law

    model = prism.build(actuators=2)
    law = preload_law(model, [0], beta=1.0, Kp=100.0, Kv=20.0, y_d=[0.2, 0.25])
    ref = simulate_event_driven(model, [0.0, 0.05], [0.0, 0.0], 1.0, law=law)
    assert not ref.stats["events"] and np.max(np.abs(ref.gaps[0])) < 1e-12
    mj = MoreauJean(model, law, backend="vm")
    errs = [np.max(np.abs(mj.run([0.0, 0.05], [0.0, 0.0], 1.0, h).q[:, -1] - ref.q[:, -1])) for h in (2e-4, 1e-4, 5e-5)]
    assert errs[2] < errs[1] < errs[0] < 1e-3
    assert 0.8 <= _slope(np.array([2e-4, 1e-4, 5e-5]), np.array(errs)) <= 2.2


def test_pd_plus_tracking_input_and_lyapunov_function_closed_form():
    """One mass m on a line, no potential, q_d = sin t: 000 (48) gives u = m qdd_d - Kv (v - qd_d) - Kp (q - q_d)
    and (50) V = m (v - qd_d)^2 / 2 + Kp (q - q_d)^2 / 2."""
    import casadi as ca

    from invctl.control.pdplus import pd_plus_tracking
    from invctl.model import Model, ParamSet

    P = ParamSet(["m"])
    q, v = ca.SX.sym("q", 1), ca.SX.sym("v", 1)
    model = Model("mass", q, v, P, {"m": 2.0}, M=P["m"] * ca.SX.eye(1), f=ca.SX.zeros(1), B=ca.DM.eye(1), h=q)
    Kp, Kv, m = 3.0, 0.5, 2.0
    law = pd_plus_tracking(model, Kp=Kp, Kv=Kv, q_d=ca.sin)
    for qq, vv, t in ((0.3, -0.2, 0.7), (-1.0, 0.4, 2.0)):
        u, V = law.function(model)([qq], [vv], t, model.theta_values, law.values())
        e, ev = qq - np.sin(t), vv - np.cos(t)
        assert float(u) == pytest.approx(-m * np.sin(t) - Kv * ev - Kp * e, rel=1e-13)
        assert float(V) == pytest.approx(0.5 * m * ev**2 + 0.5 * Kp * e**2, rel=1e-13)


@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_symbolic_small_solve_matches_numpy(n):
    """A^-1 B by the adjugate formulas (n <= 3) and symbolic QR beyond, against numpy's LU solve."""
    from invctl.simulate.codegen import small_solve

    rng = np.random.default_rng(n)
    A, B = rng.standard_normal((n, n)) + n * np.eye(n), rng.standard_normal((n, 2))
    As, Bs = ca.SX.sym("A", n, n), ca.SX.sym("B", n, 2)
    X = ca.Function("x", [As, Bs], [small_solve(As, Bs)])(A, B)
    np.testing.assert_allclose(np.array(X), np.linalg.solve(A, B), rtol=1e-12, atol=1e-12)


def test_small_solve_of_a_diagonal_matrix_divides_each_row():
    """A structurally diagonal A (the 2-DoF clearance's W_hat under PD on one body): each row of B divided
    by its diagonal entry: numpy's division to the last bit (the adjugate formula rounds three times)."""
    from invctl.simulate.codegen import small_solve

    d, B = np.array([1.7, 0.3, 2.9]), np.random.default_rng(0).standard_normal((3, 2))
    ds, Bs = ca.SX.sym("d", 3), ca.SX.sym("B", 3, 2)
    f = ca.Function("x", [ds, Bs], [small_solve(ca.diag(ds), Bs)])
    np.testing.assert_array_equal(np.array(f(d, B)), B / d[:, None])


def test_active_set_changes_counted_in_the_loop_equal_the_record(ball):
    """stats['n_changes'] (accumulated in the compiled loop) equals the steps whose active or loaded set differs
    from the previous step's, counted on the complete record (starting from nothing active)."""
    tr = ball.run([1.0], [0.0], 5.0, 1e-3)
    zero = np.zeros((tr.active.shape[0], 1), bool)
    act, load = np.hstack([zero, tr.active]), np.hstack([zero, tr.P > 0])
    changed = np.any(act[:, 1:] != act[:, :-1], axis=0) | np.any(load[:, 1:] != load[:, :-1], axis=0)
    assert tr.stats["n_changes"] == int(changed.sum()) > tr.stats["n_impacts"] > 10


def test_unmonitored_statistics_are_absent_and_asked_for_clearly(ball):
    """A run monitoring only the smallest gaps: its decimated record refuses the energy and V increases and
    the rest time with a RecordingError naming the option (no stale value), its complete record gives them
    from the rows, equal to the accumulators of the run monitoring everything; the gap statistic equals it."""
    m = ball.model
    mj = MoreauJean(m, potential=bb.potential(m), backend="vm", monitor=("gaps",))
    full = ball.run([1.0], [0.0], 5.0, 1e-3, record_every=100)
    dec = mj.run([1.0], [0.0], 5.0, 1e-3, record_every=100)
    assert dec.stats["monitor"] == ("gaps",) and full.stats["n_impacts"] >= 5
    assert not {"dE_max", "dV_max", "rest_last_bad", "n_impacts"} & set(dec.stats)
    np.testing.assert_array_equal(dec.stats["gap_min"], full.stats["gap_min"])
    from invctl.stability.lyapunov import lyapunov_report

    for ask in (lambda t: t.max_energy_increase, lambda t: t.max_V_increase, lambda t: t.rest_time(0),
                lyapunov_report):
        with pytest.raises(RecordingError, match=r"did not monitor .*monitor=\(\.\.\., '(energy|lyapunov|rest)'\)"):
            ask(dec)
    every = mj.run([1.0], [0.0], 5.0, 1e-3)
    assert every.max_energy_increase == full.max_energy_increase and every.max_V_increase == full.max_V_increase
    assert every.rest_time(0) == full.rest_time(0) < 5.0
    np.testing.assert_array_equal(every.impacts()[0], full.impacts()[0])


@pytest.mark.parametrize("bad", [("gaps", "energie"), "Energy", 3, ("gaps", None)])
def test_bad_monitor_names_are_refused_with_the_valid_ones(ball, bad):
    with pytest.raises(ParameterError, match="monitor: unknown") as ei:
        MoreauJean(ball.model, monitor=bad)
    assert all(repr(k) in str(ei.value) for k in MONITORS)
