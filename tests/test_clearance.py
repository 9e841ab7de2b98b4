"""Clearance scenes of 000: slider-crank (Prop. 2, PD+ tracking), Lyapunov monitoring (37), (51),
(52)/(54), Remark 4 switching, gear pre-loading, speed-accuracy study."""
import json

import casadi as ca
import numpy as np
import pytest

import invctl_scenes.bouncing_ball as bb
import invctl_scenes.prismatic_clearance as prism
import invctl_scenes.slider_crank_clearance as sc
from invctl.contact.mechanics import ContactSystem
from invctl.control.pdplus import christoffel_C, pd_gravity, pd_plus_tracking
from invctl.simulate.timestepping import MoreauJean
from invctl.stability.lyapunov import desired_velocity_condition, impact_jump_51, lyapunov_report


@pytest.fixture(scope="module")
def crank():
    return sc.build()


def test_christoffel_skew_symmetry(crank):
    """dM/dt - 2 C is skew-symmetric (000 Sect. 5) and C v reproduces the model's Coriolis force."""
    C = christoffel_C(crank)
    Mdot = ca.jacobian(ca.vec(crank.M), crank.q) @ crank.v
    Mdot = ca.reshape(Mdot, crank.n, crank.n)
    S = ca.Function("S", [crank.q, crank.v, crank.theta], [Mdot - 2 * C, -ca.mtimes(C, crank.v)
                                                           - ca.substitute(crank.f, crank.v, ca.DM.zeros(3))
                                                           + ca.vertcat(0, -crank.params["cs"] * crank.v[1], 0)
                                                           - crank.f])
    rng = np.random.default_rng(0)
    for _ in range(5):
        A, r = S(rng.normal(size=3), rng.normal(size=3), crank.theta_values)
        A = np.array(A)
        np.testing.assert_allclose(A, -A.T, atol=1e-12)
        np.testing.assert_allclose(np.array(r).ravel(), 0, atol=1e-12)


def test_pd_regulation_converges_to_equilibrium_set(crank):
    """Prop. 2: V (37) never increases (jumps at impacts <= 0), the crank reaches theta_d,
    velocities vanish, the journal stays in the bearing."""
    p = sc.PARAMS
    law = pd_gravity(crank, Kp=p["Kp"], Kv=p["Kv"], q_d=p["theta_d"], idx=[0])
    mj = MoreauJean(crank, law, backend="vm", projection=True)
    q0 = sc.centered_configuration(crank, p["theta0"])
    tr = mj.run(q0, np.zeros(3), 6.0, 1e-3)
    rep = lyapunov_report(tr)
    assert rep.n_impacts >= 1
    assert rep.max_increase_impacts <= 1e-12 * rep.V0
    assert rep.max_increase <= 1e-7 * rep.V0  # O(h^2) drift of the linearized step with q-dependent M
    assert rep.V_end < 1e-5 * rep.V0
    assert abs(tr.q[0, -1] - p["theta_d"]) < 1e-4
    assert np.max(np.abs(tr.v[:, -1])) < 2e-2
    assert tr.max_gap_violation <= 1e-10
    # the limit lies in the set of equilibria E (Lemma 2 with G_S2 = 0): crank at theta_d, any
    # journal position inside the bearing (the final one is not the initial centred one)
    assert cs_gap(crank, tr.q[:, -1]) >= -1e-10


def cs_gap(model, q):
    return float(ContactSystem(model).gaps(q)[0])


