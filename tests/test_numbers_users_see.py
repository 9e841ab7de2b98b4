"""Numbers users see, checked against independent computations (issue 23).

Each test recomputes a reported number by other means (brute force, an exact solver, numpy,
scipy) so that a one-line slip in the code that produces it changes a number and fails a test.
"""
import importlib
import json
import re
import subprocess
import sys
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
import scipy.sparse as sp
from scipy.integrate import solve_ivp

import invctl_scenes.manipulator as manip
import invctl_scenes.two_link_arm as arm
from invctl.analysis import relative_degree
from invctl.analysis.relative_degree import lie_chain
from invctl.contact.lcp import lcp_residual, lcp_sx, solve_lcp
from invctl.inversion import invert
from invctl.inversion.backends import _newton
from invctl.inversion.verify import forward_check
from invctl.simulate.closed_loop import plant_acceleration
from invctl.studies.commands import OPTIONS

ROOT = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------ analyze: Gamma over the samples
@pytest.fixture(scope="module")
def manipulator_model():
    return manip.build()


@pytest.fixture(scope="module")
def analyze_cli():
    """``invctl analyze manipulator --json`` with the default options: (text lines, JSON object)."""
    out = subprocess.run([sys.executable, "-m", "invctl.cli", "analyze", "manipulator", "--json"], cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    lines = out.stdout.strip().splitlines()
    return lines[:-1], json.loads(lines[-1])


def _gamma_brute_force(model, qs, vs):
    """``cond_2`` and ``det`` of Gamma at every sample, one numpy call per sample."""
    gamma = ca.Function("Gamma_check", [model.q, model.v, model.theta], [lie_chain(model).gamma])
    G = [np.array(gamma(q, v, model.theta_values)) for q, v in zip(qs, vs)]
    return np.array([np.linalg.cond(g, 2) for g in G]), np.array([np.linalg.det(g) for g in G])


def test_documented_samples_default_is_the_number_analyze_uses(manipulator_model, analyze_cli):
    """``--samples`` default: README, option table and the run agree; det Gamma over exactly those samples."""
    _, data = analyze_cli
    gamma = data["gamma"]
    declared = OPTIONS["samples"].default
    assert gamma["samples"] == declared, f"analyze used {gamma['samples']} samples, the option table declares {declared}"
    usage = re.search(r"invctl analyze\s+<scene>.*\[--samples (\d+)\]", (ROOT / "README.md").read_text())
    documented = int(usage.group(1))
    assert declared == documented, f"--samples default {declared} in the option table, {documented} in README.md"
    # the manipulator declares its region: the samples are the region's draws with seed 0
    qs, vs = manipulator_model.region.sample(documented, 0)
    assert qs.shape[0] == documented
    _, dets = _gamma_brute_force(manipulator_model, qs, vs)
    np.testing.assert_allclose(gamma["det_range"], [dets.min(), dets.max()], rtol=1e-9,
                               err_msg="det Gamma range differs from the recomputation over the documented samples")


@pytest.mark.parametrize("name", ["manipulator", "crane"])
def test_worst_condition_of_gamma_is_the_largest_over_the_samples(name, tmp_path):
    """Worst cond(Gamma) and its (q, v), also in the .npz, equal a brute-force scan of the same samples."""
    model = importlib.import_module(f"invctl_scenes.{name}").build()
    rd = relative_degree(model, samples=200)
    qs, vs = rd.diagnostics["q"], rd.diagnostics["v"]
    assert qs.shape[0] == 200
    cond, _ = _gamma_brute_force(model, qs, vs)
    k = int(np.argmax(cond))
    assert cond[k] > 100 * np.min(cond)  # the scan distinguishes the largest from the others
    assert rd.worst_condition == pytest.approx(cond[k], rel=1e-8), \
        f"reported worst condition {rd.worst_condition:.6g}, brute force max {cond[k]:.6g}"
    np.testing.assert_allclose(rd.worst_point[0], qs[k], atol=1e-14)
    np.testing.assert_allclose(rd.worst_point[1], vs[k], atol=1e-14)
    rd.to_npz(tmp_path / "rd.npz")
    with np.load(tmp_path / "rd.npz") as z:
        assert float(z["worst_condition"]) == pytest.approx(cond[k], rel=1e-8)
        np.testing.assert_allclose(z["worst_q"], qs[k], atol=1e-14)


def test_analyze_prints_the_worst_condition_of_gamma(manipulator_model, analyze_cli):
    """``invctl analyze manipulator``: worst cond(Gamma) and its q in text and JSON = brute force (same draws)."""
    model = manipulator_model
    lines, data = analyze_cli
    qc, vc = model.region.sample(data["gamma"]["samples"], 0)
    cond_c, _ = _gamma_brute_force(model, qc, vc)
    kc = int(np.argmax(cond_c))
    assert data["gamma"]["worst_condition"] == pytest.approx(cond_c[kc], rel=1e-8), \
        f"JSON worst condition {data['gamma']['worst_condition']:.6g}, brute force max {cond_c[kc]:.6g}"
    np.testing.assert_allclose(data["gamma"]["worst_point"]["q"], qc[kc], atol=1e-12)
    text = next(ln for ln in lines if "worst condition number" in ln)
    shown = float(re.search(r"worst condition number (\S+)", text).group(1))
    assert shown == pytest.approx(cond_c[kc], rel=1e-3), text
    shown_q = json.loads(re.search(r"at q = (\[.*\])", text).group(1))
    np.testing.assert_allclose(shown_q, np.round(qc[kc], 4), atol=1e-12)


# ------------------------------------------------------------ PGS: the convergence flag
@pytest.mark.parametrize("sweeps", [5, 50])
def test_pgs_flag_agrees_with_an_exact_lcp_solver(sweeps):
    """300 random 6 x 6 LCPs (SPD, some ill-conditioned): a result flagged converged solves the LCP
    (and equals the enumeration solution), an unconverged one is flagged."""
    n, res_tol = 6, 1e-9
    A, b = ca.SX.sym("A", n, n), ca.SX.sym("b", n)
    z, ok = lcp_sx(A, b, method="pgs", pgs_sweeps=sweeps, res_tol=res_tol, with_flag=True)
    F = ca.Function("pgs", [A, b], [z, ok])
    rng = np.random.default_rng(0)
    flagged = unconverged = 0
    for k in range(300):
        R = rng.standard_normal((n, n))
        Ak, bk = R @ R.T + 0.05 * np.eye(n), rng.standard_normal(n)
        zk, okk = F(Ak, bk)
        zk, okk = np.array(zk).ravel(), bool(float(okk))
        exact = solve_lcp(Ak, bk, method="enumeration").z
        scale = 1 + np.abs(bk).max() + np.abs(Ak).max() * np.abs(zk).max()
        res = lcp_residual(Ak, bk, zk)
        if okk:
            flagged += 1
            assert res <= res_tol * scale, f"LCP {k}: flagged converged with residual {res:.3g} > {res_tol * scale:.3g}"
            np.testing.assert_allclose(zk, exact, atol=1e-6 * (1 + np.abs(exact).max()),
                                       err_msg=f"LCP {k}: flagged converged, differs from the exact solution")
        else:
            unconverged += 1
            assert res > res_tol * scale, f"LCP {k}: flagged unconverged with residual {res:.3g}"
    assert flagged and unconverged  # both branches are exercised


# ------------------------------------------------------------ Newton: the stopping rule
class _CubicSystem:
    """A square system ``g(x) = x^3 + x - c`` (one residual per unknown), all residuals < 0 at x = 0."""

    def __init__(self, c):
        self.c = np.asarray(c, float)

    def banded_pattern(self):
        return None

    def evaluators(self):
        def residual(x, p):
            return x**3 + x - self.c

        def residual_and_jacobian(x, p):
            return residual(x, p), sp.csc_matrix(np.diag(3 * x**2 + 1))

        return residual, residual_and_jacobian


def test_newton_stops_on_the_absolute_residual():
    """All residuals one-signed negative at the start: Newton must still drive max |g| below tol."""
    c = np.linspace(0.5, 2.0, 5)
    tr = _CubicSystem(c)
    x0 = np.zeros(c.size)
    tol = 1e-10
    assert np.max(tr.evaluators()[0](x0, None)) < 0
    x, info = _newton(tr, x0, None, max_iter=50, max_wall_time=60.0, tol=tol, progress=False, label="t",
                      banded=False)
    g = tr.evaluators()[0](x, None)
    assert info["success"]
    assert np.max(np.abs(g)) < tol, f"returned with max |g| = {np.max(np.abs(g)):.3g} (status {info['status']})"
    assert info["max_constraint_violation"] == pytest.approx(np.max(np.abs(g)), abs=1e-16)
    assert info["iterations"] >= 1



class _Atan:
    """``g(x) = atan(x)``: Newton's full step overshoots, and from |x0| near 1.3917 (where it cycles) barely
    decreases |g|; the step and its residual are closed forms, x1 = x0 - atan(x0) (1 + x0^2)."""

    def banded_pattern(self):
        return None

    def evaluators(self):
        return (lambda x, p: np.arctan(x),
                lambda x, p: (np.arctan(x), sp.csc_matrix(np.diag(1 / (1 + x**2)))))


def _atan_start(ratio):
    """x0 whose full Newton step gives |g(x1)| = ratio |g(x0)| (bisection on the closed form)."""
    from scipy.optimize import brentq

    def step(x):
        return x - np.arctan(x) * (1 + x**2)

    x0 = brentq(lambda x: abs(np.arctan(step(x))) / np.arctan(x) - ratio, 1.0, 1.3917, xtol=1e-15)
    return x0, step(x0)


def test_newton_line_search_is_armijo_with_1e_4_and_reports_the_last_residual():
    """A full step that decreases |g| by 5e-4 (more than the sufficient decrease 1e-4 s) is taken undamped;
    after max_iter = 1 the iterate, its residual (negative) and the status are the closed forms."""
    x0, x1 = _atan_start(1 - 5e-4)
    x, info = _newton(_Atan(), np.array([x0]), None, max_iter=1, max_wall_time=60.0, tol=1e-12, progress=False,
                      label="t", banded=False)
    np.testing.assert_allclose(x, [x1], rtol=1e-12)
    assert info["status"] == "Maximum_Iterations_Exceeded" and not info["success"]
    assert info["iterations"] == 1 and info["factorizations"] == 1
    assert info["max_constraint_violation"] == pytest.approx(abs(np.arctan(x1)), rel=1e-12)


class _OvershootLinear:
    """``g(x) = x`` with the Jacobian off by a factor 2 (0.5): the full step from x0 = 1 lands on -1 exactly."""

    def banded_pattern(self):
        return None

    def evaluators(self):
        return lambda x, p: x, lambda x, p: (x, sp.csc_matrix([[0.5]]))


def test_newton_accepts_a_step_as_converged_only_below_tol():
    """With tol = 1 the full step lands exactly on max |g| = tol: that is neither a decrease nor converged
    (max |g| < tol, strict, as at the start of every iteration), so the step is halved and lands on the root."""
    x, info = _newton(_OvershootLinear(), np.array([1.0]), None, max_iter=1, max_wall_time=60.0, tol=1.0,
                      progress=False, label="t", banded=False)
    assert x.tolist() == [0.0]
    assert info["success"] and info["iterations"] == 1 and info["max_constraint_violation"] == 0.0


# ------------------------------------------------------------ closed loop: Baumgarte-stabilized plant
def _kkt_acceleration(model, q, v, u, alpha, beta):
    """Numpy solution of ``[M -G^T; G 0] [a; lam] = [f + B u; -(G v)' v - 2 alpha G v - beta^2 g]``."""
    th = model.theta_values
    M, f, B = model.evaluate("M", q), model.evaluate("f", q, v).ravel(), model.evaluate("B", q)
    G, g = model.evaluate("G", q), model.evaluate("g", q).ravel()
    dGv = ca.Function("dGv", [model.q, model.v, model.theta], [ca.jacobian(ca.mtimes(model.G, model.v), model.q)])
    Gdot_v = np.array(dGv(q, v, th)) @ v
    n, l = model.n, model.ell
    K = np.block([[M, -G.T], [G, np.zeros((l, l))]])
    rhs = np.concatenate([f + B @ u, -Gdot_v - 2 * alpha * G @ v - beta**2 * g])
    sol = np.linalg.solve(K, rhs)
    return sol[:n], sol[n:]


def test_closed_loop_plant_acceleration_is_the_stabilized_kkt_solution(manipulator_model):
    model = manipulator_model
    assert model.ell > 0 and model.J.shape[0] == 0
    alpha, beta = 20.0, 20.0
    acc = plant_acceleration(model, alpha, beta)
    rng = np.random.default_rng(1)
    for q0 in model.region.sample(5, 3)[0]:
        q = q0 + 0.05 * rng.standard_normal(model.n)  # off the constraint manifold: g(q) != 0
        v, u = rng.standard_normal(model.n), rng.standard_normal(model.m)
        a_ref, lam_ref = _kkt_acceleration(model, q, v, u, alpha, beta)
        a, lam = (np.array(x).ravel() for x in acc(q, v, u, model.theta_values))
        scale = 1 + np.abs(a_ref).max()
        assert np.max(np.abs(a - a_ref)) < 1e-9 * scale, f"plant acceleration off by {np.max(np.abs(a - a_ref)):.3g}"
        np.testing.assert_allclose(lam, lam_ref, atol=1e-9 * (1 + np.abs(lam_ref).max()))


# ------------------------------------------------------------ forward check of an inversion
@pytest.fixture(scope="module")
def arm_inverse():
    md = arm.build()
    rf = arm.reference(md)
    inv = invert(md, rf, T0=-0.5, Tf=2.0, N=120, scheme="hermite-simpson",
                 start={"q": "all", "v": "all", "u": "all"}, end={}, backend="newton")
    return md, rf, inv


class _FeedforwardPlus:
    """The inverse with ``u + delta`` (still piecewise cubic between the mesh points)."""

    def __init__(self, inv, delta):
        self.inv, self.delta = inv, np.asarray(delta, float).reshape(-1, 1)
        self.q, self.v, self.t0, self.Tf, self.t_mesh = inv.q, inv.v, inv.t0, inv.Tf, inv.t_mesh
        self.poly_degree = 3

    def u(self, t):
        return self.inv.u(t) + self.delta


def _independent_error(model, inv, rf, rep):
    """max |y - y_ref| of scipy's DOP853 on ``M a = f + B u`` (the arm has no constraints), same windows."""
    edges = np.linspace(rep["t"][0], rep["t"][-1], rep["windows"] + 1)
    worst = 0.0
    for a, b in zip(edges[:-1], edges[1:]):
        def rhs(t, x):
            q, v = x[:model.n], x[model.n:]
            M, f, B = model.evaluate("M", q), model.evaluate("f", q, v).ravel(), model.evaluate("B", q)
            return np.concatenate([v, np.linalg.solve(M, f + B @ inv.u(t).ravel())])

        x0 = np.concatenate([inv.q(a).ravel(), inv.v(a).ravel()])
        sol = solve_ivp(rhs, (a, b), x0, method="DOP853", rtol=1e-11, atol=1e-12, dense_output=True)
        t = rep["t"][(rep["t"] >= a) & (rep["t"] <= b)]
        y = np.array([model.evaluate("h", x[:model.n], x[model.n:]).ravel() for x in sol.sol(t).T]).T
        worst = max(worst, float(np.max(np.abs(y - rf(t)))))
    return worst


def test_forward_check_reports_the_error_of_a_perturbed_feedforward(arm_inverse):
    """u + 0.05: the reported error equals an independent integration; the inverse itself: small, nonzero."""
    md, rf, inv = arm_inverse
    bad = _FeedforwardPlus(inv, [0.05])
    rep_bad = forward_check(md, bad, rf)
    expected = _independent_error(md, bad, rf, rep_bad)
    assert expected > 1e-3  # the perturbation is visible in the output
    assert rep_bad["error"] == pytest.approx(expected, rel=1e-3), \
        f"forward check reports {rep_bad['error']:.4g} for u + 0.05, independent integration {expected:.4g}"
    rep = forward_check(md, inv, rf)
    assert 0 < rep["error"] < 2e-5, f"forward check of the inverse reports {rep['error']:.3g}, expected in (0, 2e-5)"
    assert rep["error"] == pytest.approx(_independent_error(md, inv, rf, rep), rel=1e-2)
