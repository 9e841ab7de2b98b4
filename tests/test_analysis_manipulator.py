"""Analysis of the manipulator of 003 Sect. 6 against the paper's closed forms.

Independent references typed from the paper: det Gamma (printed formula), the
internal dynamics (55) and the state form of eta2' with the printed inverse
(beta', gamma') before (55), the linearization coefficients C0, C1, C2 and
the eigenvalues mu_1,2 of (51)-(52).  Tolerances: all quantities are exact
formulas evaluated in double precision; the only error is round-off (and the
Newton tolerance 1e-12 of the coordinate inversion), hence 1e-9 relative.
"""
import copy
import dataclasses
import json
import math

import casadi as ca
import numpy as np
import pytest

import invctl_scenes.manipulator as scene
from invctl.analysis import (
    consistent_state, internal_dynamics, linearize_internal, position_output_gamma,
    relative_degree,
)
from invctl.studies import commands
from invctl.studies.tracking import tracking_linearization
from invctl.cli import main
from invctl.errors import CoordinateError, OptionError, SceneError


def det_gamma_printed(q, p, x3_power=2):
    """det Gamma as printed in 003 Sect. 6 (printed with X3^3; X3^2 is what (50) needs)."""
    a, b, g = q[2], q[3], q[4]
    M = scene.build(**{k: v for k, v in p.items()}).evaluate("M", q)
    br = p["I3"] + p["m3"] * p["X3"] ** x3_power - p["m3"] * p["L3"] * p["X3"] * np.cos(g)
    return -p["L1"] ** 2 * p["L2"] ** 2 * np.sin(a) * np.sin(a + b) * br / ((2 * p["L2"] + 4 * p["L3"]) * np.linalg.det(M))


def consts(p):
    L2, L3, m3 = p["L2"], p["L3"], p["m3"]
    kap = m3 * L3**2 / 3
    return L2, L3, m3, p["c"], p["D"], kap, 2 * L3 / (L2 + 2 * L3)


def F55(eta, y, yd, p, *, printed=False):
    """003 (55) typed from the paper.  ``printed=True``: exactly as printed; otherwise with the sign of the
    (1 - delta) (L3 m3 / 2) sin(.) y1' term in the first factor of F2 corrected (see docs/analysis.md)."""
    L2, L3, m3, c, D, kap, dl = consts(p)
    e1, e2 = eta
    k = 2 * (L2 + 2 * L3) / (kap * L2 * (2 - 3 * np.cos(e1)))
    sn, cs = np.sin(y[1] + (1 - dl) * e1), np.cos(y[1] + (1 - dl) * e1)
    F1 = k * (e2 - (kap + m3 * L2 * L3 / 4 * np.cos(e1)) * yd[1] + m3 * L3 / 2 * sn * yd[0])
    sgn = -1 if printed else 1
    fac1 = (1 - dl) * e2 + sgn * (1 - dl) * L3 * m3 / 2 * sn * yd[0] - L2 * L3 * m3 / 4 * np.cos(e1) * yd[1]
    fac2 = L3 * m3 / 2 * cs * yd[0] + L2 * L3 * m3 / 4 * np.sin(e1) * k * (
        kap * yd[1] - dl * e2 - dl * m3 * L3 / 2 * sn * yd[0])
    F2 = -k * fac1 * fac2 - D * F1 - c * e1
    return np.array([F1, F2])


def eta2_dot_state_form(eta, y, yd, p):
    """The paper's eta2' in the states (before (54)) with its printed beta', gamma' (after (54))."""
    L2, L3, m3, c, D, kap, dl = consts(p)
    e1, e2 = eta
    k = 2 * (L2 + 2 * L3) / (kap * L2 * (2 - 3 * np.cos(e1)))
    sn = np.sin(y[1] + (1 - dl) * e1)
    bd = k * (kap * yd[1] - dl * e2 - dl * m3 * L3 / 2 * sn * yd[0])
    gd = k * (e2 - (kap + m3 * L2 * L3 / 4 * np.cos(e1)) * yd[1] + m3 * L3 / 2 * sn * yd[0])
    beta = y[1] - dl * e1
    return (-L3 * m3 / 2 * np.cos(beta + e1) * (bd + gd) * yd[0]
            - m3 / 4 * L2 * L3 * np.sin(e1) * bd * (bd + gd) - D * gd - c * e1)


