"""Exact LCPs inside the compiled step: block principal pivoting and lexicographic Lemke in CasADi SX
against the numpy enumeration and Lemke solvers; convergence flags; the compiled Moreau-Jean step
against the same step with numpy LCPs; unconverged steps recomputed exactly or stopped."""
import importlib.util
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from invctl.contact.lcp import (default_max_pivots, default_pivot_iters, lcp_residual, lcp_sx, lemke_sx, pivot_sx,
                                solve_lcp)
from invctl.errors import ContactError
from invctl.simulate.timestepping import MoreauJean, c_compiler

ROOT = Path(__file__).resolve().parents[1]
_FN = {}


def _bench():
    spec = importlib.util.spec_from_file_location("bench_contacts", ROOT / "benchmarks" / "bench_contacts.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _solver(method, m, **kw):
    """``(A, b) -> (z, ok, iterations)`` as a CasADi Function (cached)."""
    key = (method, m, tuple(sorted(kw.items())))
    if key not in _FN:
        A, b = ca.SX.sym("A", m, m), ca.SX.sym("b", m)
        if method == "pivoting":
            out = pivot_sx(A, b, **kw)
        elif method == "lemke":
            out = lemke_sx(A, b, **kw)
        else:
            z, ok = lcp_sx(A, b, method=method, with_flag=True, **kw)
            out = (z, ok, ca.SX(0))
        _FN[key] = ca.Function(f"lcp_{method}_{m}", [A, b], list(out))
    return _FN[key]


def _batch(method, As, B, **kw):
    m = B.shape[0]
    f = _solver(method, m, **kw).map(B.shape[1])
    Z, OK, IT = f(np.hstack(As), B)
    return np.array(Z).reshape(m, -1), np.array(OK).ravel() > 0.5, np.array(IT).ravel()


def _p_matrices(rng, m, count):
    """Random P-matrices: half symmetric positive definite ``R R^T + 0.05 I``, half non-symmetric
    (that plus a skew part; the symmetric part stays positive definite, hence P)."""
    out = []
    for k in range(count):
        R = rng.normal(size=(m, m))
        A = R @ R.T + 0.05 * np.eye(m)
        if k % 2:
            S = rng.normal(size=(m, m))
            A = A + 0.5 * (S - S.T)
        out.append(A)
    return out


def _close(z, ref, A, b):
    """Agreement with the unique solution: |z - z_ref| <= 1e-9 (1 + |z_ref|).  Both are exact up to
    round-off of LU solves on matrices with condition number < 1e6 (checked), i.e. <~ 1e-10; the
    numpy reference is itself accepted at residual 1e-10 x scale."""
    assert np.linalg.cond(A) < 1e6
    return np.max(np.abs(z - ref)) <= 1e-9 * (1 + np.max(np.abs(ref))) and lcp_residual(A, b, z) <= 1e-9 * (
        1 + np.abs(b).max() + np.abs(A).max() * np.abs(z).max())


@pytest.mark.parametrize("method", ["enumeration", "pivoting", "lemke"])
@pytest.mark.parametrize("m", [1, 2, 3, 4, 5, 6, 7, 8])
def test_random_p_matrix_lcps_match_enumeration(method, m):
    """300 random P-matrix LCPs per size (b with mixed signs, and b < 0: every entry of the
    solution positive), each solved with the default budget: every solution flagged ok equals the
    numpy enumeration's; flagged failures (budget exhausted) are under 0.5 %."""
    if method == "enumeration" and m > 6:
        pytest.skip("2^m candidates: enumeration is for tiny sizes")
    rng = np.random.default_rng(100 + m)
    As = _p_matrices(rng, m, 300)
    B = rng.normal(size=(m, 300))
    B[:, ::3] = -np.abs(B[:, ::3])
    Z, OK, _ = _batch(method, As, B)
    assert OK.mean() >= 0.995
    for k in np.flatnonzero(OK):
        ref = solve_lcp(As[k], B[:, k], method="enumeration").z
        assert _close(Z[:, k], ref, As[k], B[:, k]), (k, Z[:, k], ref)


@pytest.mark.parametrize("method,m", [("pivoting", 10), ("pivoting", 12), ("pivoting", 16), ("lemke", 10),
                                      ("lemke", 12)])
def test_larger_sizes_match_numpy_lemke(method, m):
    rng = np.random.default_rng(200 + m)
    As = _p_matrices(rng, m, 100)
    B = rng.normal(size=(m, 100))
    B[:, ::2] = -np.abs(B[:, ::2])
    Z, OK, _ = _batch(method, As, B)
    assert OK.mean() >= 0.98
    for k in np.flatnonzero(OK):
        assert _close(Z[:, k], solve_lcp(As[k], B[:, k], method="lemke").z, As[k], B[:, k])


def _degenerate_cases():
    """P-matrix LCPs with zero entries of b, ties in every ratio test, and the masked
    (identity rows, zero b) form used by the time step."""
    rng = np.random.default_rng(7)
    cases = []
    for m in (2, 3, 5, 8):
        J = np.ones((m, m))
        cases += [(np.eye(m), -np.ones(m)),  # all ratios tie
                  (2 * np.eye(m) + J, -np.ones(m)),  # symmetric ties, coupled
                  (2 * np.eye(m) + J, np.zeros(m)),  # b = 0: z = 0 is the (degenerate) solution
                  (2 * np.eye(m) + J, np.r_[-1.0, np.zeros(m - 1)]),  # zero entries of b
                  (np.eye(m) + np.triu(J, 1), -np.ones(m))]  # non-symmetric, triangular
        A = _p_matrices(rng, m, 1)[0]
        b = rng.normal(size=m)
        b[::2] = 0.0
        cases.append((A, b))
        z = np.maximum(rng.normal(size=m), 0)  # a solution with w_i = z_i = 0 somewhere
        b = -A @ z
        cases.append((A, b))
        act = np.arange(m) % 2 == 0  # masked contacts, as in the Moreau-Jean step
        Dm = np.where(np.outer(act, act), A, 0.0) + np.diag(~act)
        cases.append((Dm, np.where(act, rng.normal(size=m), 0.0)))
    return cases


@pytest.mark.parametrize("method", ["enumeration", "pivoting", "lemke"])
def test_degenerate_lcps(method):
    for A, b in _degenerate_cases():
        m = b.size
        if method == "enumeration" and m > 6:
            continue
        z, ok, _ = (np.array(a).ravel() for a in _solver(method, m)(A, b))
        assert ok[0] > 0.5, (A, b)
        assert _close(z, solve_lcp(A, b, method="enumeration").z, A, b), (A, b, z)


@pytest.mark.parametrize("method", ["enumeration", "pivoting", "lemke"])
def test_flag_never_accepts_a_non_solution(method):
    """General random matrices (mostly not P: some LCPs have no solution, some several): whenever
    the flag says ok, z solves the LCP (numpy residual <= 1e-8 x scale); A = -I, b = -1 (no
    solution) is flagged."""
    rng = np.random.default_rng(5)
    for m in (2, 3, 4, 6):
        if method == "enumeration" and m > 4:
            continue
        As = [rng.normal(size=(m, m)) for _ in range(200)]
        B = rng.normal(size=(m, 200))
        Z, OK, _ = _batch(method, As, B)
        for k in np.flatnonzero(OK):
            z = Z[:, k]
            assert z.min() >= 0
            scale = 1 + np.abs(B[:, k]).max() + np.abs(As[k]).max() * np.abs(z).max()
            assert lcp_residual(As[k], B[:, k], z) <= 1e-8 * scale
        z, ok, _ = _solver(method, m)(-np.eye(m), -np.ones(m))
        assert float(ok) == 0.0


def test_exhausted_budget_is_flagged():
    """A = 2 I + 1 1^T, b = -(1, 2, 3, 4): the solution z = (0, 0.1, 0.6, 1.1) has a zero, so the first
    guess F = {b < 0} (z_1 < 0 there) and Lemke's first pivot are not solutions; a budget of one
    iteration / pivot is flagged, the default budget solves it."""
    A = 2 * np.eye(4) + np.ones((4, 4))
    b = -np.arange(1.0, 5.0)
    ref = solve_lcp(A, b).z
    assert ref.min() == 0 and ref.max() > 0
    for method, kw in (("lemke", {"max_pivots": 1}), ("pivoting", {"max_iter": 1})):
        z, ok, it = _solver(method, 4, **kw)(A, b)
        assert float(ok) == 0.0 and float(it) == 1.0
        z, ok, it = _solver(method, 4)(A, b)
        assert float(ok) == 1.0 and float(it) >= 2
        np.testing.assert_allclose(np.array(z).ravel(), ref, atol=1e-14)
    with pytest.raises(ContactError):
        lcp_sx(ca.SX.sym("A", 2, 2), ca.SX.sym("b", 2), method="magic")


def test_budgets_cover_random_problems():
    """The default budgets, measured: over 1000 random P-matrix LCPs per size (half with b < 0) at
    least 99.9 % of the block principal pivoting runs need at most default_pivot_iters(m) iterations
    and 99.8 % of the Lemke runs (500 draws, sizes up to 10) at most default_max_pivots(m) pivots."""
    rng = np.random.default_rng(11)
    for m in range(1, 17):
        As = _p_matrices(rng, m, 1000)
        B = rng.normal(size=(m, 1000))
        B[:, ::2] = -np.abs(B[:, ::2])
        _, OK, IT = _batch("pivoting", As, B, max_iter=3 * m + 3)
        assert OK.all() or OK.mean() > 0.999
        assert np.mean(IT[OK] <= default_pivot_iters(m)) >= 0.999, (m, np.percentile(IT, 99.9))
        if m <= 10:
            _, OK, PV = _batch("lemke", As[:500], B[:, :500], max_pivots=3 * m + 3)
            assert OK.all() and np.mean(PV <= default_max_pivots(m)) >= 0.998, (m, PV.max())


# ----------------------------------------------------------- the compiled step
@pytest.fixture(scope="module")
def chain6():
    return _bench().chain(6)


def _piled_up(n=6, cl=0.01):
    """Every gap 5 % of the clearance, every block moving to the wall at 0.5 m/s: the blocks pile
    up (up to 5 contacts loaded in one step) and bounce back."""
    return -0.95 * cl * np.arange(1, n + 1), -0.5 * np.ones(n)


@pytest.mark.parametrize("lcp", ["auto", "lemke", "enumeration"])
def test_compiled_step_matches_numpy_lcp_step(chain6, lcp):
    """The forced 6-block chain (wall and 5 neighbour gaps, simultaneous and persistent contacts):
    500 compiled steps (VM) equal 500 steps with the LCPs solved by numpy Lemke, to 1e-12 (the
    same arithmetic except the LCP, which both solve exactly)."""
    model, law, U = chain6
    mj = MoreauJean(model, law, potential=U, backend="vm", lcp=lcp)
    q0, v0 = _piled_up()
    tr = mj.run(q0, v0, 0.5, 1e-3)
    Q, V = mj.reference_run(q0, v0, 500, 1e-3, method="lemke")
    assert tr.stats["n_impacts"] >= 10 and np.any(np.sum(tr.P > 0, axis=0) >= 4)  # simultaneous contacts
    assert tr.stats["lcp_recomputed"] == 0
    np.testing.assert_allclose(tr.q, Q, atol=1e-12)
    np.testing.assert_allclose(tr.v, V, atol=1e-10)
    assert tr.stats["lcp_res_max"] <= 1e-12


def test_unconverged_steps_are_recomputed_or_stop_the_run(chain6):
    """With a budget of one pivoting iteration many steps are flagged: by default each is
    recomputed with the exact numpy LCP (same trajectory as the reference); with
    on_lcp_failure='raise' the run stops with a ContactError holding the trajectory so far."""
    model, law, U = chain6
    mj = MoreauJean(model, law, potential=U, backend="vm", lcp="pivoting", lcp_iters=1, chunk=128)
    q0, v0 = _piled_up()
    tr = mj.run(q0, v0, 0.5, 1e-3, record_every=5)
    Q, _ = mj.reference_run(q0, v0, 500, 1e-3, method="lemke")
    assert tr.stats["lcp_recomputed"] >= 5
    np.testing.assert_allclose(tr.q, Q[:, tr.stats["step_index"]], atol=1e-12)
    with pytest.raises(ContactError, match="did not converge") as ei:
        mj.run(q0, v0, 0.5, 1e-3, on_lcp_failure="raise")
    part, k = ei.value.partial, ei.value.diagnostics["step"]
    assert part.stats["steps"] == k and part.q.shape[1] == k + 1
    np.testing.assert_allclose(part.q, Q[:, :k + 1], atol=1e-12)


def test_position_projection_with_many_contacts(chain6):
    """Projection LCPs (6 contacts, pivoting): every gap >= -1e-10 and the same trajectory as the
    numpy projection."""
    model, law, U = chain6
    mj = MoreauJean(model, law, potential=U, backend="vm", projection=True, projection_iters=2)
    q0, v0 = _piled_up()
    tr = mj.run(q0, v0, 0.3, 2e-3)
    Q, _ = mj.reference_run(q0, v0, 150, 2e-3, method="lemke")
    assert tr.max_gap_violation <= 1e-10 and tr.stats["n_impacts"] > 0
    np.testing.assert_allclose(tr.q, Q, atol=1e-12)


@pytest.mark.skipif(c_compiler() is None, reason="no C compiler on this machine")
def test_generated_c_with_pivoting_equals_vm():
    model, law, U = _bench().chain(5)
    rng = np.random.default_rng(5)
    q0, v0 = rng.uniform(-0.004, 0.004, 5), rng.uniform(-0.3, 0.3, 5)
    a = MoreauJean(model, law, potential=U, backend="vm").run(q0, v0, 1.0, 1e-3, record="events")
    b = MoreauJean(model, law, potential=U, backend="c").run(q0, v0, 1.0, 1e-3, record="events")
    assert b.stats["backend"] == "c" and a.stats["n_impacts"] == b.stats["n_impacts"] > 10
    np.testing.assert_allclose(a.q, b.q, atol=1e-12)
