"""The LCP solvers' documented acceptance rules, checked at their boundaries.

Each test puts a problem exactly on (or a hair either side of) the rule a user reads in the docstrings
and docs/clearances.md, so a changed scale, inequality or budget changes an accepted solution, a flag or a
reported count.
"""
import casadi as ca
import numpy as np
import pytest

from invctl.contact.lcp import _lemke, _residual_ok, default_max_pivots, lcp_sx, lemke_sx, solve_lcp
from invctl.errors import ContactError

# 3 contacts, symmetric positive definite A, mixed-sign b whose largest entry in magnitude is negative; the
# solution has all three contacts active and its residual is round-off on a negative w (checked below)
A3 = np.array([[2.3125, 0.4375, -0.125], [0.4375, 1.375, -0.5625], [-0.125, -0.5625, 2.3125]])
B3 = np.array([-0.521, -0.652, 0.21])


def _scale(A, b, z):
    """The documented problem scale ``1 + max|b| + max|A| max|z|``."""
    return 1.0 + np.abs(b).max() + np.abs(A).max() * np.abs(z).max()


@pytest.mark.parametrize("method", ["enumeration", "lemke"])
def test_solve_lcp_accepts_exactly_the_documented_relative_residual(method):
    sol = solve_lcp(A3, B3, method=method)
    np.testing.assert_allclose(sol.z, np.linalg.solve(A3, -B3), rtol=1e-13)   # all active: z = -A^-1 b
    w = A3 @ sol.z + B3
    m = np.minimum(sol.z, w)
    assert sol.residual == np.max(np.abs(m)) > 0 and w[np.argmax(np.abs(m))] < 0   # round-off, on a w < 0
    ratio = sol.residual / _scale(A3, B3, sol.z)
    again = solve_lcp(A3, B3, method=method, tol=ratio * (1 + 1e-3))
    np.testing.assert_array_equal(again.z, sol.z)
    with pytest.raises(ContactError):
        solve_lcp(A3, B3, method=method, tol=ratio * (1 - 1e-3))


def test_compiled_residual_flag_is_the_documented_relative_test():
    """``ok`` of the compiled solvers: max |min(z, A z + b)| <= res_tol (1 + max|b| + max|A| max|z|), here
    for a z off the solution by 1e-3 (a residual far above round-off), a hair either side of the bound."""
    z = np.linalg.solve(A3, -B3) + np.array([1e-3, -2e-3, 5e-4])
    res = np.max(np.abs(np.minimum(z, A3 @ z + B3)))
    bound = res / _scale(A3, B3, z)
    for factor, expected in ((1 + 1e-6, 1.0), (1 - 1e-6, 0.0)):
        ok, r = _residual_ok(ca.DM(A3), ca.DM(B3), ca.DM(z), bound * factor)
        assert float(ca.evalf(ok)) == expected
        assert float(ca.evalf(r)) == pytest.approx(res, rel=1e-14)


def test_lemke_default_budget_is_m_plus_4_plus_m_over_2():
    """Murty's upper-triangular LCP (A = I + 2 strict upper ones, b = -(5, 4, 3, 2, 1)) needs 14 Lemke pivots
    (counted by the numpy Lemke); with the default budget 5 + 4 + 2 = 11 (docs/clearances.md) the compiled
    Lemke stops there and flags it, with 14 it finds the solution (1, 0, 1, 0, 1)."""
    m = 5
    A = np.eye(m) + 2 * np.triu(np.ones((m, m)), 1)
    b = -np.arange(m, 0, -1.0)
    assert _lemke(A.copy(), b.copy(), 13) is None and _lemke(A.copy(), b.copy(), 14) is not None
    assert default_max_pivots(m) == 11
    z, ok, pivots = (np.array(ca.evalf(x)).ravel() for x in lemke_sx(ca.DM(A), ca.DM(b)))
    assert ok[0] == 0 and pivots[0] == 11
    z, ok, pivots = (np.array(ca.evalf(x)).ravel() for x in lemke_sx(ca.DM(A), ca.DM(b), max_pivots=14))
    assert ok[0] == 1 and pivots[0] == 14
    np.testing.assert_allclose(z, [1, 0, 1, 0, 1], atol=1e-12)


def test_compiled_enumeration_accepts_w_on_the_tolerance():
    """A = [[-1]] (not a P-matrix: z = 0 is the only candidate) and b = -tol (1 + |b|) exactly: the
    documented rule (A z + b) >= -tol (1 + |b|) is inclusive, so z = 0 is accepted and flagged; a hair more
    negative is not."""
    tol = 1e-13
    t = tol * (1 + tol * (1 + tol))
    assert tol * (1.0 + t) == t                     # b sits exactly on the bound
    for b, expected in ((-t, 1.0), (-np.nextafter(t, 1.0), 0.0)):
        z, ok = lcp_sx(ca.DM([[-1.0]]), ca.DM([b]), method="enumeration", tol=tol, with_flag=True)
        assert float(ca.evalf(ok)) == expected and float(ca.evalf(z)) == 0.0