def random_internal_points(rng, count, p=scene.PARAMS):
    """Random (y, y', eta) for which the loop closes: |s2 + d - L2/2 cos(beta)| < 0.9 L1 (alpha exists)."""
    dl = 2 * p["L3"] / (p["L2"] + 2 * p["L3"])
    found = 0
    while found < count:
        y = np.array([rng.uniform(-0.3, 0.0), rng.uniform(0.6, 1.1)])
        eta = np.array([rng.uniform(-0.6, 0.6), rng.uniform(-0.3, 0.3)])
        beta = y[1] - dl * eta[0]
        if abs(y[0] + p["d"] - 0.5 * p["L2"] * np.cos(beta)) < 0.9 * p["L1"] and 0 < beta < np.pi / 2:
            found += 1
            yield y, rng.uniform(-1, 1, 2), eta


@pytest.fixture(scope="module")
def paper_internal(manipulator):
    return internal_dynamics(manipulator, "sect3", scene.paper_internal_coordinates,
                             point=scene.initial_configuration(manipulator), samples=200)


@pytest.fixture(scope="module")
def lin(manipulator, paper_internal):
    return tracking_linearization(scene.SCENE, manipulator, scene.reference(manipulator), internal=paper_internal)


def test_relative_degree(manipulator):
    rd = relative_degree(manipulator)
    assert rd.r_aux == (2, 2, 2, 2) and rd.r_hat == 2 and rd.r_bar == 8
    assert rd.samples == 200 and np.isfinite(rd.worst_condition) and rd.min_singular_value > 0


@pytest.mark.parametrize("overrides", [{}, {"X3": 0.2, "I3": 0.03}, {"L2": 1.3, "L3": 0.7, "m3": 0.8}])
def test_det_gamma_matches_closed_form_with_X3_squared(overrides):
    model = scene.build(**overrides)
    rd = relative_degree(model, samples=20)
    G22 = position_output_gamma(model)
    qs, vs = model.region.sample(10, 3)
    for q, v in zip(qs, vs):
        G_lie = np.array(rd.gamma(q, v, model.theta_values))
        G_closed = np.array(G22(q, model.theta_values))
        np.testing.assert_allclose(G_lie, G_closed, rtol=1e-12, atol=1e-12)
        d = np.linalg.det(G_lie)
        assert d == pytest.approx(det_gamma_printed(q, model.values, 2), rel=1e-9)
    # the printed X3^3 is a typo: with the default parameters it is off by a large factor
    q = qs[0]
    d = np.linalg.det(np.array(rd.gamma(q, vs[0], model.theta_values)))
    assert abs(det_gamma_printed(q, model.values, 3) - d) > 0.01 * abs(d)


def test_det_gamma_has_one_sign_on_U(manipulator):
    """det Gamma never vanishes on U (sampled): it is > 0 everywhere; the printed closed form is > 0 too,
    since its bracket I3 + m3 X3^2 - m3 L3 X3 cos(gamma) < 0 on U (the paper's 'det Gamma < 0' is a sign slip)."""
    rd = relative_degree(manipulator, samples=1000, rng=7)
    assert rd.det_range[0] > 0
    p = manipulator.values
    qs, _ = manipulator.region.sample(500, 11)
    bracket = p["I3"] + p["m3"] * p["X3"] ** 2 - p["m3"] * p["L3"] * p["X3"] * np.cos(qs[:, 4])
    assert np.all(bracket < 0)


def test_internal_dynamics_agree_with_55(manipulator, paper_internal):
    p = manipulator.values
    rng = np.random.default_rng(0)
    for y, yd, eta in random_internal_points(rng, 15):
        ours = paper_internal((y, yd), eta)
        np.testing.assert_allclose(ours, F55(eta, y, yd, p), rtol=1e-9, atol=1e-9)
        assert ours[1] == pytest.approx(eta2_dot_state_form(eta, y, yd, p), rel=1e-9, abs=1e-9)
    # the printed (55) (sign of one term) disagrees with the paper's own state form away from y1' = 0
    y, yd, eta = np.array([-0.1, 0.8]), np.array([0.7, -0.4]), np.array([0.3, 0.1])
    assert abs(F55(eta, y, yd, p, printed=True)[1] - eta2_dot_state_form(eta, y, yd, p)) > 1e-2


