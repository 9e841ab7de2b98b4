"""The multibody model: construction, validation, Lagrangian builder, parameters."""
import casadi as ca
import numpy as np
import pytest

from invctl.errors import DimensionError, ModelError, ParameterError
from invctl.model import Model, ParamSet, parse_assignments


def M49(q, p):
    """003 (49), typed from the paper, as an independent reference."""
    s1, s2, a, b, g = q
    m1, m2, m3, L1, L2, L3, I1, I2, I3, X3 = (p[k] for k in "m1 m2 m3 L1 L2 L3 I1 I2 I3 X3".split())
    return np.array([
        [m1, 0, L1 * m1 * np.cos(a) / 2, 0, 0],
        [0, m2 + m3, 0, -X3 * m3 * np.sin(b + g) - L2 * m3 * np.sin(b) / 2, -X3 * m3 * np.sin(b + g)],
        [L1 * m1 * np.cos(a) / 2, 0, m1 * L1**2 / 4 + I1, 0, 0],
        [0, -X3 * m3 * np.sin(b + g) - L2 * m3 * np.sin(b) / 2, 0,
         m3 * L2**2 / 4 + m3 * np.cos(g) * L2 * X3 + m3 * X3**2 + I2 + I3,
         m3 * X3**2 + L2 * m3 * np.cos(g) * X3 / 2 + I3],
        [0, -X3 * m3 * np.sin(b + g), 0, m3 * X3**2 + L2 * m3 * np.cos(g) * X3 / 2 + I3, m3 * X3**2 + I3],
    ])


def f49(q, v, p):
    s1, s2, a, b, g = q
    _, _, ad, bd, gd = v
    m1, m3, L1, L2, X3, c, D = (p[k] for k in "m1 m3 L1 L2 X3 c D".split())
    return np.array([
        0.5 * L1 * ad**2 * m1 * np.sin(a),
        0.5 * m3 * (2 * X3 * bd**2 * np.cos(b + g) + 2 * X3 * gd**2 * np.cos(b + g)
                    + L2 * bd**2 * np.cos(b) + 4 * X3 * bd * gd * np.cos(b + g)),
        0.0,
        0.5 * L2 * X3 * gd * m3 * np.sin(g) * (2 * bd + gd),
        -0.5 * L2 * X3 * m3 * np.sin(g) * bd**2 - D * gd - c * g,
    ])


def test_manipulator_lagrangian_matches_printed_49(manipulator):
    rng = np.random.default_rng(1)
    for _ in range(20):
        q, v = rng.uniform(-2, 2, 5), rng.uniform(-3, 3, 5)
        # tolerance: both are exact formulas; only round-off separates them
        np.testing.assert_allclose(manipulator.evaluate("M", q), M49(q, manipulator.values), atol=1e-13)
        np.testing.assert_allclose(manipulator.evaluate("f", q, v).ravel(), f49(q, v, manipulator.values), atol=1e-12)


def test_derived_parameters_follow_base(manipulator):
    m2 = manipulator.with_params(L3=0.6)
    assert m2.values["X3"] == pytest.approx(0.3)
    assert m2.values["I3"] == pytest.approx(manipulator.values["m3"] * 0.36 / 12)     # I3 = m3 L3^2 / 12
    m3 = manipulator.with_params(L3=0.6, X3=0.2)
    assert m3.values["X3"] == 0.2
    assert manipulator.values["X3"] == 0.25  # original untouched
    assert manipulator.scaled(m3=1.2).values["m3"] == pytest.approx(1.2 * manipulator.values["m3"])


def test_unknown_parameter_is_named(manipulator):
    with pytest.raises(ParameterError, match="m4"):
        manipulator.with_params(m4=1.0)


def test_parse_assignments_never_evals():
    assert parse_assignments(["m3=0.6", "c = 2e1"]) == {"m3": 0.6, "c": 20.0}
    with pytest.raises(ParameterError, match="not a number"):
        parse_assignments(["m3=__import__('os')"])
    with pytest.raises(ParameterError, match="name=value"):
        parse_assignments(["m3"])


def _pendulum(M=None, G=None, B=None, g=None):
    P = ParamSet(["m"])
    q, v = ca.SX.sym("q", 2), ca.SX.sym("v", 2)
    return Model("bad", q, v, P, {"m": 1.0},
                 M=M if M is not None else P["m"] * ca.SX.eye(2), f=ca.SX.zeros(2),
                 B=B if B is not None else ca.DM([[1], [0]]), h=q[0], g=g, G=G)


def test_dimension_errors_are_collected():
    with pytest.raises(DimensionError) as err:
        _pendulum(M=ca.SX.eye(3), B=ca.DM.ones(3, 1))
    assert "M has shape (3, 3)" in str(err.value) and "B has 3 rows" in str(err.value)


def test_wrong_G_is_reported():
    q = ca.SX.sym("q", 2)
    with pytest.raises(ModelError, match="G != g'"):
        P = ParamSet(["m"])
        v = ca.SX.sym("v", 2)
        Model("bad", q, v, P, {"m": 1.0}, M=ca.SX.eye(2), f=ca.SX.zeros(2), B=ca.DM([[1], [0]]),
              h=q[0], g=q[0] ** 2 + q[1], G=ca.horzcat(q[0], 1))


def test_indefinite_mass_matrix_is_reported():
    with pytest.raises(ModelError, match="not positive definite"):
        _pendulum(M=ca.diag(ca.SX([1, -1])))


def test_too_many_constraints_and_inputs_counts_non_holonomic_ones():
    """n = 2 with one non-holonomic constraint (p = 1) and two inputs/outputs: l + p + m = 3 > n."""
    P = ParamSet(["m"])
    q, v = ca.SX.sym("q", 2), ca.SX.sym("v", 2)
    with pytest.raises((DimensionError, ModelError), match=r"l \+ p \+ m = 0 \+ 1 \+ 2 > n = 2"):
        Model("overdetermined", q, v, P, {"m": 1.0}, M=P["m"] * ca.SX.eye(2), f=ca.SX.zeros(2), B=ca.DM.eye(2),
              h=q, J=ca.horzcat(ca.SX(1), ca.SX(1)), j=ca.SX.zeros(1))


def test_mass_matrix_symmetry_is_relative_to_its_largest_entry():
    """M = [[1, -1e6 + 1e-5], [-1e6, 1]]: the asymmetry 1e-5 is round-off relative to max |M| = 1e6, so what
    is reported is that M is indefinite (eigenvalues 1 -+ 1e6)."""
    with pytest.raises(ModelError, match="not positive definite"):
        _pendulum(M=ca.SX(ca.DM([[1.0, -1e6 + 1e-5], [-1e6, 1.0]])))
