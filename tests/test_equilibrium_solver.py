"""EquilibriumSolver's damped Gauss-Newton, single and batched, where the full step diverges.

One mass on a spring (f = -k q, B = 1) with output y = atan(q): the equilibrium at y is q = tan(y) held by
u = k tan(y) (closed forms). Newton on atan(q) - y overshoots from far guesses (it diverges undamped beyond
|q - tan y| of about 1.39), so only the sufficient-decrease line search brings it in.
"""
import casadi as ca
import numpy as np
import pytest

from invctl.analysis.equilibrium import EquilibriumSolver
from invctl.errors import ReferenceSignalError
from invctl.model import Model, ParamSet

K = 3.0


@pytest.fixture(scope="module")
def solver():
    P = ParamSet(["k"])
    q, v = ca.SX.sym("q", 1), ca.SX.sym("v", 1)
    model = Model("atan_spring", q, v, P, {"k": K}, M=ca.SX.eye(1), f=-P["k"] * q, B=ca.DM.eye(1),
                  h=ca.atan(q))
    return EquilibriumSolver(model)


Y = np.array([0.0, 0.3, -0.5])
GUESS = np.tan(Y) + np.array([2.0, -3.0, 2.5])   # all beyond Newton's undamped basin


def test_solve_converges_from_far_guesses(solver):
    for y, g in zip(Y, GUESS):
        X, res = solver.solve([y], guess_q=[g])
        assert res < 1e-12
        np.testing.assert_allclose(X, [np.tan(y), 0.0, K * np.tan(y)], rtol=1e-12, atol=1e-12)


def test_solve_many_converges_from_far_guesses(solver):
    W0 = np.vstack([GUESS, np.zeros(3)])
    W, res = solver.solve_many(Y[None, :], W0)
    assert np.all(res < 1e-12)
    np.testing.assert_allclose(W, [np.tan(Y), K * np.tan(Y)], rtol=1e-12, atol=1e-12)


def test_failure_reports_the_residual_after_the_last_step(solver):
    """One Gauss-Newton step on atan(q) - y (the spring row is linear and exact after a full step): the error
    names the residual at the iterate the step reached, computed here by hand, not the one before the step."""
    y, q0 = 0.3, np.tan(0.3) + 0.5
    q1 = q0 - (np.arctan(q0) - y) * (1 + q0**2)      # the full Newton step
    res0, res1 = abs(np.arctan(q0) - y), abs(np.arctan(q1) - y)
    assert 1e-6 < res1 < (1 - 1e-4) * res0           # the full step is accepted and does not converge
    with pytest.raises(ReferenceSignalError, match=f"residual {res1:.3g} after 1 Gauss-Newton steps") as err:
        solver.solve([y], guess_q=[q0], max_iter=1)
    assert err.value.diagnostics["residual"] == pytest.approx(res1, rel=1e-12)
    # the fourth step reaches the accepted residual (1e3 tol): no error (the residual before it is ~1e-6)
    X, res = solver.solve([y], guess_q=[q0], max_iter=4)
    assert res < 1e-9 and X[0] == pytest.approx(np.tan(y), rel=1e-10)
