"""Conewise stability of the switched motion/force error system (002 Sect. 3, App. B).

The return-map factor Lambda is computed three independent ways: the printed
closed forms (14)-(16), the App. B formulas (33)-(35) in numerically computed
Jordan coordinates, and a Runge-Kutta integration (rtol 1e-12) of the worst-case
system with the Lemma 1 switching rule ``argmax z^T A_i z``.  They must agree to
1e-6 relative (the integration is accurate to ~1e-10, so 1e-6 leaves margin while
still catching any wrong branch, sign or angle, which change Lambda by O(1)).
"""
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from scipy.linalg import expm

from invctl.errors import ParameterError, StabilityError
from invctl.stability.conewise import (SwitchedErrorSystem, analyze, expm2, iss_bound, lambda_appendix_b,
                                       lambda_closed_form, lambda_numerical, perturbations,
                                       theorem1_conditions, visible_eigenvectors, worst_case_flow)

PAPER = dict(M=1.0, b=0.0, kp=4000.0, kd=80.0, ke=1e6, be=10.0, kf=1.0)


def _agree(s, rtol=1e-6):
    l1, l2, lam = lambda_closed_form(s)
    rot = lambda_numerical(s)
    lam_b = lambda_appendix_b(s)[2]
    assert not rot.visible
    assert lam == pytest.approx(rot.Lambda, rel=rtol)
    assert lam_b == pytest.approx(lam, rel=1e-9)
    # per-sector factors: the rotation visits S2, S1, S2, S1 starting on (1, 0)
    f = dict(zip(rot.sector_modes, rot.sector_factors))
    assert f[1] == pytest.approx(l1, rel=rtol) and f[2] == pytest.approx(l2, rel=rtol)
    return lam


# --- the parameter sets of the paper ----------------------------------------------------------
@pytest.mark.parametrize("bf", [5.0, 9000.0])
def test_paper_parameters_closed_form_equals_integration(bf):
    s = SwitchedErrorSystem.from_params(bf=bf, **PAPER)
    assert not visible_eigenvectors(s)
    assert s.damping_case(1) == "complex"          # B1^2 = 6400 < 4 K1 = 16000
    assert s.damping_case(2) == ("complex" if bf == 5 else "real")
    lam = _agree(s)
    # our values (the paper prints 10.16 and 0.98; see docs/reproduction.md)
    assert lam == pytest.approx({5.0: 114.5760209, 9000.0: 1.178347649}[bf], rel=1e-8)


# --- property test over a sweep of all branches ----------------------------------------------
logu = lambda lo, hi: st.floats(math.log(lo), math.log(hi)).map(math.exp)  # noqa: E731


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(K1=logu(1.0, 1e4), ratio=logu(1.5, 1e4), B1=logu(0.05, 300.0), B2=logu(0.05, 3e3))
def test_lambda_closed_form_matches_integration(K1, ratio, B1, B2):
    s = SwitchedErrorSystem(K1, B1, K1 * ratio, B2)
    assume(not visible_eigenvectors(s))
    lam = _agree(s)
    assert math.isfinite(lam) and lam > 0


@pytest.mark.parametrize("K1,B1,K2,B2", [
    (4.0, 4.0, 400.0, 10.0),        # subsystem 1 critically damped (15), exactly B^2 = 4K
    (4.0, 3.0, 2500.0, 100.0),      # subsystem 2 critically damped, exactly
    (4.0, 4.0, 2500.0, 100.0),      # both critically damped
    (100.0, 30.0, 1e4, 5.0),        # subsystem 1 real (16)
    (100.0, 2.0, 1e4, 250.0),       # subsystem 2 real (16)
    (100.0, 30.0, 1e4, 30.0),       # Delta B = 0
    (100.0, 2.0, 1e4, 2.0),         # Delta B = 0, both complex
])
def test_all_branches_and_delta_b_zero(K1, B1, K2, B2):
    s = SwitchedErrorSystem(K1, B1, K2, B2)
    if visible_eigenvectors(s):
        with pytest.raises(StabilityError, match="visible"):
            lambda_closed_form(s)
        assert lambda_numerical(s).visible
        return
    _agree(s)


def test_printed_15_is_wrong_for_i1_and_right_for_i2():
    s = SwitchedErrorSystem(4.0, 4.0, 400.0, 10.0)   # subsystem 1 critically damped
    rot = lambda_numerical(s)
    f = dict(zip(rot.sector_modes, rot.sector_factors))
    printed = lambda_closed_form(s, printed_15=True)[0]
    assert printed != pytest.approx(f[1], rel=1e-2)
    assert lambda_closed_form(s)[0] == pytest.approx(f[1], rel=1e-6)
    s2 = SwitchedErrorSystem(4.0, 3.0, 2500.0, 100.0)  # subsystem 2 critically damped
    assert lambda_closed_form(s2, printed_15=True)[1] == pytest.approx(lambda_closed_form(s2)[1], rel=1e-14)


