"""Stable inversion through the normal form (003 Sect. 2): against the servo-constraint route, flatness
closed forms, a direct integration with internal dynamics of relative degree 4, and bad input."""
import casadi as ca
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import invctl_scenes.cartpole as cartpole
import invctl_scenes.crane as crane
import invctl_scenes.manipulator as manipulator
import invctl_scenes.two_link_arm as arm
from invctl.errors import (HorizonTooLongError, NoDichotomyError, ReferenceSmoothnessError, RelativeDegreeError,
                           SingularDecouplingError)
from invctl.inversion import Inverse, invert, invert_normal_form
from invctl.model import Model, ParamSet
from invctl.reference import rest_to_rest
from invctl.testing import assert_inverts


def _max_rel(a, b):
    """Largest difference of two trajectories relative to the largest value of the second."""
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))


def _compare_routes(model, reference, q_guess, phi=None, N_servo=400):
    """Both routes on the horizon the servo route's plan derives (tails below 1e-8), the normal form
    with its own tolerance 1e-7; the normal form's derived horizon (tol 1e-8) is checked to be the same."""
    sv = invert(model, reference, q_guess=q_guess, N=N_servo, backend="newton")
    nf = invert_normal_form(model, reference, q_guess=q_guess, phi=phi, tol=1e-7, T0=sv.T0, Tf=sv.Tf)
    t = np.linspace(sv.T0, sv.Tf, 1501)
    return nf, sv, t


# ------------------------------------------------------------------ two independent routes
def test_cartpole_normal_form_equals_servo_constraint_inverse():
    model = cartpole.build()
    ref = cartpole.reference(model)
    nf, sv, t = _compare_routes(model, ref, [0.0, 0.0])
    d = nf.diagnostics
    assert d["method"] == "normal-form" and d["r_hat"] == 2 and d["internal_dim"] == 2
    zd = cartpole.zero_dynamics_eigenvalues(model)
    # the same rates (+-3.836/s, the inverted pendulum) give the same horizon for the same tails (1e-8)
    h = d["horizon"]
    assert abs(h["rate_pre"] - zd[1]) < 1e-9 and abs(h["rate_post"] + zd[0]) < 1e-9
    assert abs(sv.t0 - sv.T0 - np.log(1e8) / zd[1]) < 1e-6
    eig = sorted(z[0] for z in d["horizon"]["eigenvalues_start"])
    np.testing.assert_allclose(eig, zd, rtol=1e-9)
    # two independent discretizations (solve_bvp, tol 1e-7, and Hermite-Simpson collocation at N = 400,
    # whose own error dominates: measured 1e-7 in u relative, 2e-9 in q): agreement well below 1e-6
    assert _max_rel(nf.u(t), sv.u(t)) < 1e-6
    assert _max_rel(nf.q(t), sv.q(t)) < 1e-7 and _max_rel(nf.v(t), sv.v(t)) < 1e-6
    # non-minimum phase: both pre-actuate
    assert nf.T0 < ref.t0 - 1 and np.max(np.abs(nf.u(np.linspace(nf.T0, ref.t0, 50)))) > 1e-3
    assert assert_inverts(model, nf, ref, tol=1e-8)["error"] < 1e-8


def test_manipulator_normal_form_equals_servo_constraint_inverse():
    model = manipulator.build()
    ref = manipulator.reference(model)
    q0 = manipulator.initial_configuration(model)
    nf, sv, t = _compare_routes(model, ref, q0, phi=manipulator.paper_internal_coordinates)
    # rates +24.44/s (start) and -19.64/s (end), as the servo route's plan finds them
    h, plan = nf.diagnostics["horizon"], sv.diagnostics["plan"]
    assert abs(h["rate_pre"] - plan["rate_pre"]) < 1e-6 * plan["rate_pre"]
    assert abs(h["rate_post"] - plan["rate_post"]) < 1e-6 * plan["rate_post"]
    # measured: q 1e-9, lam 1.5e-7, u 3e-8 relative (HS N = 400 dominates); multipliers come from (15)
    # here and from the jerk-level index reduction there
    assert _max_rel(nf.u(t), sv.u(t)) < 1e-6
    assert _max_rel(nf.lam(t), sv.lam(t)) < 1e-6
    assert _max_rel(nf.q(t), sv.q(t)) < 1e-7
    rep = assert_inverts(model, nf, ref, tol=1e-7)
    assert rep["error"] < 1e-7
    res = nf.diagnostics["residuals"]
    # forward dynamics under u reproduce the acceleration and the multipliers of the reconstruction
    assert res["dynamics"] < 1e-9 and res["multipliers"] < 1e-9 and res["position"] < 1e-9


