"""The generic commands on every kind of scene: pipelines, animations, scene files given by path.

What is checked is what the commands promise for any scene (runs inside their funnels, files written,
the same numbers whether a scene is shipped or given by path), with the numbers of the scenes' own
tests elsewhere.
"""
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from invctl.cli import main
from invctl.simulate.closed_loop import ClosedLoopResult


def _json(capsys):
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


@pytest.mark.parametrize("scene, animate", [("cartpole", True), ("two_link_arm", False)])
def test_tracking_pipeline_on_a_scene_without_hand_picked_numerics(scene, animate, tmp_path, capsys):
    """No boundary selection, horizon, gains or funnels declared: all derived; C1 and C2 stay inside
    their funnels on the declared plant mismatch and the feedforward helps (C1 < C2 < C3). Animations only
    with ``--animate``; the files listed are those this run wrote (not an earlier run's in the folder)."""
    stale = tmp_path / "notes_of_an_earlier_run.txt"
    stale.write_text("earlier")
    os.utime(stale, (1e9, 1e9))
    assert main(["pipeline", scene, "--out-dir", str(tmp_path), "--quiet", "--json"] + ["--animate"] * animate) == 0
    data = _json(capsys)
    runs = data["runs"]
    for name in ("C1", "C2"):
        assert runs[name]["status"] == "ok" and runs[name]["max_funnel_ratio"] < 1
    e = [runs[c]["cumulative_output_error"] for c in ("C1", "C2", "C3")]
    assert e[0] < e[1] < e[2]
    for name in ("C1", "C2", "C3"):
        assert (tmp_path / f"run_{name}.npz").exists()
    anims = sorted(p.name for p in tmp_path.glob("anim_*"))
    assert anims == (sorted(f"anim_{name}.gif" for name in runs) if animate else []) and len(runs) >= 3
    assert all(p.stat().st_size > 0 for p in tmp_path.glob("anim_*"))
    for fig in ("states", "errors", "inputs", "funnel"):
        assert (tmp_path / f"{fig}.png").exists() and f"{fig}.png" in data["files"]
    assert stale.name not in data["files"] and "run_C1.npz" in data["files"]


def test_animate_a_saved_run(tmp_path, capsys):
    from PIL import Image

    assert main(["simulate", "cartpole", "--controller", "C2", "--quiet", "--out", str(tmp_path / "run.npz")]) == 0
    capsys.readouterr()
    run = ClosedLoopResult.load(tmp_path / "run.npz")
    assert run.meta["scene"] == "cartpole" and run.meta["controller"] == "C2"
    assert main(["animate", str(tmp_path / "run.npz"), "--fps", "10", "--json"]) == 0
    out = Path(_json(capsys)["out"])
    with Image.open(out) as im:
        # frames at uniform times over the run: duration x fps + 1
        assert im.n_frames == int(round(run.t[-1] * 10)) + 1
    assert main(["animate", str(tmp_path / "run.npz")]) == 2  # exists: --force needed
    assert "exists" in capsys.readouterr().err


def test_contact_and_switched_pipelines(tmp_path, capsys):
    assert main(["pipeline", "bouncing_ball", "--set", "t_end=1.5", "--out-dir", str(tmp_path / "b"), "--json",
                 "--animate"]) == 0
    data = _json(capsys)
    none = data["runs"]["none"]
    assert none["n_impacts"] >= 2 and none["max_energy_increase"] <= 1e-12
    assert (tmp_path / "b" / "anim_none.gif").exists()
    assert main(["pipeline", "stiff_wall", "--out-dir", str(tmp_path / "w"), "--json"]) == 0
    data = _json(capsys)
    assert data["runs"]["switched"]["bounces"] >= 1 and not data["design"]["guas"]
    assert {"design.png", "run_switched.png", "run_switched.npz"} <= set(data["files"])


@pytest.mark.parametrize("actuators, ran, skipped", [
    (1, ["pd", "preload", "switching", "juggling_design"], ["juggling"]),
    (2, ["preload", "juggling"], ["pd", "switching", "juggling_design"])])
