"""Plant linearizations as control.StateSpace (invctl.analysis.statespace).

References: the textbook linearization of the cart-pole; a two-mass chain whose transfer
functions are known in closed form; the knife edge's decoupled transfer matrix; the same
arm in minimal and redundant coordinates (the transfer function does not depend on
coordinates); and a nonlinear simulation of the manipulator started near an equilibrium.
AD Jacobians are exact up to round-off, so closed forms are met to 1e-12 relative; the
frequency responses of two models go through different linear solves: 1e-10.
"""
import casadi as ca
import numpy as np
import pytest
import scipy.linalg as sla
from scipy.integrate import solve_ivp

import invctl_scenes.cartpole as cartpole
import invctl_scenes.knife_edge as knife
import invctl_scenes.manipulator as manip
import invctl_scenes.two_link_arm as arm
from invctl.analysis import consistent_state, internal_dynamics, linearize_internal, plant_linearization, \
    plant_statespace
from invctl.errors import DimensionError, LinearizationError, ModelError
from invctl.model import Model, ParamSet

control = pytest.importorskip("control")


def chain(output: str = "x1", **values):
    """Two masses joined by a spring k and damper d, force on mass 1 (a linear model)."""
    vals = {"m1": 1.0, "m2": 0.5, "k": 3.0, "d": 0.4, **values}
    P = ParamSet(list(vals))
    q, v = ca.SX.sym("q", 2), ca.SX.sym("v", 2)
    spring = P["k"] * (q[1] - q[0]) + P["d"] * (v[1] - v[0])
    h = q[0] if output == "x1" else q[1]
    return Model(f"chain_{output}", q, v, P, vals, M=ca.diag(ca.vertcat(P["m1"], P["m2"])),
                 f=ca.vertcat(spring, -spring), B=ca.DM([[1], [0]]), h=h, q_names=["x1", "x2"], u_names=["F"],
                 y_names=[output]), vals