def test_sect2_equals_sect3_same_coordinates(manipulator, paper_internal):
    s2 = internal_dynamics(manipulator, "sect2", scene.paper_internal_coordinates,
                           point=scene.initial_configuration(manipulator), samples=200)
    rng = np.random.default_rng(1)
    for y, yd, eta in random_internal_points(rng, 10):
        np.testing.assert_allclose(s2((y, yd), eta), paper_internal((y, yd), eta), rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("method", ["sect2", "sect3"])
def test_internal_dynamics_follow_the_dae(manipulator, paper_internal, method):
    """Both coordinate choices (paper's and Lemma 3.1/3.2 default) satisfy d/dt phi(x) = q(y, y', eta) along
    the DAE for any input: the same internal dynamics up to the coordinate change."""
    q0 = scene.initial_configuration(manipulator)
    default = internal_dynamics(manipulator, method, point=q0)
    acc = manipulator.accel_and_multipliers
    th = manipulator.theta_values
    m = manipulator
    X = ca.vertcat(m.q, m.v)
    out = ca.Function("out", [m.q, m.v, m.theta], [m.h, ca.mtimes(ca.jacobian(m.h, m.q), m.v)])
    rng = np.random.default_rng(2)
    for _ in range(8):
        q, v = consistent_state(m, q0 + rng.uniform(-0.15, 0.15, 5), rng.uniform(-1, 1, 5))
        u = rng.uniform(-5, 5, 2)
        a = np.array(acc(q, v, u, th)[0]).ravel()
        y, yd = (np.array(o).ravel() for o in out(q, v, th))
        for idyn in (default, paper_internal):
            deta = ca.Function("d", [m.q, m.v, m.theta], [ca.jacobian(idyn.phi_expr, X)])
            eta = np.array(idyn.eta(q, v, th)).ravel()
            true_rate = np.array(deta(q, v, th)) @ np.concatenate([v, a])
            np.testing.assert_allclose(idyn((y, yd), eta), true_rate, rtol=1e-8, atol=1e-8)


def test_linearization_structure_51_52(manipulator, lin):
    p = manipulator.values
    L2, L3, m3, c, D, kap, dl = consts(p)
    ref = scene.reference(manipulator)
    b0, bf = ref(ref.t0)[1, 0], ref(ref.tf)[1, 0]
    C0 = (2 * L2 + 4 * L3) / (kap * L2)
    C1 = -L3 * m3 * (L2 + 2 * L3) / (2 * kap * L2) * (np.sin(b0) + np.sin(bf))
    C2_printed = (4 * kap + L2 * L3 * m3) / (10 * kap * L2) * (L2 + 2 * L3)
    np.testing.assert_allclose(lin.Q, [[0, -C0], [-c, D * C0]], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(lin.P_list[0], np.zeros((2, 2)), atol=1e-9)
    # C2 as printed has 10 kappa L2 in the denominator; the Jacobian of (55) gives 2 kappa L2
    np.testing.assert_allclose(lin.P_list[1], [[C1, 5 * C2_printed], [-D * C1, -D * 5 * C2_printed]], rtol=1e-9)
    np.testing.assert_allclose(lin.P, lin.Q @ lin.P_list[1], rtol=1e-12)
    np.testing.assert_allclose(lin.F[0], -lin.P_list[1])
    mu = D * C0 / 2 + np.array([-1, 1]) * np.sqrt((D * C0 / 2) ** 2 + C0 * c)
    np.testing.assert_allclose(np.sort(lin.eigenvalues.real), mu, rtol=1e-10)
    assert lin.k == 1 and mu[0] < 0 < mu[1]
    # T of (39) is the inverse of the paper's T = [mu2/c mu1/c; 1 1] with its columns scaled to unit length
    # and negated (split "eig-unit": the normalization of the printed T^-1 P)
    Tp = np.array([[mu[1] / c, mu[0] / c], [1, 1]])
    np.testing.assert_allclose(np.linalg.inv(lin.T), -Tp / np.linalg.norm(Tp, axis=0), rtol=1e-9)
    np.testing.assert_allclose(lin.T @ lin.Q @ np.linalg.inv(lin.T), np.diag(mu), atol=1e-9)
    assert lin.Q_tilde[0, 0] == pytest.approx(mu[1])


def test_default_coordinates_give_the_same_eigenvalues(manipulator, lin):
    """At an equilibrium, linearizations in different coordinates are similar: same eigenvalues."""
    q0 = scene.initial_configuration(manipulator)
    default = internal_dynamics(manipulator, "sect3", point=q0)
    paper = internal_dynamics(manipulator, "sect3", scene.paper_internal_coordinates,
                              point=scene.initial_configuration(manipulator), samples=200)
    th = manipulator.theta_values
    ref = scene.reference(manipulator)
    for t in (ref.t0, ref.tf):
        y, z = ref(t).ravel(), np.zeros(2)
        # the physical equilibrium gamma = 0, v = 0 with these outputs
        q = np.array(paper.state(y_0=y, y_1=z, eta=z, theta=th)["q"]).ravel()
        lp = linearize_internal(manipulator, paper, [([y, z], z)])
        ld = linearize_internal(manipulator, default, [([y, z], np.array(default.eta(q, np.zeros(5), th)).ravel())])
        np.testing.assert_allclose(np.sort(ld.eigenvalues.real), np.sort(lp.eigenvalues.real), rtol=1e-8)


def test_psi_is_the_unstable_coordinate(manipulator, lin):
    """Psi (58) = [0 1] T (eta - P2 y), assembled here by hand from the paper's coordinates."""
    psi = lin.psi_function()
    th = manipulator.theta_values
    rng = np.random.default_rng(4)
    q0 = scene.initial_configuration(manipulator)
    for _ in range(5):
        q, v = consistent_state(manipulator, q0 + rng.uniform(-0.1, 0.1, 5), rng.uniform(-1, 1, 5))
        M = manipulator.evaluate("M", q)
        eta = np.array([q[4], M[4] @ v])
        y = manipulator.evaluate("h", q).ravel()
        expected = (lin.T @ (eta - lin.P_list[1] @ y))[1]
        assert float(psi(q, v, th)) == pytest.approx(expected, rel=1e-12, abs=1e-12)


def test_phi_prime_singular_is_reported(manipulator):
    """eta1 = beta + delta gamma duplicates the output h2: Phi' is singular everywhere."""
    def bad_phi(model):
        return ca.vertcat(model.h[1], ca.mtimes(model.M[4, :], model.v))

    with pytest.raises(CoordinateError, match="Phi' is singular at q = ") as err:
        internal_dynamics(manipulator, "sect3", bad_phi, point=scene.initial_configuration(manipulator), samples=20)
    assert err.value.diagnostics["sigma_min"] < 1e-10


def test_LK_phi_nonzero_is_reported(manipulator):
    with pytest.raises(CoordinateError, match="L_K phi != 0"):
        internal_dynamics(manipulator, "sect2", lambda m: ca.vertcat(m.q[4], m.v[4]),
                          point=scene.initial_configuration(manipulator), samples=20)


def test_analyze_command_json(capsys):
    assert main(["analyze", "manipulator", "--json", "--samples", "50", "--set", "m3=0.6"]) == 0
    data = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert data["relative_degree"] == [2, 2, 2, 2] and data["r_bar"] == 8
    assert data["params"]["m3"] == 0.6 and data["params"]["I3"] == pytest.approx(0.6 * 0.25 / 12)
    Q, P = np.array(data["Q"]), np.array(data["P"])
    assert Q.shape == (2, 2) and P.shape == (2, 2)
    eigs = np.sort(np.array(data["internal_eigs"]))
    np.testing.assert_allclose(eigs, np.sort(np.linalg.eigvals(Q).real), rtol=1e-12)
    assert eigs[0] < 0 < eigs[1]
    assert data["checks"]["relative_degree_exists"] and data["checks"]["A2"]["passed"]
    assert data["checks"]["sect2_vs_sect3_max_diff"] < 1e-9


def test_analyze_rejects_unknown_option():
    with pytest.raises(OptionError, match="does not take"):
        commands.analyze("manipulator", samples=10, controller="C1")


def test_sect3_velocity_reconstruction_is_28(manipulator):
    """(28) literally: v = M^-1 [G^T B] Gamma^-1 (0, y') + V eta2 with V the kernel basis of [G; h'] normalized
    by phi2 V = I (26), compared with the state the Sect. 3 route reconstructs; and (25): phi2 M^-1 [G^T B] = 0."""
    m = manipulator
    q0 = scene.initial_configuration(m)
    idyn = internal_dynamics(m, "sect3", point=q0)
    th = m.theta_values
    phi2 = ca.Function("phi2", [m.q, m.theta], [ca.jacobian(idyn.phi_expr[idyn.dim1:], m.v)])
    H = ca.Function("H", [m.q, m.theta], [ca.jacobian(m.h, m.q)])
    rng = np.random.default_rng(8)
    for _ in range(5):
        q, _ = consistent_state(m, q0 + rng.uniform(-0.1, 0.1, 5))
        y = m.evaluate("h", q).ravel()
        yd, eta1 = rng.uniform(-1, 1, 2), float(np.array(idyn.eta(q, np.zeros(5), th))[0, 0])
        eta2 = rng.uniform(-0.2, 0.2, 1)
        st = idyn.state(y_0=y, y_1=yd, eta=np.concatenate([[eta1], eta2]), theta=th)
        qs, vs = np.array(st["q"]).ravel(), np.array(st["v"]).ravel()
        np.testing.assert_allclose(qs, q, atol=1e-10)
        M, G, Hq, P2 = m.evaluate("M", q), m.evaluate("G", q), np.array(H(q, th)), np.array(phi2(q, th))
        Bt = np.hstack([G.T, m.evaluate("B", q)])
        C = np.vstack([G, Hq])
        Gam = C @ np.linalg.solve(M, Bt)
        N = np.linalg.svd(C)[2][-1:].T
        V = N @ np.linalg.inv(P2 @ N)
        v28 = np.linalg.solve(M, Bt) @ np.linalg.solve(Gam, np.concatenate([np.zeros(2), yd])) + V @ eta2
        np.testing.assert_allclose(vs, v28, rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(P2 @ np.linalg.solve(M, Bt), 0, atol=1e-12)


# ------------------------------------------------------- the printed numbers of Sect. 6 (issue 12)
def closed_form_split(p, b0, bf):
    """T^-1 Q T and T^-1 P from the closed forms (51)-(52) (C2 with 2 kappa L2), T = unit-length eigenvector
    columns with negative last entry, built by hand (no AD, no invctl linearization)."""
    L2, L3, m3, c, D, kap, dl = consts(p)
    C0 = (2 * L2 + 4 * L3) / (kap * L2)
    C1 = -L3 * m3 * (L2 + 2 * L3) / (2 * kap * L2) * (np.sin(b0) + np.sin(bf))
    C2 = (4 * kap + L2 * L3 * m3) / (2 * kap * L2) * (L2 + 2 * L3)
    Q = np.array([[0, -C0], [-c, D * C0]])
    P = Q @ np.array([[C1, C2], [-D * C1, -D * C2]])
    mu = D * C0 / 2 + np.array([-1, 1]) * np.sqrt((D * C0 / 2) ** 2 + C0 * c)
    T = np.array([[mu[1] / c, mu[0] / c], [1.0, 1.0]])      # eigenvector columns (mu1, mu2), last entry 1
    T = -T / np.linalg.norm(T, axis=0)
    return np.linalg.solve(T, Q @ T), np.linalg.solve(T, P)


def test_paper_preset_reproduces_the_printed_split_to_its_digits():
    """003 Sect. 6 prints T^-1 Q T = diag(-24.8623, 28.3917) and T^-1 P to 4 decimals: the 'paper' preset
    reproduces every entry within half a unit of the 4th decimal, both by the closed forms (51)-(52) and by
    the AD linearization the controllers use (which agree to 1e-9 relative: round-off and Newton 1e-12)."""
    from invctl.analysis.identify import linearization_features

    printed = scene.PRINTED_LINEARIZATION
    model = scene.build(**scene.PRESETS["paper"])
    ref = scene.reference(model)
    b0, bf = ref(ref.t0)[1, 0], ref(ref.tf)[1, 0]
    TQT, TP = closed_form_split(model.values, b0, bf)
    f = linearization_features(tracking_linearization(scene.SCENE, model, ref), printed["normalization"])
    for ours, ad, key in ((TQT, f["TinvQT"], "TinvQT"), (TP, f["TinvP"], "TinvP")):
        np.testing.assert_allclose(ad, ours, rtol=1e-9, atol=1e-9)
        assert np.max(np.abs(ours - np.asarray(printed[key]))) < 0.5e-4, (key, ours)
    # the printed T = [mu2/c mu1/c; 1 1] itself ("last-one") gives another T^-1 P: rows rescaled, sign flipped
    last = linearization_features(tracking_linearization(scene.SCENE, model, ref), "last-one")["TinvP"]
    assert np.all(np.sign(last) == -np.sign(np.asarray(printed["TinvP"])))
    # the defaults are this set; the former guess does not reproduce them (a different plant)
    assert {k: scene.PARAMS[k] for k in scene.PRESETS["paper"]} == dict(scene.PRESETS["paper"])
    guess = scene.build(**scene.PRESETS["guess"])
    d = linearization_features(tracking_linearization(scene.SCENE, guess, scene.reference(guess)))
    assert np.max(np.abs(d["TinvP"] - np.asarray(printed["TinvP"]))) > 100


def test_cli_analyze_preset_paper_prints_the_printed_split(capsys):
    assert main(["analyze", "manipulator", "--preset", "paper", "--samples", "20", "--json"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    data = json.loads(out[-1])
    assert data["params"]["m3"] == 3.4 and data["params"]["c"] == 50.0 and data["params"]["D"] == 0.25
    rep = data["reports"]["003 Sect. 6: T^-1 Q T and T^-1 P (printed numbers)"]
    assert rep["values"]["equal to the printed 4 decimals"] is True
    assert max(rep["differences"].values()) < 0.5e-4
    assert any("T^-1 P" in line and "paper:" in line for line in out)
    # a preset name that does not exist is a ParameterError naming the presets (exit 2)
    assert main(["analyze", "manipulator", "--preset", "papr", "--samples", "5"]) == 2
    assert "presets: guess, paper" in capsys.readouterr().err


# ------------------------------------------------------- the boundary selection (36) (issue 12)
@pytest.fixture(scope="module", params=["default", "paper"])
def inverse_modes(request):
    """The index-reduced inverse model linearized at the start and end equilibria of y_ref."""
    from invctl.inversion.boundary import tangent_dynamics
    from invctl.inversion.cache import equilibrium_solver as _equilibrium_solver, servo_model

    model = scene.build(**({} if request.param == "default" else scene.PRESETS["paper"]))
    ref = scene.reference(model)
    sv = servo_model(model)
    th = model.theta_values
    eq = _equilibrium_solver(model)
    Y = sv.reference_samples(ref, np.array([ref.t0, ref.tf]))
    out = {"model": model, "ref": ref, "servo": sv}
    for end, t, col in (("start", ref.t0, Y[:, :1]), ("end", ref.tf, Y[:, 1:])):
        E, _ = eq.solve(ref(t).ravel(), guess_q=scene.initial_configuration(model))
        A, T, _ = tangent_dynamics(sv, E, col, th)
        out[end] = (E, col, A, T)
    out["labels"] = [f"{k}:{n}" for k in ("q", "v", "lam", "mu", "u") for n in sv.names[k]]
    return out


def _gamma_coordinates(modes, end):
    """The tangent space of the constraint manifold at an equilibrium in the coordinates (gamma, gamma_dot):
    row i = how entry i of X = (q, v, lam, u) moves with (gamma, gamma_dot)."""
    T = modes[end][3]
    lab = modes["labels"]
    C = T[[lab.index("q:gamma"), lab.index("v:gamma_dot")]]
    return T @ np.linalg.inv(C)


def test_consistent_states_at_the_equilibria_depend_on_gamma_gamma_dot_as_claimed(inverse_modes):
    """The argument of issue 12, first way: at both equilibria the tangent space is 2-dim (the internal
    state); q moves with gamma only, v with gamma_dot only (every consistent velocity is proportional to
    gamma_dot), s2 and s2_dot not at all (servo constraint), and lam, u only through c gamma + D gamma_dot.
    Tolerance 1e-9 relative: a null-space basis of an exact Jacobian (round-off)."""
    lab = inverse_modes["labels"]
    c, D = inverse_modes["model"].values["c"], inverse_modes["model"].values["D"]
    for end in ("start", "end"):
        assert inverse_modes[end][3].shape[1] == 2
        R = _gamma_coordinates(inverse_modes, end)
        scale = np.abs(R).max()
        for i, name in enumerate(lab):
            if name in ("q:s2", "v:s2_dot"):
                assert np.abs(R[i]).max() < 1e-9 * scale
            elif name.startswith("q:"):
                assert abs(R[i, 1]) < 1e-9 * scale and abs(R[i, 0]) > 1e-3
            elif name.startswith("v:"):
                assert abs(R[i, 0]) < 1e-9 * scale and abs(R[i, 1]) > 1e-3
            else:   # lam, u: multiples of (c, D)
                assert R[i, 1] * c == pytest.approx(R[i, 0] * D, rel=1e-9, abs=1e-9 * scale)
                assert abs(R[i, 0]) > 1e-3


def test_every_binary_selection_fixes_both_internal_modes_at_T0(inverse_modes):
    """Second way, ranks of selected rows: the printed (36) has rank 2 on the tangent space at T0 (gamma by q,
    gamma_dot by s1_dot: the unstable mode is fixed at T0) and rank 2 at Tf (gamma and c gamma + D gamma_dot by
    lam2, u: the stable mode is fixed at Tf), while the dichotomy of the stabilized model needs 13 decaying
    modes at T0 and 1 growing mode at Tf.  Every choice of 13 entries at T0 has rank 2 there; the largest set of
    entries with rank <= 1 has 6 (s2, s2_dot and one family).  What a selection can do is keep the
    inconsistency small that the decaying constraint-drift modes absorb: |C Zs (S Zs)^-1 S W| (C the Jacobian of
    the invariants, Zs the decaying modes, W the growing one scaled to gamma = 1); the automatic plan's choice
    needs far less of it than the former hand selection."""
    import itertools

    import scipy.linalg as sla

    from invctl.inversion.boundary import resolve_selection
    from invctl.inversion.plan import plan_inversion

    sv, lab = inverse_modes["servo"], inverse_modes["labels"]
    nx = len(lab)
    T0b, Tfb = inverse_modes["start"][3], inverse_modes["end"][3]

    def rank(rows, T):
        return np.linalg.matrix_rank(np.eye(nx)[list(rows)] @ T, tol=1e-8)

    paper = resolve_selection(sv, scene.BOUNDARY_PAPER["start"], scene.BOUNDARY_PAPER["end"])
    assert (rank(paper.start, T0b), rank(paper.end, Tfb)) == (2, 2)
    assert {rank(c, T0b) for c in itertools.combinations(range(nx), nx - 1)} == {2}
    assert max(len(c) for k in range(1, 8) for c in itertools.combinations(range(nx), k) if rank(c, T0b) <= 1) == 6
    E0, Y0, A0, _ = inverse_modes["start"]
    th = inverse_modes["model"].values
    C0 = np.array(sv.constraint_jacobian(E0, Y0, inverse_modes["model"].theta_values))
    w, V = np.linalg.eig(A0)
    W = np.real(V[:, np.argmax(w.real)])
    W = W / W[lab.index("q:gamma")]
    Zs = sla.schur(A0, output="real", sort=lambda re, im: re < 0)[1][:, :nx - 1]

    def absorbed(rows):
        S = np.eye(nx)[list(rows)]
        return np.linalg.norm(C0 @ Zs @ np.linalg.solve(S @ Zs, S @ W))

    hand = resolve_selection(sv, scene.BOUNDARY["start"], scene.BOUNDARY["end"])
    plan = plan_inversion(inverse_modes["model"], inverse_modes["ref"],
                          q_guess=scene.initial_configuration(inverse_modes["model"]))
    auto = resolve_selection(sv, plan.start, plan.end)
    print(f"c = {th['c']}: absorbed inconsistency per unit unstable tail: hand {absorbed(hand.start):.4g}, "
          f"plan {absorbed(auto.start):.4g}")
    assert absorbed(auto.start) < 0.2 * absorbed(hand.start)
    assert min(absorbed(c) for c in itertools.combinations(range(nx), nx - 1)) > 1.0


def test_printed_58_has_two_signs_that_conflict_with_52_and_phi10():
    """(58) prints Psi(x) = [0,1] T^-1 (x5; +(m3 L3/2) sin(x4+x5) x7 + kappa (x9+x10) + (m3 L2 L3/4) cos(x5) x9)
    + [0,1] T^-1 P2 (x2; x4 + delta x5).  (i) The eta2 entry must be phi~10(q) v = e5^T M v, whose s2_dot
    coefficient is -(m3 L3/2) sin(beta+gamma) (as printed before (54)); only that sign satisfies L_K phi = 0,
    phi~10 M^-1 [G^T B] = 0, the condition of Lemma 3.1.  (ii) (52) subtracts P2 y: at rest (v = 0, gamma = 0)
    Psi must be the equilibrium -Q~^-1 P~ y of (40), which -[0,1] T^-1 P2 y is and the printed + is not.
    invctl's Psi is the consistent form.  Tolerances: exact formulas, round-off (1e-10 relative)."""
    model = scene.build(**scene.PRESETS["paper"])
    ref = scene.reference(model)
    lin = tracking_linearization(scene.SCENE, model, ref)
    p = model.values
    L2, L3, m3, c, D, kap, dl = consts(p)
    th = model.theta_values
    rng = np.random.default_rng(7)
    q0 = scene.initial_configuration(model)
    for _ in range(4):
        q, v = consistent_state(model, q0 + rng.uniform(-0.1, 0.1, 5), rng.uniform(-1, 1, 5))
        be, ga = q[3], q[4]
        M = model.evaluate("M", q)
        GB = np.hstack([model.evaluate("G", q).T, model.evaluate("B", q)])
        row = {s: np.array([0, s * m3 * L3 / 2 * np.sin(be + ga), 0, kap + m3 * L2 * L3 / 4 * np.cos(ga), kap])
               for s in (-1, +1)}
        np.testing.assert_allclose(row[-1], M[4], rtol=1e-12, atol=1e-12)
        scale = np.abs(np.linalg.solve(M, GB)).max() * np.abs(M[4]).max()
        assert np.abs(row[-1] @ np.linalg.solve(M, GB)).max() < 1e-12 * scale
        assert np.abs(row[+1] @ np.linalg.solve(M, GB)).max() > 1e-2 * scale
    psi = lin.psi_function()
    for t in (ref.t0, ref.tf):
        y = ref(t).ravel()
        q = np.array(lin.internal.state(y_0=y, y_1=[0, 0], eta=[0, 0], theta=th)["q"]).ravel()
        consistent = -(lin.T[1] @ lin.P_list[1] @ y)
        as_printed = +(lin.T[1] @ lin.P_list[1] @ y)
        equilibrium = -np.linalg.solve(lin.Q_tilde, lin.P_tilde @ y)[0]
        assert consistent == pytest.approx(equilibrium, rel=1e-10)
        assert float(psi(q, np.zeros(5), th)) == pytest.approx(consistent, rel=1e-10)
        assert abs(as_printed - equilibrium) > 0.5 * abs(equilibrium)


def test_scene_presets_apply_before_set_and_are_checked():
    from invctl.errors import ParameterError
    from invctl.scenes import Scene

    params, _ = scene.SCENE.split({"m3": 4.0}, preset="paper")
    assert params == {"m3": 4.0, "c": 50.0, "D": 0.25}          # --set overrides the preset
    assert scene.SCENE.split({}, preset=None) == scene.SCENE.split({})
    with pytest.raises(ParameterError, match="no preset 'x'; presets: guess, paper"):
        scene.SCENE.split({}, preset="x")
    with pytest.raises(ParameterError, match="positive"):        # preset values go through the same checks
        Scene("s", scene.build, params=scene.PARAMS, positive=("m3",), presets={"bad": {"m3": -1.0}}).split(
            {}, preset="bad")
    with pytest.raises(SceneError, match="unknown values"):
        Scene("s", scene.build, params=scene.PARAMS, presets={"p": {"nope": 1.0}})
    with pytest.raises(SceneError, match="non-numbers"):
        Scene("s", scene.build, params=scene.PARAMS, presets={"p": {"m3": float("nan")}})
    with pytest.raises(SceneError, match="identifier-like"):
        Scene("s", scene.build, params=scene.PARAMS, presets={"a b": {"m3": 1.0}})


def test_phi_prime_singular_set_in_the_region_is_data(manipulator):
    """The paper's coordinates (gamma, [0 0 0 0 1] M v): the q-block of Phi' = d(g, h, gamma)/dq has determinant
    L1 sin(alpha) (expand along s2, beta, gamma), the v-block the same, so Phi' is singular on alpha = 0, the edge
    of U_q = ... x (0, pi/2) x ...  Region samples with alpha in (0, 1e-6] (sigma_min ~ alpha^2) are counted and one is named, not an
    error (this stopped `invctl analyze manipulator --samples 100000`); samples with alpha >= 0.1 are regular."""
    q0 = scene.initial_configuration(manipulator)

    def with_alpha(lo, hi):
        model = copy.copy(manipulator)
        model.region = dataclasses.replace(manipulator.region, sample_bounds=(
            [-1.0, -1.0, lo, 0.0, -0.8], [1.0, 1.0, hi, math.pi / 2, 0.8]))
        return internal_dynamics(model, "sect3", scene.paper_internal_coordinates, point=q0, samples=40).checks

    near = with_alpha(0.0, 1e-6)
    assert near["Phi_singular_count"] == 40 and near["Phi_invertible_fraction_region"] == 0.0
    assert 0.0 <= near["Phi_singular_sample"][2] <= 1e-6 and near["Phi_sigma_min_region"] < 1e-10
    assert near["Phi_sigma_min"] > 1e-3           # the design point (alpha0 = 0.6435) is regular
    away = with_alpha(0.1, 1.5)
    assert away["Phi_singular_count"] == 0 and away["Phi_singular_sample"] is None