def test_a_contact_pipeline_runs_the_controllers_that_fit(actuators, ran, skipped, tmp_path, capsys):
    """Each controller declares the actuators it needs (``Contact.requires``): the pipeline runs those that
    fit the values given and says which it skipped and why (JSON and text)."""
    argv = ["pipeline", "prismatic_clearance", "--set", f"actuators={actuators}", "--t-end", "0.05",
            "--no-animation", "--quiet", "--out-dir", str(tmp_path)]
    assert main(argv + ["--json"]) == 0
    data = _json(capsys)
    assert list(data["runs"]) == ran and sorted(data["skipped"]) == sorted(skipped)
    for name in skipped:
        assert f"needs actuators={3 - actuators}" in data["skipped"][name]
        assert f"--set actuators={3 - actuators}" in data["skipped"][name]
        assert not (tmp_path / f"run_{name}.npz").exists()
    assert all((tmp_path / f"run_{name}.npz").exists() for name in ran)
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert all(f"skipped controller '{name}' needs actuators" in text for name in skipped)


def test_a_contact_requirement_is_checked_by_the_library(tmp_path):
    from invctl.errors import SceneError
    from invctl.scenes import Contact, Scene
    from invctl.studies import commands
    from invctl_scenes import prismatic_clearance as pc

    c = pc.SCENE.contact
    with pytest.raises(SceneError, match="not one of its controllers"):
        Scene("x", pc.build, params=pc.SCENE.params, settings=pc.SCENE.settings,
              contact=Contact(controllers=dict(c.controllers), initial_state=c.initial_state, requires={"pid": {}}))
    # the library refuses before the law is built (the law's own check is never reached)
    only_two = Contact(controllers={"pd": c.controllers["pd"]}, initial_state=c.initial_state,
                       requires={"pd": {"actuators": 2, "Kp": 100}})
    scene = Scene("two", pc.build, params=pc.SCENE.params, settings=pc.SCENE.settings, contact=only_two)
    with pytest.raises(SceneError, match=r"needs actuators=2 \(here actuators=1\); use --set actuators=2"):
        commands.simulate(scene, t_end=0.01, quiet=True)
    with pytest.raises(SceneError, match="no controller fits"):
        commands.pipeline(scene, t_end=0.01, quiet=True, out_dir=str(tmp_path), no_animation=True)


def test_a_scene_file_given_by_path_works_like_the_shipped_one(tmp_path, capsys):
    import invctl_scenes as problems

    copy = tmp_path / "my_cartpole.py"
    shutil.copy(Path(problems.__file__).parent / "cartpole.py", copy)
    results = []
    for scene in ("cartpole", str(copy)):
        assert main(["invert", scene, "--quiet", "--json", "--N", "80"]) == 0
        results.append(_json(capsys))
    a, b = results
    assert a["selection"] == b["selection"] and a["T0"] == b["T0"] and a["Tf"] == b["Tf"]
    np.testing.assert_allclose(a["max_output_error"], b["max_output_error"], rtol=1e-12)


def test_two_scene_files_with_the_same_name_are_different_scenes(tmp_path):
    from invctl.scenes import load_scene

    text = ("from invctl.scenes import Scene, Tracking\nfrom invctl_scenes.cartpole import build, PARAMS\n"
            "SCENE = Scene('{name}', build, params={{**PARAMS, 'l': {l}}}, tracking=Tracking(point=[0.0, 0.0]))\n")
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    (tmp_path / "a" / "scene.py").write_text(text.format(name="first", l=0.5))
    (tmp_path / "b" / "scene.py").write_text(text.format(name="second", l=0.8))
    first, second = load_scene(str(tmp_path / "a" / "scene.py")), load_scene(str(tmp_path / "b" / "scene.py"))
    assert (first.name, first.params["l"]) == ("first", 0.5)
    assert (second.name, second.params["l"]) == ("second", 0.8)


def test_a_flat_output_goes_through_the_generic_commands(capsys):
    """The crane's load position (relative degree (4, 4), r_bar = 2n): analyze says it is flat, invert
    chooses the normal form (no pre-actuation, T0 = t0) and the forward check holds."""
    assert main(["analyze", "crane", "--samples", "20", "--json"]) == 0
    data = _json(capsys)
    assert data["flat"] and data["r_hat"] == 4 and data["internal_dim"] == 0
    assert main(["invert", "crane", "--quiet", "--json"]) == 0
    data = _json(capsys)
    assert data["method"] == "normal-form" and data["T0"] == data["t0"] and data["Tf"] == data["tf"]
    assert data["max_output_error"] < 1e-6 and data["max_u_pre_actuation"] == 0.0
