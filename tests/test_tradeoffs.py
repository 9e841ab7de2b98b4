"""``invctl study tradeoff <scene>`` for every scene with a spec, in smoke mode (INVCTL_SMOKE=1).

Each test checks the JSON contract (rows with knob, value, error, time_s; a
reference) and that the error falls with the knob the way theory says; never
wall time.
"""
import json
import math

import numpy as np
import pytest

from invctl.cli import main
from invctl.errors import SceneError
from invctl.scenes import load_scene
from invctl.studies.tradeoff_specs import fitted_order, jobs_of, spec_for


def _study(scene, tmp_path, capsys, monkeypatch, *extra):
    monkeypatch.setenv("INVCTL_SMOKE", "1")
    out = tmp_path / "out"
    assert main(["study", "tradeoff", scene, "--out-dir", str(out), "--json", "--quiet", *extra]) == 0
    data = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert data["reference"] and not data["failures"]
    for row in data["rows"]:
        assert {"knob", "value", "error", "time_s"} <= set(row)
        assert np.isfinite(row["error"]) and row["time_s"] > 0
    for ext in ("csv", "json", "png"):
        assert (out / f"tradeoff_{data['scene']}.{ext}").stat().st_size > 0
    return data


def _knob_error(data):
    return np.array([r["value"] for r in data["rows"]], float), np.array([r["error"] for r in data["rows"]])


@pytest.mark.parametrize("scene", ["cartpole", "two_link_arm", "knife_edge"])
def test_analysis_sampling_tradeoff(scene, tmp_path, capsys, monkeypatch):
    data = _study(scene, tmp_path, capsys, monkeypatch, "--job", "analyze")
    n, err = _knob_error(data)
    # the reference is the region's minimum: no sample may undercut it (1e-9: SLSQP tolerance)
    assert err.min() >= -1e-9
    assert np.all(np.diff(err) < 0)
    # random search for a smooth minimum: excess ~ n^(-2/d) (interior) to n^(-1/d) (face of the
    # box); Gamma depends on one or two coordinates here, so the slope is between -2 and -1
    assert fitted_order(n, err) < -0.8


@pytest.mark.parametrize("scene", ["stiff_wall", "compliant_wrist"])
def test_switched_sampling_tradeoff(scene, tmp_path, capsys, monkeypatch):
    data = _study(scene, tmp_path, capsys, monkeypatch)
    h, err = _knob_error(data)
    assert np.all(np.diff(err) < 0)
    # trapezoidal quadrature of a force with kinks at the (exact) events: order 1 to 2 in h
    assert 0.8 < fitted_order(h, err) < 2.5
    for row in data["rows"]:
        # events and the peak force are exact at every sampling step
        assert row["event_time_error"] < 1e-9
        assert row["peak_force_error"] < 1e-8


def test_closed_loop_tolerance_tradeoff(tmp_path, capsys, monkeypatch):
    data = _study("manipulator", tmp_path, capsys, monkeypatch, "--job", "simulate")
    assert data["scene"] == "manipulator_simulate"
    rtol, err = _knob_error(data)
    assert np.all(np.diff(err) < 0)
    # CVODES controls the local error: the global error stays within a modest factor of rtol
    assert np.all(err <= 100 * rtol)
    assert fitted_order(rtol, err) > 0.5


def test_inversion_mesh_tradeoff(tmp_path, capsys, monkeypatch):
    data = _study("manipulator", tmp_path, capsys, monkeypatch)
    rows = data["rows"]
    hs = sorted((r["value"]["N"], r["error"]) for r in rows if r["value"]["scheme"] == "hermite-simpson")
    assert [n for n, _ in hs] == [40, 80]
    # Hermite-Simpson is 4th order in the states (3rd in the collocated derivative): halving the
    # mesh must cut the forward-check error at least 2^2 = 4 times
    assert hs[0][1] / hs[1][1] > 4
    assert all(r["build_s"] + r["solve_s"] == pytest.approx(r["time_s"]) for r in rows)
    assert {r["value"]["scheme"] for r in rows} == {"hermite-simpson", "radau3"}


@pytest.mark.parametrize("scene", ["bouncing_ball", "prismatic_clearance"])
def test_contact_impacts_tradeoff(scene, tmp_path, capsys, monkeypatch):
    """Impact times and post-impact velocities against the closed form (ball) or the event-driven run."""
    data = _study(scene, tmp_path, capsys, monkeypatch, "--job", "impacts")
    h, err = _knob_error(data)
    assert np.all(np.diff(err) < 0)
    # Moreau-Jean is first order in h for impact times and post-impact velocities (000 Sect. 4)
    assert 0.6 < fitted_order(h, err) < 1.6


