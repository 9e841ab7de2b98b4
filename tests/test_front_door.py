"""One result vocabulary and the Python front door.

Every run result is a Trajectory (t, q, v, u, y, lam with time last, a Status, sample, plot, to_npz) and
``invctl.load`` reads each saved kind back as its class; a scene loaded in Python runs the same
computations as the command line (compared number for number with what the CLI wrote), and
``throw=False`` turns a failure into data.
"""
import json

import numpy as np
import pytest

import invctl
from invctl.cli import main
from invctl.errors import InversionFailed, ResultFileError
from invctl.results import Curve, Status, Trajectory


def _json(capsys):
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def _check_fields(res):
    """The common fields: 2-D, time last, the length of ``t``; ``sample`` at the sample times returns them."""
    K = np.size(res.t)
    for f in ("q", "v", "u", "y", "lam"):
        a = res.field(f)
        assert a.ndim == 2 and a.shape[1] == K, (f, a.shape)
    s = res.sample(res.t[:5])
    for f in ("q", "v"):
        np.testing.assert_allclose(s[f], res.field(f)[:, :5], rtol=0, atol=1e-12)
    assert isinstance(res.status, Status) and res.success == (res.status is Status.OK)


def test_every_saved_result_kind_loads_back_as_its_class(tmp_path, capsys):
    saved = {}
    assert main(["invert", "cartpole", "--N", "60", "--quiet", "--out", str(tmp_path / "inv.npz")]) == 0
    saved["Inverse"] = tmp_path / "inv.npz"
    assert main(["simulate", "cartpole", "--controller", "C2", "--t-end", "0.5", "--quiet",
                 "--out", str(tmp_path / "cl.npz")]) == 0
    saved["ClosedLoopResult"] = tmp_path / "cl.npz"
    assert main(["simulate", "bouncing_ball", "--t-end", "0.3", "--quiet", "--out", str(tmp_path / "ball.npz")]) == 0
    saved["ContactTrajectory"] = tmp_path / "ball.npz"
    assert main(["simulate", "stiff_wall", "--t-end", "0.2", "--quiet", "--out", str(tmp_path / "wall.npz")]) == 0
    saved["SwitchedSimulation"] = tmp_path / "wall.npz"
    capsys.readouterr()
    for kind, path in saved.items():
        res = invctl.load(path)
        assert type(res).__name__ == kind and isinstance(res, Trajectory)
        back = type(res).load(path)  # the class's own reader gives the same arrays
        np.testing.assert_array_equal(np.asarray(res.q), np.asarray(back.q))
        _check_fields(res)
    # what each kind's fields mean, against the kind's own arrays
    ball = invctl.load(saved["ContactTrajectory"])
    np.testing.assert_allclose(ball.lam[:, :-1], ball.P / ball.h)
    wall = invctl.load(saved["SwitchedSimulation"])
    np.testing.assert_array_equal(wall.u[0], wall.Fc) and np.testing.assert_array_equal(wall.lam[0], wall.Fe)
    inv = invctl.load(saved["Inverse"])
    np.testing.assert_array_equal(inv.t, inv.t_mesh)
    np.testing.assert_allclose(inv.u, inv.u(inv.t_mesh), atol=1e-12)  # the mesh values are the polynomial's