def test_pdplus_tracking_and_V_jump_51(crank):
    """PD+ (57) on the crank: bounded tracking error; at an exact impact, the jump of V equals
    T_L - qd_dot^T M11 sigma_1 (000 Sect. 6, item 5), checked to 1e-12."""
    p = sc.PARAMS
    th0, amp, per = p["theta0"], p["amp"], p["period"]
    law = pd_plus_tracking(crank, Kp=p["Kp"], Kv=p["Kv"], q_d=lambda t: th0 + amp * ca.sin(2 * np.pi * t / per), idx=[0])
    mj = MoreauJean(crank, law, backend="vm", projection=True)
    q0 = sc.centered_configuration(crank, th0)
    tr = mj.run(q0, np.zeros(3), 3.0, 1e-3)
    err = tr.q[0] - (th0 + amp * np.sin(2 * np.pi * tr.t / per))
    assert np.max(np.abs(err)) < 0.2 and tr.max_gap_violation <= 1e-10
    # exact impact at a contact configuration
    cs = ContactSystem(crank)
    k = int(np.flatnonzero(np.any(tr.impact_mask(), axis=0))[-1])
    q, vminus, t = tr.q[:, k + 1], tr.v[:, k], tr.t[k]
    W = cs.gradients(q)[:, 0]
    vminus = vminus - W * (W @ vminus) / (W @ W) - 0.05 * W / np.linalg.norm(W)  # approaching
    res = cs.impact(q, vminus, involved=[0])
    fn = law.function(crank)
    V = lambda vv: float(fn(q, vv, t, crank.theta_values, law.values())[1])  # noqa: E731
    M = crank.evaluate("M", q)
    sigma = res.v_plus - vminus
    qd_dot = 2 * np.pi / per * amp * np.cos(2 * np.pi * t / per)
    pred = res.kinetic_jump - qd_dot * (M[0, :] @ sigma)
    assert abs((V(res.v_plus) - V(vminus)) - pred) <= 1e-12 * max(1.0, abs(pred))
    # (51) for full-state V: the same identity with qd_dot on the actuated coordinate only
    e = crank.values["e"]
    assert abs(impact_jump_51(M, sigma, e, [qd_dot, 0, 0]) - pred) <= 1e-12 * max(1.0, abs(pred))


def test_desired_velocity_conditions_52_54():
    """(52)/(54): at a closed contact with tangential w, qd_dot must point into Phi."""
    model = prism.build(actuators=2)
    cs = ContactSystem(model)
    q = [0.0, 0.05]  # f1 = 0
    ok, margins, K = desired_velocity_condition(cs, q, [0.3, 0.3], [0.0, 1.0])
    assert ok and K.tolist() == [0] and margins[0] > 0
    ok, margins, _ = desired_velocity_condition(cs, q, [0.3, 0.3], [1.0, 0.0])
    assert not ok and margins[0] < 0
    ok, _, K = desired_velocity_condition(cs, q, [0.0, 1.0], [1.0, 0.0])  # separating: K(w) empty
    assert ok and K.size == 0


def test_remark4_switching_strategy():
    """Body 1 alone drives body 2 back and forth: persistent contact on f1 and f2 alternates
    through impacts, body 2 follows x_d with a small error, gaps stay >= -O(h)."""
    model = prism.build(actuators=1)
    p = prism.PARAMS
    law = prism.switching_law(model, Kp=p["Kp"], Kv=p["Kv"], amp=p["amp"], period=p["period"])
    tr = MoreauJean(model, law, backend="vm").run([0.0, p["l"]], [0.0, 0.0], 4.0, 1e-4)
    on1 = tr.active[0] & (tr.P[0] > 0)
    on2 = tr.active[1] & (tr.P[1] > 0)
    assert on1.mean() > 0.2 and on2.mean() > 0.2
    xd = p["l"] + p["amp"] * np.sin(2 * np.pi * tr.t / p["period"])
    assert np.max(np.abs(tr.q[1, tr.t > 2] - xd[tr.t > 2])) < 0.02
    assert tr.max_gap_violation < 1e-5


def test_gear_preload_cli(capsys):
    from invctl.cli import main

    assert main(["simulate", "gear_backlash", "--json", "--t-end", "0.5"]) == 0
    d = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert d["multiplier_error"] < 1e-9 and d["contacts_kept"] and d["rank"] == 2
    assert main(["analyze", "gear_backlash", "--json"]) == 0
    d = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    rep = d["reports"]["000 Example 4 (pre-loading f1 = f4 = 0)"]
    assert rep["differences"]["E_hat, f4 = theta3 - theta2 + alpha4 (c4 = +1)"] < 1e-14
    assert rep["differences"]["E_hat, f4 as printed (c4 = -1)"] > 0.5
    assert rep["values"]["printed conditions 2t1 > t2 + t3, t1 > -t2 + 2t3 <=> E_hat t < 0 (200 samples)"]
    assert main(["simulate", "slider_crank_clearance", "--controller", "nope"]) == 2


def test_timestep_study_slopes():
    from invctl.studies.timestep import timestep_study

    m = bb.build()
    mj = MoreauJean(m, potential=bb.potential(m), backend="vm")
    mjp = MoreauJean(m, potential=bb.potential(m), backend="vm", projection=True)
    ex_t, _, ex_post, _ = bb.exact_impacts(1.0, 9.81, 0.8, 2.0)
    st = timestep_study(mj, mjp, [1.0], [0.0], 2.0, [4e-3, 2e-3, 1e-3, 5e-4, 2.5e-4], ex_t, ex_post,
                        reference="closed form")
    assert 0.8 <= st.slope_time <= 1.6 and 0.8 <= st.slope_velocity <= 1.6
    assert np.all(st.penetration_projected <= 1e-10)
    assert st.plot() is not None


