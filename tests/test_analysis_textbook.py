"""Textbook cases: cart-pole (non-minimum phase), colocated two-link arm (minimum phase,
Gamma = Schur complement case of 003 Sect. 2.3), knife edge (non-holonomic), and
outputs whose relative degree does not exist.

References are closed forms derived by hand in the scene docstrings; they are
exact, so tolerances only cover round-off and the 1e-12 Newton tolerance.
"""
import casadi as ca
import numpy as np
import pytest

import invctl_scenes.cartpole as cartpole
import invctl_scenes.knife_edge as knife
import invctl_scenes.two_link_arm as arm
from invctl.analysis import (
    auxiliary_system, colocated_check, consistent_state, internal_dynamics, linearize_internal, relative_degree,
    schur_complement,
)
from invctl.errors import CoordinateError, RelativeDegreeError


# ------------------------------------------------------------------ cart-pole
def test_cartpole_zero_dynamics_closed_form():
    model = cartpole.build(D=0.3)
    p = model.values
    J = p["I"] + p["mp"] * p["l"] ** 2
    idyn = internal_dynamics(model, "sect3", point=[0.0, 0.0])
    assert idyn.dim == 2 and np.allclose(idyn.E, [[0, 1]])
    rng = np.random.default_rng(0)
    for _ in range(10):
        y, yd = rng.uniform(-1, 1, 1), rng.uniform(-1, 1, 1)
        e1, e2 = rng.uniform(-1, 1), rng.uniform(-2, 2)
        e1d = e2 - p["mp"] * p["l"] * np.cos(e1) * yd[0] / J
        e2d = (p["mp"] * p["g"] * p["l"] * np.sin(e1) - p["mp"] * p["l"] * np.sin(e1) * yd[0] * e1d - p["D"] * e1d) / J
        np.testing.assert_allclose(idyn((y, yd), [e1, e2]), [e1d, e2d], rtol=1e-10, atol=1e-12)
    lin = linearize_internal(model, idyn, [([[0.0], [0.0]], [0.0, 0.0])])
    np.testing.assert_allclose(np.sort(lin.eigenvalues.real), cartpole.zero_dynamics_eigenvalues(model), rtol=1e-10)
    assert lin.k == 1 and not lin.minimum_phase


def test_cartpole_is_colocated_with_positive_gamma():
    rep = colocated_check(cartpole.build(), samples=50)
    assert rep.colocated and rep.gamma_min_eig > 0 and rep.schur_min_eig > 0


# ------------------------------------------------------------- two-link arm
def test_two_link_arm_minimum_phase_closed_form():
    model = arm.build()
    idyn = internal_dynamics(model, "sect3", point=[0.0, 0.0])
    for q1 in (0.0, 0.4):
        q2 = arm.zero_dynamics_equilibrium(model, q1)
        lin = linearize_internal(model, idyn, [([[q1], [0.0]], [q2, 0.0])])
        ev = np.sort_complex(lin.eigenvalues)
        np.testing.assert_allclose(ev, np.sort_complex(arm.zero_dynamics_eigenvalues(model, q1)), rtol=1e-9)
        assert lin.minimum_phase and lin.k == 0


def test_two_link_arm_redundant_schur_complement_equals_minimal_gamma():
    """003 Sect. 2.3: with the joint as a holonomic constraint Gamma is symmetric positive definite and the
    Schur complement S of (15) is the high-gain of the reduced system, i.e. Gamma of the minimal model."""
    red, mini = arm.build_redundant(), arm.build()
    rep = colocated_check(red, samples=60)
    assert rep.colocated and rep.gamma_max_asym < 1e-12 and rep.gamma_min_eig > 0 and rep.schur_min_eig > 0
    rd_min = relative_degree(mini, samples=10)
    S = schur_complement(red)
    rng = np.random.default_rng(3)
    for _ in range(10):
        q1, q2 = rng.uniform(-2, 2), rng.uniform(-1.2, 1.2)
        qr = arm.redundant_configuration(red, q1, q2)
        S_val = float(S(qr, np.zeros(4), red.theta_values))
        G_min = float(rd_min.gamma([q1, q2], [0, 0], mini.theta_values))
        assert S_val == pytest.approx(G_min, rel=1e-12)


