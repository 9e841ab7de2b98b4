"""The flexible arm in Cartesian coordinates (``coordinates="cartesian"``: (x_i, y_i, theta_i) per link,
constant diagonal M, 2n pin constraints) against the closed-form model in absolute angles: the same
physics by two constructions (invctl_scenes/flexible_arm.py).  Compared through what the library computes
from each (internal dynamics, stable inverse) and by a forward simulation with scipy, so a wrong
constraint, spring sign, damping or input column of either model shows up."""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.integrate import solve_ivp

import invctl_scenes.flexible_arm as fa
from invctl.cli import main
from invctl.errors import ParameterError, SceneError
from invctl.inversion import forward_check, invert
from invctl.scenes import Scene, load_scene
from test_gallery import internal_eigenvalues_at as internal_eigenvalues  # the same linearization check


def angle_twin(n, **params):
    return fa.build(n=n, **params), fa.build(n=n, coordinates="cartesian", **params)


def test_cartesian_model_structure():
    """3n coordinates, 2n constraints satisfied by the mapped configuration, constant diagonal M; M of the
    angles is J^T M J (J = d(Cartesian)/d(theta)) at random configurations (round-off)."""
    n = 3
    A, C = angle_twin(n)
    assert (A.n, A.ell) == (n, 0) and (C.n, C.ell, C.m) == (3 * n, 2 * n, 1)
    rng = np.random.default_rng(3)
    l = C.values["l"]
    for _ in range(5):
        th = rng.uniform(-1, 1, n)
        q = fa.cartesian_configuration(n, th, l)
        assert np.max(np.abs(C.evaluate("g", q))) < 1e-15
        np.testing.assert_allclose(C.evaluate("h", q), A.evaluate("h", th), rtol=1e-14)
        # J by central differences of the map theta -> q (exact up to 1e-9 here)
        J = np.column_stack([(fa.cartesian_configuration(n, th + 1e-6 * e, l)
                              - fa.cartesian_configuration(n, th - 1e-6 * e, l)) / 2e-6 for e in np.eye(n)])
        np.testing.assert_allclose(J.T @ C.evaluate("M", q) @ J, A.evaluate("M", th), rtol=1e-8, atol=1e-12)
        assert np.max(np.abs(C.evaluate("G", q) @ J)) < 1e-8  # J spans the tangent space of g = 0
    Mc = C.evaluate("M", fa.initial_configuration(C))
    assert np.count_nonzero(Mc - np.diag(np.diag(Mc))) == 0


@pytest.mark.parametrize("n", [2, 3, 4])
def test_internal_eigenvalues_agree(n):
    """The linearized internal dynamics (the transmission zeros) at the hanging arm: 1e-8 relative
    (measured 2e-15 .. 6e-14), with one real unstable zero in both."""
    A, C = angle_twin(n)
    ea = internal_eigenvalues(A, np.zeros(n))
    ec = internal_eigenvalues(C, fa.initial_configuration(C))
    assert ea.size == ec.size == 2 * n - 2
    assert np.max(np.abs(ea - ec) / np.maximum(1.0, np.abs(ea))) < 1e-8
    assert np.sum(ec.real > 0) == 1


def _inverses(n, N):
    A, C = angle_twin(n)
    ra, rc = fa.reference(A), fa.reference(C)
    auto = invert(A, ra, q_guess=np.zeros(n), N=N)  # the automatic horizon (its mesh is graded)
    hor = {"T0": auto.diagnostics["T0"], "Tf": auto.diagnostics["Tf"]}
    ia = invert(A, ra, q_guess=np.zeros(n), N=N, **hor)  # both on the same piecewise uniform mesh
    ic = invert(C, rc, q_guess=fa.initial_configuration(C), N=N, **hor)
    return A, C, ra, ia, ic, hor


@pytest.mark.parametrize("n", [2, 3])
def test_stable_inverse_feedforward_agrees(n):
    """u_ff of invert() on the same horizon and mesh (Hermite-Simpson, N = 200): the two formulations
    differ by less than 5 % of the discretization error of either (estimated by N = 100 against 200) and
    less than 1e-6 of max |u| (measured: 4e-11 and 3e-11 against discretization errors of 3e-8 and 5e-7).
    Different collocation equations (an ODE against an index-reduced DAE) agreeing far below the mesh error
    means they discretize the same continuous inverse."""
    A, C, ra, ia, ic, hor = _inverses(n, 200)
    coarse = invert(A, ra, q_guess=np.zeros(n), N=100, **hor)
    t = np.linspace(hor["T0"], hor["Tf"], 1501)
    ua, uc = ia.u(t).ravel(), ic.u(t).ravel()
    disc = np.max(np.abs(coarse.u(t).ravel() - ua))
    diff = np.max(np.abs(ua - uc))
    assert disc > 0
    assert diff < 0.05 * disc and diff < 1e-6 * np.max(np.abs(ua)), (diff, disc)
    # the constraint forces of the Cartesian inverse hold the shoulder: lam is not trivially zero
    assert ic.diagnostics["iterations"] >= 1