def test_lemke_first_pivot_breaks_ties_lexicographically():
    """b = (0, -2, -2) ties rows 2 and 3. Worked by hand with w = A z + b + z0 e: the lexicographic rule
    (smallest (b_i, e_i)) lets w3 leave as z0 enters (z0 = 2, w2 = 0); z3 enters, z0 = 2 - 2 z3 leaves at
    z3 = 1 while w2 = 2 z3 - 2 + z0 stays 0 and w1 = 2 + z3: 2 pivots, z = (0, 0, 1), w = (3, 0, 0)."""
    A = np.array([[3.0, 2.0, 3.0], [-3.0, 1.0, 2.0], [3.0, -2.0, 2.0]])
    b = np.array([0.0, -2.0, -2.0])
    z, ok, pivots = (np.array(ca.evalf(x)).ravel() for x in lemke_sx(ca.DM(A), ca.DM(b)))
    assert ok[0] == 1 and pivots[0] == 2
    np.testing.assert_allclose(z, [0, 0, 1], atol=1e-14)


# not a P-matrix (det < 0): z = (0.9/7, 0) (round-off residual r0 > 0 on w1), z = (0, 0.1) (exact) and an
# interior point all solve it; enumeration visits active sets by size, {1} before {2}
A_NP = np.array([[7.0, 10.0], [8.0, 9.0]])
B_NP = np.array([-0.9, -0.9])
Z_FIRST, Z_EXACT = np.array([0.9 / 7.0, 0.0]), np.array([0.0, 0.1])


def test_enumeration_returns_the_first_solution_within_the_inclusive_tolerance():
    """With tol scale = r0 exactly, the first active set's solution is within the tolerance (<=) and returned."""
    r0 = np.max(np.abs(np.minimum(Z_FIRST, A_NP @ Z_FIRST + B_NP)))
    assert r0 > 0 and np.max(np.abs(np.minimum(Z_EXACT, A_NP @ Z_EXACT + B_NP))) == 0.0
    s = _scale(A_NP, B_NP, Z_FIRST)
    tol = r0 / s
    while tol * s != r0:                       # the tolerance that puts r0 exactly on the bound
        tol = np.nextafter(tol, 1.0 if tol * s < r0 else 0.0)
    sol = solve_lcp(A_NP, B_NP, method="enumeration", tol=tol, check_unique=False)
    np.testing.assert_array_equal(sol.z, Z_FIRST)
    assert sol.residual == r0


def test_enumeration_keeps_the_smallest_residual_when_the_first_is_outside_tol():
    """With tol below r0 / scale the first solution is not accepted; the exact one (residual 0) is."""
    r0 = np.max(np.abs(np.minimum(Z_FIRST, A_NP @ Z_FIRST + B_NP)))
    sol = solve_lcp(A_NP, B_NP, method="enumeration", tol=0.5 * r0 / _scale(A_NP, B_NP, Z_FIRST),
                    check_unique=False)
    np.testing.assert_array_equal(sol.z, Z_EXACT)
    assert sol.residual == 0.0


def test_lcp_sx_methods_are_the_named_ones():
    """Murty's LCP (14 Lemke pivots): method='lemke' is Lemke with its default budget of 11 pivots, so it flags
    the solve; method='pivoting' (block principal pivoting) solves it, z = (1, 0, 1, 0, 1)."""
    m = 5
    A = ca.DM(np.eye(m) + 2 * np.triu(np.ones((m, m)), 1))
    b = ca.DM(-np.arange(m, 0, -1.0))
    _, ok = lcp_sx(A, b, method="lemke", with_flag=True)
    assert float(ca.evalf(ok)) == 0.0
    z, ok = lcp_sx(A, b, method="pivoting", with_flag=True)
    assert float(ca.evalf(ok)) == 1.0
    np.testing.assert_allclose(np.array(ca.evalf(z)).ravel(), [1, 0, 1, 0, 1], atol=1e-12)


def test_lcp_sx_lemke_keeps_its_pivot_budget_below_max_enum():
    """m = 3 <= max_enum: method='lemke' is still Lemke (Murty's LCP of size 3 needs 6 pivots, more than
    max_iter = 3), not the enumeration 'auto' would pick, which solves it: z = (1, 0, 1)."""
    m = 3
    A = ca.DM(np.eye(m) + 2 * np.triu(np.ones((m, m)), 1))
    b = ca.DM(-np.arange(m, 0, -1.0))
    _, ok = lcp_sx(A, b, method="lemke", max_iter=3, with_flag=True)
    assert float(ca.evalf(ok)) == 0.0
    z, ok = lcp_sx(A, b, with_flag=True)
    assert float(ca.evalf(ok)) == 1.0
    np.testing.assert_allclose(np.array(ca.evalf(z)).ravel(), [1, 0, 1], atol=1e-12)


def test_lemke_meeting_a_singular_basis_is_a_contact_error():
    """A non-P-matrix LCP on which Lemke's pivoting reaches a singular basis: ContactError (no solution
    found), not numpy's LinAlgError; enumeration of all 16 active sets finds none either."""
    A = np.array([[0.0, -0.01, -30.0, 1000.0], [0.02, -0.003, 30000.0, -0.002],
                  [-1000.0, 0.0, 0.0002, -20000.0], [-20000.0, -3.0, -0.001, -20000.0]])
    b = np.array([-1.0, -1.0, -2.0, -1.0])
    with pytest.raises(ContactError, match=r"solve_lcp \(lemke\): no solution found"):
        solve_lcp(A, b, method="lemke")
    with pytest.raises(ContactError, match=r"solve_lcp \(enumeration\): no solution found"):
        solve_lcp(A, b, method="auto")