def test_servo_route_converges_to_the_normal_form_inverse_at_order_four():
    # the normal form at tol 1e-9 as the reference; Hermite-Simpson (order 4) at N = 100, 200, 400 on the
    # same horizon: the differences fall by 2^4 per doubling (measured 2.4e-5, 1.4e-6, 9.0e-8 in u), so they
    # are the servo route's discretization error, not a disagreement of the methods
    model = cartpole.build()
    ref = cartpole.reference(model)
    errs = []
    for N in (100, 200, 400):
        sv = invert(model, ref, N=N, backend="newton", q_guess=[0.0, 0.0])
        if N == 100:
            nf = invert_normal_form(model, ref, tol=1e-9, T0=sv.T0, Tf=sv.Tf)
        t = np.linspace(sv.T0, sv.Tf, 3001)
        errs.append(_max_rel(sv.u(t), nf.u(t)))
    slopes = np.diff(np.log2(errs))
    assert np.all((-4.6 < slopes) & (slopes < -3.5)), errs
    assert errs[-1] < 2e-7


def test_inverse_does_not_depend_on_the_internal_coordinates():
    # Lemma 3.1/3.2 coordinates (default) against the paper's eta = (gamma, e5^T M v): different BVPs for
    # the same inverse; cart-pole (cheap) with its default coordinates against (theta, J theta' + ...)
    model = cartpole.build()
    ref = cartpole.reference(model)
    a = invert_normal_form(model, ref, tol=1e-7)
    b = invert_normal_form(model, ref, tol=1e-7, phi=lambda m: ca.vertcat(m.q[1], ca.mtimes(m.M[1, :], m.v)))
    assert a.diagnostics["coordinates"] != b.diagnostics["coordinates"]
    t = np.linspace(a.T0, a.Tf, 1001)
    # both within tol = 1e-7 of the exact inverse (solve_bvp residual and Hermite interpolation)
    assert _max_rel(a.u(t), b.u(t)) < 1e-6 and _max_rel(a.q(t), b.q(t)) < 1e-7


# ------------------------------------------------------------------ flat outputs: closed forms
def linear_cartpole_flat():
    """The cart-pole linearized at the upright with y = x + (J / (mp l)) theta = x + (4/3) l theta (homogeneous
    pole): y'' = g theta, so the output is flat with relative degree 4 (the nonlinear x + (4/3) l sin(theta) is
    not, see test_nonlinear_cartpole_output_has_no_relative_degree)."""
    P = ParamSet(["mc", "mp", "l", "g"])
    mc, mp, l, g = (P[k] for k in P.names)
    q, v = ca.SX.sym("q", 2), ca.SX.sym("v", 2)
    J = 4 * mp * l**2 / 3
    M = ca.vertcat(ca.horzcat(mc + mp, mp * l), ca.horzcat(mp * l, J))
    f = ca.vertcat(0, mp * g * l * q[1])
    return Model("cartpole_linear_flat", q, v, P, {"mc": 1.0, "mp": 0.2, "l": 0.5, "g": 9.81}, M=M, f=f,
                 B=ca.DM([[1], [0]]), h=q[0] + J / (mp * l) * q[1], q_names=["x", "theta"], u_names=["F"])


