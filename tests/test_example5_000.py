"""000 Example 5: the slider-crank with play in the prismatic joint J4 and the four-bar with a clearance at
J4.  The gaps and the Delassus matrices are checked against hand-written numpy kinematics (positions by
trigonometry, Jacobians and the mass matrix by central differences), Corollary 1 / Lemma 1 against the
paper's statements, and the pre-loading law (13) by the multipliers the time-stepping LCP returns."""
import json
import math

import numpy as np
import pytest

import invctl_scenes.fourbar_clearance as fc
import invctl_scenes.slider_crank_prismatic_play as sp
from invctl.contact.structure import open_structure
from invctl.control.preload import preload_check, preload_terms
from invctl.errors import PreloadInfeasible
from invctl.scenes import load_scene
from invctl.studies.contact import contact_setup, run_contact


def _jac(fun, q, dq=1e-6):
    q = np.asarray(q, float)
    cols = [(np.asarray(fun(q + dq * e)) - np.asarray(fun(q - dq * e))) / (2 * dq) for e in np.eye(q.size)]
    return np.array(cols).T.reshape(-1, q.size)


def _mass(bodies, q):
    """``sum m Jc^T Jc + I Jw^T Jw`` for bodies ``(mass, inertia, com(q), angle row)``."""
    M = np.zeros((q.size, q.size))
    for m, inertia, com, w in bodies:
        J = _jac(com, q)
        M += m * J.T @ J + inertia * np.outer(w, w)
    return M


# ---------------------------------------------------------------- slider-crank, play in J4
def _sc_points(p, q):
    a1, a2 = q[0], q[0] + q[1]
    a3 = a2 + q[2]
    A = p["r"] * np.array([math.cos(a1), math.sin(a1)])
    S = A + p["Lr"] * np.array([math.cos(a2), math.sin(a2)])
    R = np.array([[math.cos(a3), -math.sin(a3)], [math.sin(a3), math.cos(a3)]])
    return A, S, R


def _sc_gaps(p, q):
    """The four corner gaps by hand: faces at y = +-(sw + c), corners of the tilted slider."""
    _, S, R = _sc_points(p, q)
    face = p["sw"] + p["c"]
    out = []
    for sx in (1, -1):                                   # front, back
        top = (S + R @ [sx * p["sl"], p["sw"]])[1]
        bot = (S + R @ [sx * p["sl"], -p["sw"]])[1]
        out += [face - top, bot + face]
    return np.array(out)


def _sc_mass(p, q):
    mc, mr, ms = p["rho"] * p["r"], p["rho"] * p["Lr"], p["ms"]
    return _mass([(mc, mc * p["r"] ** 2 / 12, lambda x: _sc_points(p, x)[0] / 2, [1, 0, 0]),
                  (mr, mr * p["Lr"] ** 2 / 12, lambda x: (_sc_points(p, x)[0] + _sc_points(p, x)[1]) / 2, [1, 1, 0]),
                  (ms, ms * (p["sl"] ** 2 + p["sw"] ** 2) / 3, lambda x: _sc_points(p, x)[1], [1, 1, 1])], q)


def _model_gaps(model, q):
    import casadi as ca

    f = ca.Function("g", [model.q, model.theta], [ca.vertcat(*[g.expr for g in model.gaps])])
    return np.array(f(q, model.theta_values)).ravel()


def test_slider_crank_gaps_against_the_corners_by_hand():
    """n = 3, m_u = 4 (000 Example 5); the four gaps equal the corners' distances to the guide's faces at
    random configurations (1e-15 m), and vanish in pairs on the two faces."""
    model = sp.build()
    p = model.values
    assert model.n == 3 and len(model.gaps) == 4
    rng = np.random.default_rng(5)
    q0 = sp.configuration(model, 0.5, -1)
    for _ in range(20):
        q = q0 + rng.uniform(-0.01, 0.01, 3)
        np.testing.assert_allclose(_model_gaps(model, q), _sc_gaps(p, q), atol=1e-15)
    for side, kept in ((-1, [3, 1]), (1, [2, 0])):
        g = _sc_gaps(p, sp.configuration(model, 1.2, side))
        assert np.abs(g[kept]).max() < 1e-15 and np.allclose(np.delete(g, kept), 2 * p["c"], atol=1e-15)
        assert sorted(sp.CORNERS[1 if side == -1 else 2][1]) == sorted(kept)