def test_two_link_arm_redundant_internal_dynamics_match_minimal():
    red, mini = arm.build_redundant(), arm.build()
    idyn = internal_dynamics(red, "sect3", point=arm.redundant_configuration(red, 0.0, 0.0))
    assert idyn.dim == 2
    for q1 in (0.0, 0.4):
        q2 = arm.zero_dynamics_equilibrium(mini, q1)
        lr = linearize_internal(red, idyn, [([[q1], [0.0]], np.array(
            idyn.eta(arm.redundant_configuration(red, q1, q2), np.zeros(4), red.theta_values)).ravel())])
        np.testing.assert_allclose(np.sort_complex(lr.eigenvalues),
                                   np.sort_complex(arm.zero_dynamics_eigenvalues(mini, q1)), rtol=1e-8)


def test_two_link_arm_sect2_equals_sect3():
    model = arm.build_redundant()
    q0 = arm.redundant_configuration(model, 0.1, 0.2)
    s3 = internal_dynamics(model, "sect3", point=q0)
    s2 = internal_dynamics(model, "sect2", s3.phi_expr, point=q0)
    rng = np.random.default_rng(5)
    for _ in range(5):
        ys = (rng.uniform(-0.3, 0.3, 1), rng.uniform(-1, 1, 1))
        eta = rng.uniform(-0.3, 0.3, 2)
        np.testing.assert_allclose(s2(ys, eta), s3(ys, eta), rtol=1e-10, atol=1e-10)


def test_tip_output_relative_degree_undefined_at_stretched_arm():
    model = arm.build_tip()
    with pytest.raises(RelativeDegreeError, match="det Gamma changes sign") as err:
        relative_degree(model, samples=100)
    assert err.value.partial is not None and err.value.diagnostics["sigma_min"] > 0
    # at the stretched arm itself the error names the point and Gamma's smallest singular value
    with pytest.raises(RelativeDegreeError, match=r"does not exist at q = \[0.3, 0.0\].*smallest singular value") as err:
        relative_degree(model, samples=0, points=[[0.3, 0.0]])
    assert err.value.diagnostics["sigma_min"] < 1e-12


# --------------------------------------------------------------- knife edge
def test_knife_edge_relative_degree_and_gamma():
    model = knife.build()
    rd = relative_degree(model, samples=100)
    assert rd.r_aux == (1, 2, 2) and rd.r_hat == 2 and rd.r_bar == 5
    p = model.values
    for th in (-1.0, 0.0, 0.7):
        G = np.array(rd.gamma([0.3, -0.2, th], [0.1, 0.2, 0.3], model.theta_values))
        assert np.linalg.det(G) == pytest.approx(np.cos(th) / (p["m"] ** 2 * p["I"]), rel=1e-12)


def test_knife_edge_internal_dynamics_closed_form():
    model = knife.build()
    idyn = internal_dynamics(model, "sect3", point=[0.0, 0.0, 0.3])
    assert idyn.dim == 1 and idyn.dim2 == 0
    s2 = internal_dynamics(model, "sect2", point=[0.0, 0.0, 0.3])
    rng = np.random.default_rng(1)
    for _ in range(10):
        y, yd, eta = rng.uniform([-1, -1.0], [1, 1.0]), rng.uniform(-1, 1, 2), rng.uniform(-1, 1, 1)
        expected = np.tan(y[1]) * yd[0]
        assert idyn((y, yd), eta)[0] == pytest.approx(expected, rel=1e-10, abs=1e-12)
        assert s2((y, yd), eta)[0] == pytest.approx(expected, rel=1e-10, abs=1e-12)
        q, v = (np.array(a).ravel() for a in idyn.state(y_0=y, y_1=yd, eta=eta, theta=model.theta_values).values())
        assert abs(model.evaluate("J", q) @ v) < 1e-12  # the velocity respects the constraint


def test_knife_edge_position_output_has_no_relative_degree():
    with pytest.raises(RelativeDegreeError, match="smallest singular value is 0"):
        relative_degree(knife.build_position_output(), samples=20)