def test_flat_linear_cartpole_matches_flatness_closed_form():
    model = linear_cartpole_flat()
    ref = rest_to_rest(0.0, 0.5, 0.0, 2.0, smoothness=5)
    with pytest.raises(SingularDecouplingError):       # why this route exists: h' M^-1 B = 0
        invert(model, ref, N=40)
    inv = invert_normal_form(model, ref)
    d = inv.diagnostics
    assert d["r_hat"] == 4 and d["internal_dim"] == 0
    assert inv.T0 == ref.t0 and inv.Tf == ref.tf and d["pre_actuation"] == 0.0 and d["post_actuation"] == 0.0
    # closed form: theta = y''/g, x = y - c theta, F = (mc + mp) x'' + mp l theta''
    p = model.values
    c = 4 * p["l"] / 3
    t = np.linspace(ref.t0 - 0.5, ref.tf + 0.5, 1201)
    y, y2, y4 = ref(t), ref(t, 2), ref(t, 4)
    theta = y2 / p["g"]
    x = y - c * theta
    F = (p["mc"] + p["mp"]) * (y2 - c * y4 / p["g"]) + p["mp"] * p["l"] * y4 / p["g"]
    # the Hermite interpolant is within tol = 1e-8 of the reconstruction relative to each block's scale
    assert _max_rel(inv.q(t), np.vstack([x, theta])) < 3e-8
    assert _max_rel(inv.u(t), F) < 3e-8
    assert np.all(inv.u_causal(t) == inv.u(t) * (t >= ref.t0))
    assert np.max(np.abs(inv.u(t[t < ref.t0]))) < 1e-12          # no pre-actuation at all
    assert assert_inverts(model, inv, ref, tol=1e-8)["error"] < 1e-8


def test_nonlinear_cartpole_output_has_no_relative_degree():
    # y = x + (4/3) l sin(theta): y'' = sin^2(theta) x'' + ...: relative degree 2 away from the upright, the
    # coefficient vanishes at theta = 0, so neither route can invert it there (the cart-pole is not flat)
    base = cartpole.build()
    l = base.params["l"]
    model = Model("cartpole_sin", base.q, base.v, base.params, base.values, M=base.M, f=base.f, B=base.B,
                  h=base.q[0] + 4 * l / 3 * ca.sin(base.q[1]), region=base.region)
    ref = rest_to_rest(0.0, 0.5, 0.0, 2.0, smoothness=5)
    with pytest.raises(RelativeDegreeError, match=r"does not exist at q = \[0.0, 0.0\]"):
        invert_normal_form(model, ref)


def test_crane_inverse_is_the_flatness_closed_form():
    model = crane.build()
    ref = crane.reference(model)
    with pytest.raises(SingularDecouplingError):
        invert(model, ref, N=40, q_guess=crane.initial_configuration(model))
    inv = invert_normal_form(model, ref, q_guess=crane.initial_configuration(model))
    d = inv.diagnostics
    assert d["relative_degree"] == [4, 4] and d["internal_dim"] == 0
    # minimum phase and flat: no pre- or post-actuation, the feedforward starts at rest at t0
    assert inv.T0 == ref.t0 and inv.Tf == ref.tf
    t = np.linspace(ref.t0, ref.tf, 1501)
    qf, uf = crane.flat_inverse(model, ref)
    Q = np.array(qf.map(t.size)(t[None, :]))
    U = np.array(uf.map(t.size)(t[None, :]))
    # Newton's laws (closed form by AD in t) against the Lagrangian normal form: both exact, the interpolant
    # within tol = 1e-8 of each block's scale (measured 1.4e-9 m and 5e-8 N of 10.7 N)
    assert np.max(np.abs(inv.q(t) - Q)) < 3e-8 * np.max(np.abs(Q))
    assert _max_rel(inv.u(t), U) < 3e-8
    # at rest at both ends: holding forces (0, -mL g)
    np.testing.assert_allclose(inv.u([ref.t0, ref.tf]), [[0, 0], [-9.81, -9.81]], atol=1e-9)
    np.testing.assert_allclose(inv.q(ref.t0).ravel(), crane.rest_configuration(model, crane.Y0), atol=1e-12)
    rep = assert_inverts(model, inv, ref, tol=1e-7)     # measured 5e-9 m
    assert rep["error"] < 1e-7


def test_crane_scene_declares_a_tracking_scene():
    from invctl.scenes import load_scene

    scene = load_scene("crane")
    assert scene.kind == "tracking" and "invert" in scene.commands
    model = scene.model({"mL": 2.0})
    assert model.values["mL"] == 2.0 and dict(scene.tracking.plant) == {"mL": 1.2}
    dr = scene.drawing(model)
    assert set(dr.points) == {"trolley", "load"}