def test_critical_branch_is_selected_exactly_and_is_continuous():
    s = SwitchedErrorSystem(4.0, 4.0, 400.0, 10.0)
    assert s.damping_case(1) == "critical"
    lam_c = lambda_closed_form(s)[0]
    # neighbours on either side use (14) and (16): continuity across the branch border
    for B in (4.0 - 1e-6, 4.0 + 1e-6):
        lam_n = lambda_closed_form(SwitchedErrorSystem(4.0, B, 400.0, 10.0))[0]
        assert lam_n == pytest.approx(lam_c, rel=1e-5)


def test_q_zero_has_no_division_by_zero():
    # Q = B_i dK - 2 K_i dB = 0 for i = 2: arctan(. / Q) is replaced by arctan2
    K1, B1, K2 = 100.0, 30.0, 1e4
    B2 = 2 * K2 * B1 / (2 * K2 + (K1 - K2))  # solves B2 dK = 2 K2 dB
    s = SwitchedErrorSystem(K1, B1, K2, B2)
    assert s.B2 * s.dK - 2 * s.K2 * s.dB == pytest.approx(0.0, abs=1e-8)
    assume_no_vis = not visible_eigenvectors(s)
    if assume_no_vis:
        _agree(s)


# --- visible eigenvectors: geometry vs the printed inequalities of Theorem 1 i -------------------
@settings(max_examples=150, deadline=None)
@given(K1=logu(1.0, 1e4), ratio=logu(1.01, 1e4), B1=logu(0.05, 1e3), B2=logu(0.05, 1e4))
def test_visible_eigenvectors_geometric_equals_theorem1(K1, ratio, B1, B2):
    s = SwitchedErrorSystem(K1, B1, K1 * ratio, B2)
    vis = visible_eigenvectors(s)
    cond = theorem1_conditions(s)
    assert bool(vis) == any(cond.values())
    assert (1 in {v.cone for v in vis}) == cond["i_a"]
    assert (2 in {v.cone for v in vis}) == (cond["i_b1"] or cond["i_b2"])


@pytest.mark.parametrize("K1,B1,K2,B2", [
    (100.0, 30.0, 1e4, 300.0),      # visible in S2 (i b 1)
    (100.0, 30.0, 1e4, 20.0),       # Delta B > 0 ... complex A2: only S1 can hold one
    (1.0, 3.0, 50.0, 1.0),          # visible in S1 (i a)
    (100.0, 2.0, 1e4, 2.0 ** 0.5 * 200),  # Delta B < 0, real A2
])
def test_visible_eigenvector_stops_rotation(K1, B1, K2, B2):
    s = SwitchedErrorSystem(K1, B1, K2, B2)
    vis = visible_eigenvectors(s)
    rot = lambda_numerical(s)
    assert rot.visible == bool(vis)
    rep = analyze(s, with_iss=False)
    if vis:
        assert all(v.eigenvalue < 0 for v in vis)
        assert rep.guas and rep.case == "i" and rep.Lambda is None
    else:
        assert rep.case == "ii" and rep.Lambda == pytest.approx(rot.Lambda, rel=1e-6)


# --- Lemma 1 ----------------------------------------------------------------------------------
@settings(max_examples=200, deadline=None)
@given(z1=st.floats(-1e3, 1e3), z2=st.floats(-1e5, 1e5))
def test_lemma1_worst_case_maximises_vdot_pointwise(z1, z2):
    s = SwitchedErrorSystem(4000.0, 80.0, 95238.1, 330.7)
    z = np.array([z1, z2])
    w = s.worst_case_mode(z)
    vd = [z @ s.A(i) @ z for i in (1, 2)]
    assert vd[w - 1] >= max(vd) - 1e-12 * (abs(vd[0]) + abs(vd[1]))
    assert s.in_cone(w, z)


def test_lemma1_trajectory_bound_counterexample():
    """Lemma 1 claims |Phi_u(t) z0| <= |Phi_w(t) z0| for all t; the greedy argmax rule does not give
    that (documented in docs/reproduction.md).  A random switching sequence beats it at t = 0.04 s;
    the worst-case value is confirmed by an independent RK integration of the argmax rule."""
    from scipy.integrate import solve_ivp

    s = SwitchedErrorSystem(4000.0, 80.0, 95238.1, 330.7)
    rng = np.random.default_rng(331)
    z0 = rng.normal(size=2)
    z0[1] *= 100
    T, t, z = 0.04, 0.0, z0.copy()
    while t < T:
        dt = min(T - t, rng.exponential(0.003))
        z = expm(s.A(int(rng.integers(1, 3))) * dt) @ z
        t += dt
    _, zw = worst_case_flow(s, z0, T, n=2)
    sol = solve_ivp(lambda t, y: s.A(s.worst_case_mode(y)) @ y, (0, T), z0, method="DOP853",
                    rtol=1e-11, atol=1e-12, max_step=1e-5)
    assert np.linalg.norm(sol.y[:, -1]) == pytest.approx(np.linalg.norm(zw[-1]), rel=1e-6)
    assert np.linalg.norm(z) > 1.1 * np.linalg.norm(zw[-1])