def test_bouncing_ball_tradeoff_runs_to_rest_against_the_closed_form(tmp_path, capsys, monkeypatch):
    """The ball's default study covers the whole bouncing sequence to rest: the closed-form rest time is
    sqrt(2H/g) (1 + 2e/(1-e)) (typed here, 1e-15), every run comes to rest, the error (rest time and the
    impact times every setting resolves, against the closed form) falls strictly from the coarsest to the
    finest step while the number of steps grows 4x per setting (64x overall), first order in h."""
    from invctl.studies.tradeoff import run_tradeoff

    data = _study("bouncing_ball", tmp_path, capsys, monkeypatch)
    assert data["scene"] == "bouncing_ball" and "rest" in data["reference"]
    assert next(iter(jobs_of(load_scene("bouncing_ball")))) == "rest"
    scene = load_scene("bouncing_ball")
    p, s = scene.params, scene.settings
    rest = math.sqrt(2 * s["H"] / p["g"]) * (1 + 2 * p["e"] / (1 - p["e"]))
    assert abs(scene.contact.exact_rest(scene.model({}), s) - rest) < 1e-15 * rest
    res = run_tradeoff(spec_for(scene, {}, dict(s)), progress=False, max_repeats=1)
    h, err = np.array([r["value"] for r in res.rows]), res.errors
    steps = np.array([r["steps"] for r in res.rows])
    assert np.all(np.diff(h) < 0) and np.all(np.diff(err) < 0) and np.all(steps[1:] > 3.99 * steps[:-1])
    assert all(abs(r["rest_time"] - rest) == r["rest_time_error"] < 1e-2 for r in res.rows)
    assert 0.6 < fitted_order(h, err) < 1.6


@pytest.mark.parametrize("scene,order", [("gear_backlash", 1.5), ("slider_crank_clearance", 0.5)])
def test_clearance_fine_step_tradeoff(scene, order, tmp_path, capsys, monkeypatch):
    data = _study(scene, tmp_path, capsys, monkeypatch)
    h, err = _knob_error(data)
    assert np.all(np.diff(err) < 0)
    # gear train: persistent pre-loaded contact, smooth motion, theta = 1/2 -> second order;
    # slider-crank: impacts in the journal clearance -> at best first order, the impact
    # sequence shifts with h, so only a positive order is claimed
    assert fitted_order(h, err) > order


def test_every_shipped_scene_has_a_study():
    import pkgutil

    import invctl_scenes as problems

    names = sorted(m.name for m in pkgutil.iter_modules(problems.__path__) if not m.name.startswith("_"))
    missing = [n for n in names if not jobs_of(load_scene(n))]
    assert not missing


def test_scene_without_spec_is_explained(tmp_path):
    path = tmp_path / "plain.py"
    path.write_text("from invctl.scenes import Scene\nfrom invctl_scenes.cartpole import build, PARAMS\n"
                    "SCENE = Scene('plain', build, params=PARAMS)\n")
    with pytest.raises(SceneError, match="offers no speed-versus-accuracy study"):
        spec_for(load_scene(str(path)), {}, {}, smoke=True)


def test_unknown_job_is_explained():
    with pytest.raises(SceneError, match="choose one of"):
        spec_for(load_scene("manipulator"), {}, {}, smoke=True, job="pipeline")


def test_library_call_returns_the_cli_data(tmp_path, capsys, monkeypatch):
    from invctl.studies.tradeoff import run_tradeoff

    data = _study("gear_backlash", tmp_path, capsys, monkeypatch)
    scene = load_scene("gear_backlash")
    res = run_tradeoff(spec_for(scene, {}, dict(scene.settings), smoke=True), progress=False)
    lib = res.to_dict()
    assert lib["reference"] == data["reference"] and lib["knob"] == data["knob"]
    assert [r["value"] for r in lib["rows"]] == [r["value"] for r in data["rows"]]
    # errors are deterministic (same compiled loop, same steps); times are not compared
    np.testing.assert_allclose([r["error"] for r in lib["rows"]], [r["error"] for r in data["rows"]], rtol=1e-12)
    best = res.recommend(1e-6)
    assert best is not None and best["error"] <= 1e-6
    assert best["time_s"] == min(r["time_s"] for r in lib["rows"] if r["error"] <= 1e-6)