def test_crane_closed_loop_end_to_end_with_a_heavier_load():
    # feedforward from the normal form, funnel feedback for the flat output (lin=None: no internal dynamics),
    # plant with the scene's mismatch (load x 1.2); no study glue involved
    from invctl.control.funnel_design import design_funnel_feedback
    from invctl.control.funnel_nmp import NMPFunnelController
    from invctl.simulate.closed_loop import ClosedLoop

    model = crane.build()
    ref = crane.reference(model)
    plant = model.scaled(**crane.SCENE.tracking.plant)
    inv = invert_normal_form(model, ref, q_guess=crane.initial_configuration(model))
    t_end = 3.5
    t = np.linspace(0.0, t_end, 3501)
    uff = (t, inv.u_causal(t))
    q0 = crane.rest_configuration(plant, crane.Y0)
    exact = ClosedLoop(model, ref, u_ff=uff, t_end=t_end, dt=5e-3).run(crane.rest_configuration(model, crane.Y0))
    assert np.max(exact.output_error) < 1e-6      # the sampled (1 ms, linear) feedforward on the model: 6e-8
    ff = ClosedLoop(plant, ref, u_ff=uff, t_end=t_end, dt=5e-3).run(q0)
    # feedforward alone: the winch holds mL g of the model, so load and drum fall together with
    # a = (1.2 - 1) mL g / (1.2 mL + Jw) from t = 0 (the rope's bounce and the swing add millimetres)
    p = model.values
    a = 0.2 * p["mL"] * p["g"] / (1.2 * p["mL"] + p["Jw"])
    assert abs(ff.output_error[-1] - 0.5 * a * t_end**2) < 0.01 * 0.5 * a * t_end**2
    design = design_funnel_feedback(model, None, ref, q0=q0, controller_options={"t_end": t_end})
    ctrl = NMPFunnelController(model, None, ref, t_end=t_end, **design.controller_options())
    assert ctrl.r_hat == 4 and ctrl.k == 0
    c1 = ClosedLoop(plant, ref, controller=ctrl, u_ff=uff, t_end=t_end, dt=5e-3).run(q0)
    assert c1.status == "ok" and np.all(c1.ratios < 1)         # inside every funnel
    assert c1.cumulative_errors["output"] < 0.1 * ff.cumulative_errors["output"]


# ------------------------------------------------------------------ relative degree 4 with internal dynamics
def spring_chain():
    """Three masses on a line: force on mass 1, spring k12 to mass 2 (the output: relative degree 4),
    spring k23 and damper d23 to mass 3 (internal dynamics of dimension 2, stable: minimum phase)."""
    P = ParamSet(["m1", "m2", "m3", "k12", "k23", "d23"])
    m1, m2, m3, k12, k23, d23 = (P[k] for k in P.names)
    q, v = ca.SX.sym("q", 3), ca.SX.sym("v", 3)
    T = 0.5 * (m1 * v[0] ** 2 + m2 * v[1] ** 2 + m3 * v[2] ** 2)
    V = 0.5 * k12 * (q[0] - q[1]) ** 2 + 0.5 * k23 * (q[1] - q[2]) ** 2
    Qd = d23 * (v[2] - v[1])
    values = {"m1": 1.0, "m2": 1.0, "m3": 0.5, "k12": 40.0, "k23": 20.0, "d23": 2.0}
    return Model.from_lagrangian("spring_chain", q, v, P, values, T=T, V=V, Q=ca.vertcat(0, Qd, -Qd),
                                 B=ca.DM([[1], [0], [0]]), h=q[1])