def _simulate_cartesian(C, u, t0, t1, q0):
    """scipy DOP853 on the index-1 form of the Cartesian model (the library's accel_and_multipliers)
    under the input u(t), from rest at q0."""
    acc, th = C.accel_and_multipliers, C.theta_values
    k = C.n

    def rhs(t, x):
        a = np.array(acc(x[:k], x[k:], u(t), th)[0]).ravel()
        return np.concatenate([x[k:], a])

    return solve_ivp(rhs, (t0, t1), np.concatenate([q0, np.zeros(k)]), method="DOP853", rtol=1e-11, atol=1e-13,
                     dense_output=True)


def test_cartesian_forward_simulation_with_angle_feedforward():
    """n = 3: the Cartesian model simulated from rest at T0 under the feedforward computed on the angle
    model follows y_ref to 1e-6 of the move (like the angle model's own forward check; measured ~5e-10),
    and the pin constraints stay closed (drift < 1e-8 m).  A wrong spring, damping or input in either
    model would leave O(1e-3) errors."""
    n = 3
    A, C = angle_twin(n)
    ref = fa.reference(A)
    ia = invert(A, ref, q_guess=np.zeros(n))
    T0 = ia.diagnostics["T0"]
    t1 = ref.tf + 0.1 * (ref.tf - ref.t0)
    sol = _simulate_cartesian(C, lambda t: float(ia.u(t).ravel()[0]), T0, t1, fa.initial_configuration(C))
    assert sol.success
    t = np.linspace(T0, t1, 801)
    X = sol.sol(t)
    y = np.array([C.evaluate("h", X[:C.n, i]).item() for i in range(t.size)])
    err = np.max(np.abs(y - ref(t).ravel()))
    own = forward_check(A, ia, ref)["error"]
    move = 0.05
    assert err < 1e-6 * move, (err, own)
    drift = max(np.max(np.abs(C.evaluate("g", X[:C.n, i]))) for i in range(0, t.size, 40))
    assert drift < 1e-8


def test_coordinates_choice_is_validated():
    """``coordinates`` takes one of the declared words; anything else is a ParameterError (nothing is
    evaluated), from the scene, the build function and the command line."""
    scene = load_scene("flexible_arm")
    assert scene.choices["coordinates"] == ("angles", "cartesian")
    params, _ = scene.split({"coordinates": "cartesian", "n": 2})
    assert params == {"coordinates": "cartesian", "n": 2.0}
    assert scene.model(params).ell == 4
    assert scene.model({}).ell == 0  # default: the angle formulation, unchanged
    for bad in ("polar", 1.0, "Cartesian"):
        with pytest.raises(ParameterError, match="coordinates must be one of angles, cartesian"):
            scene.split({"coordinates": bad})
    with pytest.raises(ParameterError, match="coordinates must be one of"):
        fa.build(coordinates="polar")
    with pytest.raises(ParameterError, match="is not a number"):
        scene.split({"m": "heavy"})


def test_cli_coordinates(capsys):
    assert main(["analyze", "flexible_arm", "--set", "coordinates=polar", "--json"]) == 2
    data = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert data["error"] == "ParameterError" and "coordinates must be one of" in data["message"]
    assert main(["analyze", "flexible_arm", "--set", "coordinates=__import__('os')"]) == 2
    assert "is not a number" in capsys.readouterr().err
    assert main(["analyze", "flexible_arm", "--set", "coordinates=cartesian", "--set", "n=2", "--json"]) == 0
    out = capsys.readouterr().out
    assert "n = 6, l = 4" in out


def test_scene_choices_declaration_is_checked():
    """A choice needs identifier-like words and may not shadow a parameter."""
    build = fa.build
    for bad in ({"coordinates": ()}, {"coordinates": ("angles", "angles")}, {"coordinates": ("a b",)},
                {"n": ("x",)}):
        with pytest.raises(SceneError):
            Scene("arm", build, params={"n": 3}, choices=bad)


def test_cartesian_coordinates_beyond_the_memory_limit_are_rejected_before_any_work():
    from invctl.errors import ParameterError
    from invctl.scenes import load_scene

    scene = load_scene("flexible_arm")
    scene.split({"n": 10, "coordinates": "cartesian"})  # accepted
    with pytest.raises(ParameterError, match="limited to n <= 10.*coordinates=angles"):
        scene.split({"n": 16, "coordinates": "cartesian"})
    scene.split({"n": 32})  # angles: no limit