# --- Theorem 2: ISS bound holds for perturbed arbitrary switching -----------------------------
def test_iss_bound_holds_for_perturbed_switching():
    s = SwitchedErrorSystem(4000.0, 80.0, 95238.1, 330.7)
    b = iss_bound(s, n_angles=48)
    assert b.rate > 0 and b.c >= 1 and b.gain == pytest.approx(b.c / b.rate)
    rng = np.random.default_rng(3)
    from scipy.integrate import solve_ivp

    z0 = np.array([1e-3, 0.2])
    w_max = 0.5
    sw = np.cumsum(rng.exponential(0.004, 400))
    modes = rng.integers(1, 3, 400)
    freq = rng.uniform(10, 200)

    def f(t, z):
        i = modes[np.searchsorted(sw, t)]
        return s.A(int(i)) @ z + s.N[:, 0] * w_max * math.sin(freq * t)

    sol = solve_ivp(f, (0, 1.0), z0, max_step=2e-4, rtol=1e-8, atol=1e-12)
    bound = b.c * np.exp(-b.rate * sol.t) * np.linalg.norm(z0) + b.gain * w_max
    assert np.all(np.linalg.norm(sol.y, axis=0) <= bound)


# --- errors ----------------------------------------------------------------------------------
def test_unstable_subsystem_is_a_clear_error():
    with pytest.raises(StabilityError, match="not Hurwitz.*B2"):
        SwitchedErrorSystem.from_params(M=1, b=0, kp=4000, kd=80, ke=1e6, be=0.0, kf=1, bf=-10)
    with pytest.raises(StabilityError, match="K1"):
        SwitchedErrorSystem(-1.0, 1.0, 10.0, 1.0)
    with pytest.raises(ParameterError):
        SwitchedErrorSystem(float("nan"), 1.0, 10.0, 1.0)


def test_theorem_not_applicable_when_wall_softer_than_controller():
    s = SwitchedErrorSystem(4000.0, 80.0, 100.0, 10.0)
    with pytest.raises(StabilityError, match="K2 > K1"):
        lambda_closed_form(s)


# --- helpers ---------------------------------------------------------------------------------
@pytest.mark.parametrize("K,B", [(4.0, 4.0), (4.0, 4.0 + 1e-7), (4000.0, 80.0), (2e6, 9020.0), (2e9, 0.01)])
def test_expm2_matches_scipy(K, B):
    A = np.array([[0.0, 1.0], [-K, -B]])
    ts = np.array([0.0, 1e-6, 1e-3, 0.05, 0.5])
    for E, t in zip(expm2(A, ts), ts):
        ref = expm(A * t)
        assert np.allclose(E, ref, rtol=1e-9, atol=1e-12 * np.abs(ref).max())


def test_perturbations_vanish_with_exact_model_and_static_reference():
    w1, w2 = perturbations([0.0, 1e-6], [0.0, 0.0], [0.0, 0.0], M=1, b=0, Ma=1, bf=5, ke=1e6, be=10)
    assert np.all(w1 == 0) and np.all(w2 == 0)
    _, w2 = perturbations([1e-6], [0.0], [0.0], M=1, b=0, Ma=1, bf=5, ke=1e6, be=10, ke_hat=2e6)
    assert w2[0] == pytest.approx(-1.0)  # -w_f/M with w_f = (ke_hat - ke) x_d


def test_statespace_subsystems():
    s = SwitchedErrorSystem.from_params(bf=5.0, **PAPER)
    ss2 = s.statespace(2)
    assert np.allclose(np.sort_complex(ss2.poles()), np.sort_complex(s.eigenvalues(2)))


def test_sweep_grid_covers_every_branch_pair():
    """Deterministic sweep: critical (exact B^2 = 4K), complex and real subsystems in every combination."""
    import itertools

    seen = set()
    n = 0
    for K1, K2f, f1, f2 in itertools.product((4.0, 100.0, 2500.0), (10.0, 1000.0), (1.0, 0.5, 3.0),
                                             (1.0, 0.3, 1.5, 4.0)):
        K2 = K1 * K2f
        B1 = 2 * math.sqrt(K1) * f1
        B2 = 2 * math.sqrt(K2) * f2
        s = SwitchedErrorSystem(K1, B1, K2, B2)
        if visible_eigenvectors(s):
            assert lambda_numerical(s).visible
            continue
        _agree(s)
        seen.add((s.damping_case(1), s.damping_case(2)))
        n += 1
    cases = ("complex", "critical", "real")
    assert seen == set(itertools.product(cases, cases)), seen
    assert n >= 20