def test_relative_degree_four_with_internal_dynamics_matches_direct_integration():
    model = spring_chain()
    p = model.values
    ref = rest_to_rest(0.0, 0.2, 0.0, 1.0, smoothness=5)
    inv = invert_normal_form(model, ref, tol=1e-8, phi=lambda m: ca.vertcat(m.q[2], m.v[2]))
    d = inv.diagnostics
    assert d["r_hat"] == 4 and d["internal_dim"] == 2
    # zero dynamics m3 s^2 + d23 s + k23 = 0: -2 +- 6i, stable: no pre-actuation, post-actuation ln(1e8)/2
    np.testing.assert_allclose(sorted(z[1] for z in d["horizon"]["eigenvalues_start"]), [-6.0, 6.0], rtol=1e-9)
    # the post-actuation is the shortest span with ||exp(A s)||_2 <= tol for A of the zero dynamics in
    # (x3, v3) (checked by scipy's expm; longer than ln(1/tol)/2 by the non-normality of A)
    from scipy.linalg import expm

    A = np.array([[0.0, 1.0], [-p["k23"] / p["m3"], -p["d23"] / p["m3"]]])
    s = d["post_actuation"]
    assert inv.T0 == ref.t0 and d["pre_actuation"] == 0.0
    assert np.linalg.norm(expm(A * s), 2) <= 1.0001e-8 < np.linalg.norm(expm(A * 0.99 * s), 2)

    def x3_rhs(t, z):  # mass 3 driven by the prescribed mass 2
        y, y1 = ref(t).item(), ref(t, 1).item()
        return [z[1], (p["k23"] * (y - z[0]) + p["d23"] * (y1 - z[1])) / p["m3"]]

    sol = solve_ivp(x3_rhs, (inv.T0, inv.Tf), [0.0, 0.0], method="DOP853", rtol=1e-12, atol=1e-14,
                    dense_output=True)
    t = np.linspace(inv.T0, inv.Tf, 801)
    x3, v3 = sol.sol(t)
    y, y1, y2, y3, y4 = (ref(t, k).ravel() for k in range(5))
    a3 = (p["k23"] * (y - x3) + p["d23"] * (y1 - v3)) / p["m3"]
    j3 = (p["k23"] * (y1 - v3) + p["d23"] * (y2 - a3)) / p["m3"]
    x1 = y + (p["m2"] * y2 + p["k23"] * (y - x3) + p["d23"] * (y1 - v3)) / p["k12"]
    a1 = y2 + (p["m2"] * y4 + p["k23"] * (y2 - a3) + p["d23"] * (y3 - j3)) / p["k12"]
    F = p["m1"] * a1 + p["k12"] * (x1 - y)
    # solve_bvp (tol 1e-8) against DOP853 (1e-12): agreement to a few 1e-8 of the signals' scales
    assert _max_rel(inv.q(t), np.vstack([x1, y, x3])) < 5e-8
    assert _max_rel(inv.u(t), F) < 5e-8
    assert assert_inverts(model, inv, ref, tol=1e-8)["error"] < 1e-8


# ------------------------------------------------------------------ results and bad input
def test_save_load_roundtrip(tmp_path):
    model = linear_cartpole_flat()
    ref = rest_to_rest(0.0, 0.5, 0.0, 2.0, smoothness=5)
    inv = invert_normal_form(model, ref, tol=1e-6)
    path = inv.to_npz(tmp_path / "nf.npz", meta={"scene": "test"})
    back = Inverse.load(path)
    t = np.linspace(-0.5, 2.5, 91)
    np.testing.assert_allclose(back.X(t), inv.X(t), rtol=0, atol=1e-14)
    assert back.diagnostics["method"] == "normal-form" and back.diagnostics["r_hat"] == 4


def test_reference_needs_r_hat_plus_one_derivatives():
    model = crane.build()
    rough = rest_to_rest(crane.Y0, crane.YF, 0.0, 3.0, smoothness=4)     # C^4: u is C^0 but u' jumps
    with pytest.raises(ReferenceSmoothnessError, match="5 continuous derivatives"):
        invert_normal_form(model, rough, q_guess=crane.initial_configuration(model))


def test_neutral_zero_dynamics_have_no_dichotomy():
    model = arm.build(D2=0.0)        # the undamped pendulum of link 2: eigenvalues on the imaginary axis
    with pytest.raises(NoDichotomyError, match="imaginary axis"):
        invert_normal_form(model, arm.reference(model))


def test_horizon_cap_and_options_are_checked():
    model = cartpole.build()
    ref = cartpole.reference(model)
    with pytest.raises(HorizonTooLongError, match="max_horizon"):
        invert_normal_form(model, ref, max_horizon=3.0)
    with pytest.raises(ValueError, match="tol"):
        invert_normal_form(model, ref, tol=2.0)
    with pytest.raises(ValueError, match="N must be"):
        invert_normal_form(model, ref, N=1)
    with pytest.raises(ValueError, match="q_guess"):
        invert_normal_form(model, ref, q_guess=[0.0])