def test_load_reads_a_pipeline_folder_and_rejects_what_it_cannot_read(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(ResultFileError, match="without study.json"):
        invctl.load(tmp_path / "empty")
    with pytest.raises(ResultFileError, match="no such file"):
        invctl.load(tmp_path / "missing.npz")
    from invctl.io import save_npz

    save_npz(tmp_path / "odd.npz", "SomethingElse", {"a": np.zeros(2)})
    with pytest.raises(ResultFileError, match="cannot read"):
        invctl.load(tmp_path / "odd.npz")


def test_the_python_front_door_computes_what_the_cli_writes(tmp_path, capsys):
    """``load_scene(name, **values).invert()`` equals ``invctl invert --set ...`` to round-off, and a bound
    value reaches the model (another mass gives another feedforward)."""
    scene = invctl.load_scene("cartpole", mp=0.25)
    assert scene.values == {"mp": 0.25}
    inv = scene.invert(N=80, quiet=True)
    assert isinstance(inv, invctl.Trajectory) and inv.success and isinstance(inv.u, Curve)
    assert main(["invert", "cartpole", "--set", "mp=0.25", "--N", "80", "--quiet",
                 "--out", str(tmp_path / "inv.npz")]) == 0
    capsys.readouterr()
    cli = invctl.load(tmp_path / "inv.npz")
    np.testing.assert_allclose(np.asarray(inv.u), np.asarray(cli.u), rtol=0, atol=1e-9 * np.abs(cli.u).max())
    default = invctl.load_scene("cartpole").invert(N=80, quiet=True)
    assert np.abs(np.asarray(default.u) - np.asarray(inv.u)).max() > 1e-3
    run = scene.simulate("C2", t_end=0.5, quiet=True)
    assert type(run).__name__ == "ClosedLoopResult" and run.success
    _check_fields(run)
    with pytest.raises(invctl.ParameterError, match="unknown parameter"):
        invctl.load_scene("cartpole", nonsense=1.0)


def test_throw_false_returns_the_failed_inverse_as_data():
    scene = invctl.load_scene("cartpole")
    with pytest.raises(InversionFailed):  # stopped by its time limit before the first iteration
        scene.invert(N=60, max_wall_time=1e-6, quiet=True)
    partial = scene.invert(N=60, max_wall_time=1e-6, quiet=True, throw=False)
    assert partial.status is Status.FAILED and not partial.success
    assert partial.solver_status != "Solve_Succeeded" and partial.status.message.startswith("the solver")


def test_plots_share_one_signature(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    run = invctl.load_scene("cartpole").simulate("C2", t_end=0.3, quiet=True)
    fig = run.plot(tmp_path / "a.png")  # a path in place of the axes, as before
    assert (tmp_path / "a.png").stat().st_size > 0 and fig.axes
    plt.close(fig)
    fig, axes = plt.subplots(2, 1)
    out = run.plot(axes)
    assert out is fig and axes[0].get_ylabel() == "outputs y" and axes[-1].get_xlabel() == "time t [s]"
    assert [ln.get_label() for ln in axes[0].get_lines()] == run.row_names("y")
    plt.close(fig)


def test_status_is_one_vocabulary():
    assert Status.of("left_region") is Status.LEFT_REGION and Status.OK == "ok"
    assert f"{Status.FAILED}" == "failed" and json.dumps({"s": Status.OK}) == '{"s": "ok"}'
    with pytest.raises(ValueError, match="statuses"):
        Status.of("fine")


# ------------------------------------------------------------ a user-written scene of each kind
_USER_SCENES = {
    "tracking": '''
import casadi as ca
from invctl.model import Model, ParamSet
from invctl.reference import rest_to_rest
from invctl.scenes import Scene, Tracking

PARAMS = {"m1": 1.0, "m2": 0.5, "k": 20.0, "d": 0.5}


def build(**overrides):
    P = ParamSet(list(PARAMS))
    q, v = ca.SX.sym("q", 2), ca.SX.sym("v", 2)
    spring = P["k"] * (q[1] - q[0]) + P["d"] * (v[1] - v[0])
    M = ca.diag(ca.vertcat(P["m1"], P["m2"]))
    return Model("two_masses", q, v, P, PARAMS, M=M, f=ca.vertcat(spring, -spring), B=ca.DM([[1.0], [0.0]]),
                 h=q[0], overrides=overrides)


SCENE = Scene("two_masses", build, params=PARAMS,
              tracking=Tracking(reference=lambda model: rest_to_rest([0.0], [0.2], 0.5, 1.5),
                                plant={"m2": 1.2}, controllers=("C1", "C2")))
''',
    "contact": '''
import casadi as ca
from invctl.model import Gap, Model, ParamSet
from invctl.scenes import Contact, Scene


def build(**overrides):
    P = ParamSet(["m", "g", "e"])
    q, v = ca.SX.sym("q", 1), ca.SX.sym("v", 1)
    return Model("ball", q, v, P, {"m": 1.0, "g": 9.81, "e": 0.5}, M=ca.reshape(P["m"], 1, 1), f=-P["m"] * P["g"],
                 B=ca.SX.zeros(1, 0), gaps=[Gap("floor", q[0], "e")], overrides=overrides)


SCENE = Scene("ball", build, params={"m": 1.0, "g": 9.81, "e": 0.5}, settings={"h": 1e-3, "t_end": 0.8},
              contact=Contact(initial_state=lambda model, settings, controller: ([0.5], [0.0])))
''',
    "switched": '''
from invctl_scenes.stiff_wall import PARAMS, build, check
from invctl.scenes import Scene, Switched

SCENE = Scene("my_wall", build, params={**PARAMS, "t_end": 0.35}, validate=check, switched=Switched())
''',
}


@pytest.mark.parametrize("kind", list(_USER_SCENES))
def test_a_user_written_scene_of_each_kind_runs_the_pipeline_from_python_and_the_cli(kind, tmp_path, capsys):
    """The same pipeline (one function for every kind) from the scene's method and from the command line:
    the same runs, number for number, each a Trajectory saved where the report says."""
    path = tmp_path / f"my_{kind}.py"
    path.write_text(_USER_SCENES[kind])
    scene = invctl.load_scene(str(path))
    assert scene.kind == kind
    runs = scene.pipeline(tmp_path / "py", quiet=True, no_animation=True)
    assert runs and all(isinstance(r, Trajectory) for r in runs.values())
    assert main(["pipeline", str(path), "--out-dir", str(tmp_path / "cli"), "--quiet", "--no-animation",
                 "--json"]) == 0
    data = _json(capsys)
    assert set(data["runs"]) == set(runs)
    for name, run in runs.items():
        cli = invctl.load(tmp_path / "cli" / f"run_{name}.npz")
        assert type(cli) is type(run) and cli.status == run.status
        np.testing.assert_allclose(cli.field("q"), run.field("q"), rtol=0, atol=1e-12)
        py = invctl.load(tmp_path / "py" / f"run_{name}.npz")
        np.testing.assert_array_equal(py.field("q"), run.field("q"))


def test_a_ctrl_c_swallowed_inside_a_python_call_is_honoured(monkeypatch):
    """As on the command line: a Ctrl-C that a compiled library caught and dropped (CasADi's argument
    conversion does) still interrupts the scene's method when it returns."""
    import os
    import signal
    import time

    import invctl.inversion

    real = invctl.inversion.forward_check

    def swallowing(*a, **k):
        out = real(*a, **k)
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.2)  # the handler runs here and raises KeyboardInterrupt ...
        except KeyboardInterrupt:
            pass  # ... which the library swallows
        return out

    monkeypatch.setattr(invctl.inversion, "forward_check", swallowing)
    with pytest.raises(invctl.RunInterrupted, match="as the command finished"):
        invctl.load_scene("cartpole").invert(N=60, quiet=True)


@pytest.mark.parametrize("declared, source, match", [
    ("rigid_wall", "compliant_wrist", "declare Switched\\(plant='compliant_wrist'\\)"),
    ("compliant_wrist", "stiff_wall", "lack \\['Mt', 'bt', 'kt'\\]"),
    ("spring_wall", "stiff_wall", "switched.plant must be one of"),
])
def test_a_switched_scene_declares_its_plant(declared, source, match, tmp_path):
    """The plant is the scene's declaration, checked against its parameters (not guessed from them)."""
    path = tmp_path / "wall.py"
    path.write_text(f"from invctl_scenes.{source} import PARAMS, build\n"
                    "from invctl.scenes import Scene, Switched\n"
                    f"SCENE = Scene('wall', build, params=PARAMS, switched=Switched(plant={declared!r}))\n")
    with pytest.raises(invctl.SceneError, match=match):
        invctl.load_scene(str(path)).model()
    assert invctl.load_scene("compliant_wrist").switched.wrist and not invctl.load_scene("stiff_wall").switched.wrist


def test_a_pipeline_builds_the_model_once_and_animates_every_run_with_it(tmp_path):
    """One ``pipeline`` binds the scene once: the options, the runs of every controller and their animations use
    one model (before, each run and each animation built it again: four builds for two controllers)."""
    path = tmp_path / "counted.py"
    path.write_text(_USER_SCENES["contact"].replace("def build(**overrides):", "BUILDS = []\n\n\ndef build(**overrides):\n"
                                                     "    BUILDS.append(dict(overrides))") + '''
from invctl.control.pdplus import zero_input
from invctl.plot.animate import Drawing

SCENE = Scene("ball", build, params={"m": 1.0, "g": 9.81, "e": 0.5}, settings={"h": 1e-3, "t_end": 0.3},
              contact=Contact(initial_state=lambda model, settings, controller: ([0.2], [0.0]),
                              controllers={"off": lambda m, s: zero_input(), "also_off": lambda m, s: zero_input()}),
              drawing=lambda model: Drawing({"ball": ca.vertcat(0.0, model.q[0])}))
''')
    scene = invctl.load_scene(str(path))
    builds = scene.build.__globals__["BUILDS"]
    runs = scene.pipeline(tmp_path / "out", quiet=True, t_end=0.3, animate=True)
    assert sorted(runs) == ["also_off", "off"] and builds == [{}]
    assert all((tmp_path / "out" / f"anim_{k}.gif").stat().st_size > 0 for k in runs)


def test_the_commands_a_scene_offers_follow_from_what_it_declares():
    from invctl.scenes import Contact, Report, Scene, Switched, Tracking

    def build():
        return None

    def ref(model):
        return None

    def compute(ctx):
        return {}

    offers = {
        ("analyze", "invert", "design", "simulate", "pipeline", "study"): Scene("a", build, tracking=Tracking(ref)),
        ("analyze", "study"): Scene("b", build, tracking=Tracking()),
        ("simulate", "pipeline", "study"): Scene("c", build, contact=Contact(initial_state=ref)),
        ("analyze", "simulate", "pipeline", "study"): Scene("d", build, contact=Contact(initial_state=ref),
                                                            reports=(Report("r", compute, command="analyze"),)),
        ("analyze", "simulate", "design", "pipeline", "study"): Scene("e", build, switched=Switched()),
        (): Scene("f", build),
        ("study",): Scene("g", build, studies={"job": build}),
    }
    for commands, scene in offers.items():
        assert scene.commands == commands, scene.name
    with pytest.raises(invctl.errors.SceneError, match=r"does not offer 'invert'; it offers: analyze, study \(invert "
                                                       r"needs a model with outputs and tracking=Tracking\(reference"):
        offers[("analyze", "study")].require("invert")