def test_cartpole_matches_the_textbook_linearization():
    model = cartpole.build(D=0.3)
    p = model.values
    J = p["I"] + p["mp"] * p["l"] ** 2
    mt, ml = p["mc"] + p["mp"], p["mp"] * p["l"]
    delta = mt * J - ml**2
    # M0 [x''; th''] = [F; mp g l th - D th'] with M0 = [[mt, ml], [ml, J]]
    A = np.zeros((4, 4))
    A[0, 2] = A[1, 3] = 1
    A[2, 1], A[2, 3] = -ml * ml * p["g"] / delta, ml * p["D"] / delta
    A[3, 1], A[3, 3] = mt * ml * p["g"] / delta, -mt * p["D"] / delta
    B = np.array([[0], [0], [J / delta], [-ml / delta]])
    sys = plant_statespace(model, [0.0, 0.0])
    assert isinstance(sys, control.StateSpace)
    assert sys.state_labels == ["x", "theta", "x_dot", "theta_dot"]
    assert sys.input_labels == ["F"] and sys.output_labels == ["x"]
    np.testing.assert_allclose(sys.A, A, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(sys.B, B, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(sys.C, [[1, 0, 0, 0]], atol=0)
    np.testing.assert_allclose(sys.D, 0, atol=0)


@pytest.mark.parametrize("output", ["x1", "x2"])
def test_two_mass_chain_transfer_function_closed_form(output):
    """x1/F = (m2 s^2 + d s + k) / den,  x2/F = (d s + k) / den,  den = s^2 (m1 m2 s^2 + (m1 + m2)(d s + k))."""
    model, p = chain(output)
    sys = plant_statespace(model, [0.2, 0.2])           # spring at rest: an equilibrium with u = 0
    num = [p["m2"], p["d"], p["k"]] if output == "x1" else [p["d"], p["k"]]
    den = np.polymul([1, 0, 0], [p["m1"] * p["m2"], (p["m1"] + p["m2"]) * p["d"], (p["m1"] + p["m2"]) * p["k"]])
    for s in (0.3j, 1.0 + 2.0j, -0.7 + 5.0j, 10j):
        assert complex(sys(s)) == pytest.approx(np.polyval(num, s) / np.polyval(den, s), rel=1e-12)
    # control.tf (ss2tf): leading numerator coefficients that vanish come out at round-off (1e-14)
    tf = control.tf(sys)
    n_tf, d_tf = np.ravel(tf.num[0][0]), np.ravel(tf.den[0][0])
    np.testing.assert_allclose(d_tf / d_tf[0], den / den[0], rtol=1e-10, atol=1e-12)
    expected = np.r_[np.zeros(n_tf.size - len(num)), np.array(num) / den[0]]
    np.testing.assert_allclose(n_tf / d_tf[0], expected, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(np.sort_complex(sys.zeros()), np.sort_complex(np.roots(num)), rtol=1e-10)


def test_knife_edge_transfer_matrix_is_diagonal_closed_form():
    """At rest with heading th0: x'' = cos(th0) F / m, th'' = (tau - Dth th') / I; the lateral
    coordinate y is neither driven (y' = tan(th0) x' only along the blade) nor seen."""
    model = knife.build()
    p = model.values
    th0 = 0.3
    lin = plant_linearization(model, [0.5, -0.2, th0])
    assert lin.nstates == 5 and set(lin.states) == {"x", "y", "theta", "x_dot", "theta_dot"}
    sys = lin.to_statespace()
    for s in (0.5j, 1 + 1j, -2 + 3j):
        G = np.array(sys(s))
        expected = np.diag([np.cos(th0) / (p["m"] * s**2), 1 / (s * (p["I"] * s + p["Dth"]))])
        np.testing.assert_allclose(G, expected, rtol=1e-12, atol=1e-14)
    # the tangent basis respects the non-holonomic constraint: J (dv) = 0 for every state direction
    Jm = model.evaluate("J", [0.5, -0.2, th0])
    np.testing.assert_allclose(Jm @ lin.basis[3:], 0, atol=1e-15)


@pytest.mark.parametrize("q1", [0.0, 0.4])
def test_two_link_arm_minimal_and_redundant_have_the_same_transfer_function(q1):
    mini, red = arm.build(), arm.build_redundant()
    q2 = arm.zero_dynamics_equilibrium(mini, q1)
    lm = plant_linearization(mini, [q1, q2])
    lr = plant_linearization(red, arm.redundant_configuration(red, q1, q2))
    assert lr.nstates == 2 * 4 - 2 * 2 == lm.nstates
    assert lm.u0 == pytest.approx(lr.u0, rel=1e-12)       # the holding torque
    sm, sr = lm.to_statespace(), lr.to_statespace()
    for s in (0.1j, 2j, 1 + 4j, -3 + 10j, 30j):
        assert complex(sr(s)) == pytest.approx(complex(sm(s)), rel=1e-10)
    np.testing.assert_allclose(np.sort_complex(sr.poles()), np.sort_complex(sm.poles()), rtol=1e-9)


def test_chosen_states_give_the_same_system():
    model = manip.build()
    q0 = manip.initial_configuration(model)
    auto = plant_linearization(model, q0)
    chosen = plant_linearization(model, q0, states=["s2", "beta", "gamma", "s2_dot", "beta_dot", "gamma_dot"])
    assert chosen.states == ("s2", "beta", "gamma", "s2_dot", "beta_dot", "gamma_dot")
    for s in (1j, 3 + 2j, 20j):
        np.testing.assert_allclose(chosen.to_statespace()(s), auto.to_statespace()(s), rtol=1e-10, atol=1e-14)
    with pytest.raises(DimensionError, match="states must be 6"):
        plant_linearization(model, q0, states=["s1", "s2"])
    with pytest.raises(DimensionError, match="not coordinates of the constraint manifold"):
        # s1 and s2 together with alpha fix beta: alpha and beta cannot both be states with s1, s2
        plant_linearization(model, q0, states=["s1", "s2", "alpha", "s1_dot", "s2_dot", "alpha_dot"])


def test_manipulator_linearization_predicts_the_nonlinear_motion():
    """Start the index-1 DAE at an equilibrium perturbed by eps = 1e-5 along the tangent space: the states
    follow exp(A t) z0 up to O(eps^2), i.e. relative O(eps) (measured 1e-6 .. 4.4e-6 over 0.15 s, where the
    unstable mode grows 40-fold); 1e-4 allowed, while a 1 % error in A would give ~1e-1."""
    model = manip.build()
    q0 = manip.initial_configuration(model)
    lin = plant_linearization(model, q0)
    n, th = model.n, model.theta_values
    rng = np.random.default_rng(2)
    z0 = 1e-5 * rng.normal(size=lin.nstates)
    dx = lin.basis @ z0
    q, v = consistent_state(model, q0 + dx[:n], dx[n:])
    z0 = (np.r_[q, v] - np.r_[q0, np.zeros(n)])[list(lin.independent)]
    acc = model.accel_and_multipliers

    def rhs(t, x):
        return np.r_[x[n:], np.array(acc(x[:n], x[n:], lin.u0, th)[0]).ravel()]

    ts = np.linspace(0, 0.15, 7)
    sol = solve_ivp(rhs, (0, ts[-1]), np.r_[q, v], t_eval=ts, rtol=1e-12, atol=1e-16, method="DOP853")
    for k, t in enumerate(ts):
        z_lin = sla.expm(lin.A * t) @ z0
        z_nl = (sol.y[:, k] - np.r_[q0, np.zeros(n)])[list(lin.independent)]
        assert np.linalg.norm(z_nl - z_lin) <= 1e-4 * np.linalg.norm(z_lin)


def test_internal_statespace_is_38():
    model = cartpole.build()
    idyn = internal_dynamics(model, point=[0.0, 0.0])
    lin = linearize_internal(model, idyn, [([[0.0], [0.0]], [0.0, 0.0])])
    sys = lin.to_statespace()
    np.testing.assert_array_equal(sys.A, lin.Q)
    np.testing.assert_array_equal(sys.B, lin.P)
    assert sys.input_labels == ["x"] and sys.state_labels == ["eta1", "eta2"]
    np.testing.assert_allclose(np.sort(sys.poles().real), cartpole.zero_dynamics_eigenvalues(model), rtol=1e-10)


def test_not_an_equilibrium_or_off_the_manifold_is_reported():
    model = cartpole.build()
    with pytest.raises(LinearizationError, match="not an equilibrium.*no input holds") as err:
        plant_linearization(model, [0.0, 0.3])          # the pole is not held by a cart force
    assert err.value.partial is not None and err.value.partial.A.shape == (4, 4)
    assert err.value.diagnostics["equilibrium_residual"] > 1
    with pytest.raises(LinearizationError, match="v0 != 0"):
        plant_linearization(model, [0.0, 0.0], v0=[0.1, 0.0])
    with pytest.raises(LinearizationError, match="u0 does not hold it"):
        plant_linearization(model, [0.0, 0.0], u0=[1.0])
    man = manip.build()
    q = manip.initial_configuration(man)
    q[2] += 0.01
    with pytest.raises(ModelError, match="not on the constraint manifold.*consistent_state"):
        plant_linearization(man, q)
    with pytest.raises(DimensionError, match="q0 must be 5 finite numbers"):
        plant_linearization(man, [0.0, 1.0])


def test_holding_input_residual_is_the_unheld_torque_either_way():
    """Cart-pole at rest with the pole tilted by -+0.3: the cart force cannot hold the pole; what is left is
    the gravity torque mp g l sin(0.3) (closed form), whatever its sign."""
    from invctl.analysis.statespace import holding_input

    model = cartpole.build()
    p = model.values
    for th in (0.3, -0.3):
        u, lam, mu, res = holding_input(model, [0.0, th])
        assert res == pytest.approx(p["mp"] * p["g"] * p["l"] * np.sin(0.3), rel=1e-12)
        assert u == pytest.approx([0.0], abs=1e-15)


def test_off_the_manifold_on_either_side_is_reported():
    """The manipulator moved off its two loop constraints along -+ G^+ (1, 1) (so both residuals are about
    -+0.01): negative residuals are off the manifold as much as positive ones."""
    man = manip.build()
    q0 = manip.initial_configuration(man)
    g = ca.Function("g", [man.q, man.theta], [man.g])
    G = man.evaluate("G", q0).reshape(man.ell, man.n)
    for sign in (1.0, -1.0):
        q = q0 + sign * 0.01 * np.linalg.pinv(G) @ np.ones(man.ell)
        phi = np.array(g(q, man.theta_values)).ravel()
        assert np.all(sign * phi > 0.005)
        with pytest.raises(ModelError, match="not on the constraint manifold"):
            plant_linearization(man, q)


def test_unknown_state_names_are_rejected():
    model = manip.build()
    q0 = manip.initial_configuration(model)
    with pytest.raises(DimensionError, match="states must be 6 = 2n - 2l - p distinct names"):
        plant_linearization(model, q0, states=["s2", "beta", "gamma", "s2_dot", "beta_dot", "bogus"])