@pytest.mark.parametrize("actuators", [1, 2, 3])
def test_slider_crank_corollary_1_and_the_delassus_matrix(actuators):
    """Corners A, B closed: the Delassus matrix (7) equals grad f'^T M^-1 grad f' from the numpy mass matrix
    and corner Jacobians (1e-7), it is positive definite with equal diagonal entries (the corners lie
    symmetrically about the slider's centre), and E_hat has rank 2 = m_u' exactly when p >= 2: with the
    crank torque alone (full actuation of the clearance-free slider-crank) Corollary 1 fails, as 000 says."""
    model = sp.build(actuators=actuators)
    p = model.values
    q = sp.configuration(model, 0.8, -1)
    kept = sp.CORNERS[1][1]
    import casadi as ca

    _, _, D, _ = preload_terms(model, kept)
    D = np.array(ca.Function("D", [model.q, model.theta], [D])(q, model.theta_values))
    J = _jac(lambda x: _sc_gaps(p, x)[kept], q)
    M = _sc_mass(p, q)
    D_hand = J @ np.linalg.solve(M, J.T)
    np.testing.assert_allclose(D, D_hand, rtol=1e-7)
    assert np.linalg.eigvalsh(D).min() > 0 and abs(D[0, 0] - D[1, 1]) < 1e-12 * D[0, 0]
    E = np.eye(3)[:, [int(j[1]) - 1 for j in sp.ACTUATED[actuators]]]   # J_k drives theta_J_k (theta_crank for J1)
    Ehat_hand = np.linalg.solve(D_hand, J @ np.linalg.solve(M, E))
    chk = preload_check(model, q, np.zeros(3), kept, raise_=False)
    np.testing.assert_allclose(chk.E_hat, Ehat_hand, rtol=1e-6, atol=1e-9)
    assert chk.rank == min(actuators, 2) == np.linalg.matrix_rank(Ehat_hand)
    if actuators == 1:
        with pytest.raises(PreloadInfeasible, match="Corollary 1"):
            preload_check(model, q, np.zeros(3), kept)
    st = open_structure(model, q)
    assert st.n == 3 and st.n_ind == 1


def _run(name, values, controller):
    scene = load_scene(name)
    params, settings = scene.split(values)
    return run_contact(contact_setup(scene, params, settings, controller=controller), progress=False)


def test_slider_crank_preloading_keeps_corners_a_b_closed():
    """Pre-loading (13) with p = 3: at every step the LCP's multipliers of corners A, B equal beta (1e-3
    relative), they stay closed up to the drift of the unprojected velocity-level scheme (1.5 % of the play
    c), the other corners stay open by the full play 2c, there is no impact, and the free part
    turns the crank towards crank_d.  PD (36) on the crank alone (p = 1) lets the slider cross to the upper
    face (impacts there): without pre-loading the contact at A, B is not kept."""
    run = _run("slider_crank_prismatic_play", {"t_end": 0.5}, "preload")
    tr, s = run.trajectory, run.settings
    kept = sp.CORNERS[1][1]
    lam = tr.P[kept, 1:] / tr.h
    np.testing.assert_allclose(lam, s["beta"], rtol=1e-3)
    assert np.abs(tr.gaps[kept]).max() < 2e-2 * run.model.values["c"]  # drift of the velocity-level scheme
    assert np.delete(tr.gaps, kept, axis=0).min() > 1.99 * run.model.values["c"]
    assert tr.impact_mask().sum() == 0 and tr.q[0, -1] > s["crank0"] + 0.3
    pd = _run("slider_crank_prismatic_play", {"t_end": 0.5, "actuators": 1}, "pd").trajectory
    assert pd.gaps[kept].max() > 1.99 * run.model.values["c"] and pd.impact_mask().sum() >= 1


# ---------------------------------------------------------------- four-bar, clearance at J4
def _fb_points(p, q):
    a1, a2 = q[0], q[0] + q[1]
    a3 = a2 + q[2]
    B = p["b"] * np.array([math.cos(a1), math.sin(a1)])
    C = B + p["c"] * np.array([math.cos(a2), math.sin(a2)])
    P = C - p["d"] * np.array([math.cos(a3), math.sin(a3)])
    return B, C, P, a3


def _fb_gap(p, q):
    P = _fb_points(p, q)[2]
    return np.array([(p["cl"] ** 2 - np.sum((P - [p["a"], 0.0]) ** 2)) / (2 * p["cl"])])


def _fb_mass(p, q):
    m = {k: p["rho"] * p[k] for k in "bcd"}

    def com(k):
        def f(x):
            B, C, P, _ = _fb_points(p, x)
            return {"b": B / 2, "c": (B + C) / 2, "d": (P + C) / 2}[k]
        return f
    return _mass([(m["b"], m["b"] * p["b"] ** 2 / 12, com("b"), [1, 0, 0]),
                  (m["c"], m["c"] * p["c"] ** 2 / 12, com("c"), [1, 1, 0]),
                  (m["d"], m["d"] * p["d"] ** 2 / 12, com("d"), [1, 1, 1])], q)