def test_condition_52_separates_V_jumps():
    """PD+ (57) on the crank: at impacts where (52) holds (grad f^T qd_dot >= 0 on the
    contacts that take an impulse) V does not increase; positive jumps occur only where
    (52) is violated (000 (51)-(52))."""
    from invctl.studies import commands

    d = commands.simulate("slider_crank_clearance", {"projection": 1.0, "h": 1e-4}, controller="pdplus",
                          t_end=2.0).data
    assert d["n_impacts"] > 10 and d["impacts_violating_52"] > 0
    assert d["max_V_jump_where_52_holds"] <= 1e-12
    assert d["max_V_jump_where_52_violated"] > 0


def test_juggling_law_linear_gap_dynamics():
    """I/O linearization (25) on the prismatic clearance (both bodies driven), output y = f1:
    in free flight y'' + Dy y' + Ky (y - y_d) = 0 (closed form), no contact is touched."""
    from invctl.control.juggling import juggling_law

    model = prism.build(actuators=2)
    Ky, Dy, yd = 400.0, 30.0, 0.002
    law = juggling_law(model, [0], Ky=Ky, Dy=Dy, y_d=yd)
    y0 = 0.005
    tr = MoreauJean(model, law, backend="vm").run([0.0, 0.05 + y0], [0.0, 0.0], 0.5, 1e-4)
    assert np.all(tr.P == 0)
    r = np.roots([1.0, Dy, Ky])  # distinct real roots (Dy^2 > 4 Ky)
    c = np.linalg.solve([[1.0, 1.0], [r[0], r[1]]], [y0 - yd, 0.0])
    y_exact = yd + (c[0] * np.exp(r[0] * tr.t) + c[1] * np.exp(r[1] * tr.t)).real
    np.testing.assert_allclose(tr.gaps[0], y_exact, atol=1e-8)  # theta = 1/2: O(h^2)


def test_prismatic_juggling_controller_cli(capsys):
    from invctl.cli import main

    assert main(["simulate", "prismatic_clearance", "--set", "actuators=2", "--controller", "juggling",
                 "--t-end", "2", "--json"]) == 0
    d = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert abs(d["gap_error_final"][0]) < 1e-6 and d["n_impacts"] >= 1
    assert main(["simulate", "prismatic_clearance", "--controller", "juggling"]) == 2  # one actuator: refused


def test_lemma2_equilibria_and_projector_form():
    """Lemma 2 on the prismatic clearance under PD (36): the limit (q1 = qd, journal against f1)
    is an equilibrium, a point with q1 != qd in the same contact is not (its PD force is not a
    non-negative combination of the normal). The projector form holds with D^{-1}; the printed
    form with D fails on a generic system (typo, docs/reproduction.md)."""
    from invctl.stability.lyapunov import equilibrium_check

    model = prism.build(actuators=1)
    p = prism.PARAMS
    law = pd_gravity(model, Kp=p["Kp"], Kv=p["Kv"], q_d=p["qd"], idx=[0])
    tr = MoreauJean(model, law, backend="vm", projection=True).run([0.0, 0.055], [0.0, 0.3], 4.0, 1e-4)
    cs = ContactSystem(model)
    qf = tr.q[:, -1]
    chk = equilibrium_check(cs, qf, [p["Kp"] * (qf[0] - p["qd"]), 0.0], gap_tol=1e-9, rtol=1e-6)
    assert chk.is_equilibrium  # interior (Lemma 2 (i)) or against f1 (ii), depending on the last bounce
    bad = equilibrium_check(cs, [0.1, 0.15], [p["Kp"] * (0.1 - p["qd"]), 0.0])
    assert not bad.is_equilibrium and bad.closed.tolist() == [0]
    # projector form of Lemma 2 (ii), random independent contacts: G = W lam
    rng = np.random.default_rng(2)
    M = rng.normal(size=(4, 4))
    M = M @ M.T + np.eye(4)
    W = rng.normal(size=(4, 2))
    G = W @ np.array([0.7, 1.3])
    D = W.T @ np.linalg.solve(M, W)
    good = (np.eye(4) - W @ np.linalg.solve(D, W.T @ np.linalg.inv(M))) @ G
    printed = (np.eye(4) - W @ D @ W.T @ np.linalg.inv(M)) @ G
    assert np.linalg.norm(good) < 1e-12 and np.linalg.norm(printed) > 1e-3