# ------------------------------------------------------------ auxiliary ODE
@pytest.mark.parametrize("build", [knife.build, arm.build_redundant])
def test_auxiliary_ode_reproduces_the_dae(build):
    """(10) with u_aux = (mu, lam, u) from the index-1 DAE gives the DAE's acceleration."""
    model = build()
    aux = auxiliary_system(model)
    acc = model.accel_and_multipliers
    th = model.theta_values
    rng = np.random.default_rng(2)
    qs, _ = model.region.sample(5, 4)
    for q in qs:
        q, v = consistent_state(model, q, rng.uniform(-1, 1, model.n))
        u = rng.uniform(-2, 2, model.m)
        a, lam, mu = (np.array(x).ravel() for x in acc(q, v, u, th))
        xdot, yaux = aux.function(q, v, np.concatenate([mu, lam, u]), th)
        np.testing.assert_allclose(np.array(xdot).ravel(), np.concatenate([v, a]), rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(np.array(yaux).ravel()[: model.p + model.ell], 0, atol=1e-10)


# -------------------------------------------------------------- bad inputs
def test_phi_with_wrong_size_is_reported():
    model = cartpole.build()
    with pytest.raises(CoordinateError, match="phi has 1 rows.*dimension 2n - r_bar = 4 - 2 = 2"):
        internal_dynamics(model, "sect2", lambda m: m.q[1], point=[0, 0])


def test_velocity_coordinate_violating_25_is_reported():
    model = cartpole.build()
    with pytest.raises(CoordinateError, match="L_K phi != 0"):
        internal_dynamics(model, "sect3", lambda m: ca.vertcat(m.q[1], m.v[1]), point=[0, 0], samples=10)


def test_linearization_point_with_wrong_derivative_count():
    model = cartpole.build()
    idyn = internal_dynamics(model, point=[0, 0])
    with pytest.raises(CoordinateError, match="r_hat = 2 output derivatives, got 1"):
        linearize_internal(model, idyn, [([[0.0]], [0.0, 0.0])])


def test_velocity_output_relative_degree_one_by_sect2():
    """Two masses coupled by a spring-damper, force on mass 1, velocity output y = v1 (r_hat = 1): the general
    Sect. 2 route with user coordinates eta = (q1, q2, v2) (L_K phi = 0: M is diagonal and the input acts on
    v1 only). Closed form: q1' = y, q2' = v2, v2' = (-k2 (q2 - q1) - d2 (v2 - y)) / m2."""
    from invctl.model import Model, ParamSet

    P = ParamSet(["m1", "m2", "k2", "d2"])
    q, v = ca.SX.sym("q", 2), ca.SX.sym("v", 2)
    spring = P["k2"] * (q[1] - q[0]) + P["d2"] * (v[1] - v[0])
    model = Model("msd", q, v, P, {"m1": 1.0, "m2": 0.5, "k2": 3.0, "d2": 0.2},
                  M=ca.diag(ca.vertcat(P["m1"], P["m2"])), f=ca.vertcat(spring, -spring), B=ca.DM([[1], [0]]),
                  h=v[0])
    rd = relative_degree(model, samples=20)
    assert rd.r_aux == (1,) and rd.r_hat == 1 and rd.r_bar == 1
    with pytest.raises(CoordinateError, match="position output"):
        internal_dynamics(model, "sect3", point=[0, 0])
    idyn = internal_dynamics(model, "sect2", lambda m: ca.vertcat(m.q, m.v[1]), point=[0, 0], samples=20)
    assert idyn.dim == 3
    rng = np.random.default_rng(0)
    for _ in range(5):
        y, (q1, q2, v2) = rng.uniform(-1, 1, 1), rng.uniform(-1, 1, 3)
        expected = [y[0], v2, (-3.0 * (q2 - q1) - 0.2 * (v2 - y[0])) / 0.5]
        np.testing.assert_allclose(idyn((y,), [q1, q2, v2]), expected, rtol=1e-12, atol=1e-12)
    lin = linearize_internal(model, idyn, [([[0.0]], [0.0, 0.0, 0.0])])
    # q1 is a pure integrator of y: one zero eigenvalue; the rest is the spring-damper of mass 2
    ev = np.sort_complex(lin.eigenvalues)
    np.testing.assert_allclose(np.sort_complex(np.concatenate([[0.0], np.roots([1, 0.2 / 0.5, 3.0 / 0.5])])), ev,
                               atol=1e-12)


def test_phi_with_foreign_symbols_is_reported():
    model = cartpole.build()
    foreign = ca.SX.sym("q", 2)  # same name as model.q, but another symbol
    with pytest.raises(CoordinateError, match="not the model's"):
        internal_dynamics(model, "sect2", ca.vertcat(foreign[1], model.v[1]), point=[0, 0])


def test_wrong_sizes_at_evaluation_are_reported():
    from invctl.errors import DimensionError

    model = cartpole.build()
    idyn = internal_dynamics(model, point=[0, 0])
    with pytest.raises(DimensionError, match=r"eta has length 3, expected 2n - r_bar = 2"):
        idyn(([0.0], [0.0]), [0.0, 0.0, 0.0])
    with pytest.raises(DimensionError, match=r"y\^\(1\) has length 2, expected m = 1"):
        linearize_internal(model, idyn, [([[0.0], [0.0, 1.0]], [0.0, 0.0])])


def test_analyze_command_on_a_scene_file(tmp_path, capsys):
    """A scene given by path: the generic analysis (default coordinates at the design point)."""
    import json

    from invctl.cli import main

    path = tmp_path / "pendulum_cart.py"
    path.write_text(
        "from invctl.scenes import Scene, Tracking\nfrom invctl_scenes.cartpole import build, PARAMS\n"
        "SCENE = Scene('pendulum_cart', build, params=PARAMS, tracking=Tracking(point=[0.0, 0.0]))\n"
    )
    assert main(["analyze", str(path), "--json", "--samples", "20", "--set", "l=0.8"]) == 0
    data = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    model = cartpole.build(l=0.8)
    np.testing.assert_allclose(sorted(data["internal_eigs"]), cartpole.zero_dynamics_eigenvalues(model), rtol=1e-10)
    bad = tmp_path / "not_a_model.py"
    bad.write_text(path.read_text().replace("from invctl_scenes.cartpole import build, PARAMS",
                                            "PARAMS = {}\ndef build(**p):\n    return {}"))
    assert main(["analyze", str(bad)]) == 2
    assert "must return an invctl.model.Model" in capsys.readouterr().err


# ------------------------------------------------- reported numbers of colocated_check
def _two_masses(k, B, h, **kw):
    from invctl.model import Model, ParamSet

    P = ParamSet(["m1", "m2", "k"])
    q, v = ca.SX.sym("q", 2), ca.SX.sym("v", 2)
    return Model("two_masses", q, v, P, {"m1": 2.0, "m2": 5.0, "k": k},
                 M=ca.diag(ca.vertcat(P["m1"], P["m2"])), f=-q, B=B(P), h=h(P, q), **kw)


def test_colocated_check_reports_gamma_extremes_and_scales_round_off():
    """Two free masses (m1 = 2, m2 = 5), y = c k q and B = 0.3 k I with c = 0.1 + 0.2 (0.3 up to one ulp):
    Gamma = h' M^-1 B = 0.3 c k^2 diag(1/m1, 1/m2), so its smallest eigenvalue is 0.3 c k^2 / 5 exactly (no
    constraints: S = Gamma). h' - B^T = (c - 0.3) k I is round-off of size k 1e-16, which the colocation test
    must accept at k = 1e6 (its tolerance scales with the parameters)."""
    c, k = 0.1 + 0.2, 1e6
    model = _two_masses(k, lambda P: 0.3 * P["k"] * ca.DM.eye(2), lambda P, q: c * P["k"] * q)
    rep = colocated_check(model, samples=10)
    assert 1e-12 < rep.max_mismatch < 1e-12 * k          # the case the scaled tolerance exists for
    assert rep.colocated
    np.testing.assert_allclose(rep.gamma_min_eig, 0.3 * c * k**2 / 5.0, rtol=1e-12)
    np.testing.assert_allclose(rep.schur_min_eig, 0.3 * c * k**2 / 5.0, rtol=1e-12)
    assert rep.gamma_max_asym == 0.0 and rep.samples == 10


def test_relative_degree_error_names_the_output_without_constraints():
    """No constraints (p = l = 0): auxiliary output 0 is the output itself, and y = q2 never sees the force
    on mass 1 (diagonal M, no coupling)."""
    model = _two_masses(1.0, lambda P: ca.DM([[1], [0]]), lambda P, q: q[1], y_names=["x2"])
    with pytest.raises(RelativeDegreeError, match=r"auxiliary output 0 \(output x2\) is not influenced"):
        relative_degree(model, samples=10)


def test_velocity_output_with_numeric_mass_matrix_has_relative_degree_one():
    """y = v1 with a numeric M = diag(2, 5) and the force on mass 1: L_K y = B^T M^-1 e1 = 1/2 is a nonzero
    constant row, so r = 1 and Gamma = 1/2 everywhere."""
    from invctl.model import Model, ParamSet

    q, v = ca.SX.sym("q", 2), ca.SX.sym("v", 2)
    model = Model("numeric_masses", q, v, ParamSet([]), {}, M=ca.DM([[2.0, 0.0], [0.0, 5.0]]), f=-q,
                  B=ca.DM([[1.0], [0.0]]), h=v[0])
    rd = relative_degree(model, samples=5)
    assert rd.r_aux == (1,)
    assert rd.min_singular_value == pytest.approx(0.5, rel=1e-15)


def test_reported_worst_point_is_the_smallest_relative_singular_value():
    """y = (q1, q2 + q1^2 / 2), M = diag(2, 5), B = I: Gamma = h' M^-1 = [[1/2, 0], [q1/2, 1/5]] in closed
    form. Over the sampled points the worst condition number, its point (smallest sigma_min / sigma_max) and
    the smallest singular value are those of the closed form at the reported samples."""
    model = _two_masses(1.0, lambda P: ca.DM.eye(2), lambda P, q: ca.vertcat(q[0], q[1] + q[0] ** 2 / 2))
    rd = relative_degree(model, samples=40)
    qs = rd.diagnostics["q"]
    sv = np.array([np.linalg.svd([[0.5, 0.0], [q[0] / 2, 0.2]], compute_uv=False) for q in qs])
    k = int(np.argmin(sv[:, 1] / sv[:, 0]))
    assert np.ptp(sv[:, 1] / sv[:, 0]) > 0.1                   # the points differ
    np.testing.assert_array_equal(rd.min_singular_point[0], qs[k])
    np.testing.assert_array_equal(rd.worst_point[0], qs[k])
    assert rd.worst_condition == pytest.approx(sv[k, 0] / sv[k, 1], rel=1e-12)
    assert rd.min_singular_value == pytest.approx(sv[:, 1].min(), rel=1e-12)


def test_sect3_rejects_a_velocity_output_of_relative_degree_two():
    """y = q1 + v2 with the force on mass 1 (diagonal M): L_K y = e2^T M^-1 e1 = 0 and the damper couples v1
    into v2', so r_hat = 2 although y depends on v; the Sect. 3 coordinates need a position output."""
    from invctl.model import Model, ParamSet

    P = ParamSet(["m1", "m2", "k2", "d2"])
    q, v = ca.SX.sym("q", 2), ca.SX.sym("v", 2)
    spring = P["k2"] * (q[1] - q[0]) + P["d2"] * (v[1] - v[0])
    model = Model("msd_qv", q, v, P, {"m1": 1.0, "m2": 0.5, "k2": 3.0, "d2": 0.2},
                  M=ca.diag(ca.vertcat(P["m1"], P["m2"])), f=ca.vertcat(spring, -spring), B=ca.DM([[1], [0]]),
                  h=q[0] + v[1])
    assert relative_degree(model, samples=10).r_hat == 2
    for phi in (None, lambda m: ca.vertcat(m.q[1], m.v[0])):   # default and user coordinates
        with pytest.raises(CoordinateError, match="position output"):
            internal_dynamics(model, "sect3", phi, point=[0, 0])