def test_fourbar_gap_delassus_and_lemma_1_against_numpy():
    """n = 3, m_u = 1 (000 Example 5); the journal gap equals (cl^2 - |P - D|^2) / (2 cl) with P by hand
    (1e-15 m); D (7) and E_hat (11) equal the numpy computation (1e-7); with the crank torque alone (p = 1,
    enough by Corollary 1) E_hat changes sign twice per crank turn: Lemma 1 fails at two crank angles."""
    model = fc.build(actuators=1)
    p = model.values
    assert model.n == 3 and len(model.gaps) == 1
    q0 = fc.configuration(model, 0.5)
    assert abs(_fb_gap(p, q0)[0]) < 1e-15
    rng = np.random.default_rng(4)
    for _ in range(10):
        q = q0 + rng.uniform(-0.01, 0.01, 3)
        np.testing.assert_allclose(_model_gaps(model, q), _fb_gap(p, q), atol=1e-15)
    import casadi as ca

    Ehat, _, D, _ = preload_terms(model, [0])
    fn = ca.Function("e", [model.q, model.theta], [Ehat, D])
    signs = []
    for th in np.linspace(0, 2 * np.pi, 73)[:-1]:
        q = fc.configuration(model, th)
        J = _jac(lambda x: _fb_gap(p, x), q)
        M = _fb_mass(p, q)
        D_hand = J @ np.linalg.solve(M, J.T)
        E_hand = np.linalg.solve(D_hand, J @ np.linalg.solve(M, np.eye(3)[:, :1]))
        E, Dm = (np.array(x) for x in fn(q, model.theta_values))
        np.testing.assert_allclose(Dm, D_hand, rtol=1e-7)
        np.testing.assert_allclose(E, E_hand, rtol=1e-6, atol=1e-9)
        signs.append(np.sign(E_hand[0, 0]))
    assert np.count_nonzero(np.diff(np.r_[signs, signs[0]])) == 2
    from invctl.scenes import ReportContext

    rep = fc.lemma1_report(ReportContext(load_scene("fourbar_clearance"), model, {"actuators": 1}, fc.SETTINGS))
    flips = rep["crank turn: E_hat changes sign near crank angles [rad] (Lemma 1 fails there)"]
    assert len(flips) == 2 and all(np.sign(E_at(model, th - 0.01)) != np.sign(E_at(model, th + 0.01)) for th in flips)


def E_at(model, crank):
    return preload_check(model, fc.configuration(model, crank), np.zeros(3), [0], raise_=False).E_hat[0, 0]


def test_fourbar_preloading_keeps_the_journal_on_the_bearing():
    """Pre-loading (13) with p = 2: the journal stays on the bearing (|f| below 2e-5 of the clearance), the
    LCP's multiplier equals beta at 90 % of the steps and on average over every 100 steps (2 %); PD (36)
    on the crank alone lets the journal leave the bearing."""
    run = _run("fourbar_clearance", {"t_end": 0.5}, "preload")
    tr, beta, cl = run.trajectory, run.settings["beta"], run.model.values["cl"]
    lam = tr.P[0, 1:] / tr.h
    assert np.abs(tr.gaps[0]).max() < 2e-5 * cl
    assert np.mean(np.abs(lam - beta) <= 1e-3 * beta) > 0.9
    np.testing.assert_allclose(lam[:lam.size // 100 * 100].reshape(-1, 100).mean(axis=1), beta, rtol=0.02)
    from invctl.scenes import ReportContext

    rep = fc.lemma1_report(ReportContext(load_scene("fourbar_clearance"), run.model, {}, run.settings, tr, "preload"))
    E0 = preload_check(run.model, tr.q[:, 0], tr.v[:, 0], [0], raise_=False).E_hat
    assert rep["along the run: smallest |E_hat|"] <= np.linalg.norm(E0) + 1e-12  # the start is on the run
    pd = _run("fourbar_clearance", {"t_end": 0.5, "actuators": 1}, "pd").trajectory
    assert pd.gaps[0].max() > 0.1 * cl and pd.impact_mask().sum() >= 1


@pytest.mark.parametrize("name, skipped", [("slider_crank_prismatic_play", "actuators=1"),
                                           ("fourbar_clearance", "actuators=1")])
def test_example_5_through_pipeline(name, skipped, tmp_path, capsys):
    """Both mechanisms through ``invctl pipeline``: the pre-loading run with its report, PD skipped (it
    needs the crank torque alone), and ``analyze`` with the open system beside 000's n and m_u."""
    from invctl.cli import main

    assert main(["pipeline", name, "--t-end", "0.1", "--no-animation", "--out-dir", str(tmp_path), "--json"]) == 0
    d = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert list(d["runs"]) == ["preload"] and skipped in d["skipped"]["pd"]
    assert d["runs"]["preload"]["reports"] and (tmp_path / "run_preload.png").stat().st_size > 0
    assert main(["analyze", name, "--json"]) == 0
    d = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    rep = d["reports"]["000 Sect. 2: open system"]
    assert rep["values"]["n (open system)"] == 3 and rep["values"]["n_ind"] == 1
    assert all(v == 0 for v in rep["differences"].values())
