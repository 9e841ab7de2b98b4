"""Errors name the real cause with the class docs/errors.md lists, and advice names only options that
exist for the command; scene files named only inside a run file are never run."""
from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import pytest

from invctl.cli import _memory_advice, build_parser, main
from invctl.scenes import SCENE_COMMANDS

ROOT = Path(__file__).resolve().parents[1]
OPTION = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]*")


def _options() -> dict[str, set]:
    """Every command's option strings, from the parser the command line uses."""
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return {name: {o for a in p._actions for o in a.option_strings} for name, p in sub.choices.items()}


OPTIONS = _options()


def run_cli(capsys, *argv):
    rc = main([*argv, "--json"])
    cap = capsys.readouterr()
    return rc, json.loads(cap.out.strip().splitlines()[-1])


def _wrong_reference_scene(tmp: Path) -> str:
    """The cart-pole with a reference of two components for its one output."""
    text = (ROOT / "invctl_scenes" / "cartpole.py").read_text()
    old = "return Reference(t, x0 + (xf - x0) * poly9_timing_law(t, t0, tf), t0, tf"
    assert old in text
    path = tmp / "two_components.py"
    path.write_text(text.replace(old, "return Reference(t, ca.vertcat(x0, x0 + (xf - x0) * poly9_timing_law(t, t0, "
                                      "tf)), t0, tf"))
    return str(path)


#: (argv, class, words in the message); "{tmp}" is the test's folder, "{wrong_ref}" a scene file
CASES = [
    (["animate", "{tmp}/run.npz", "--fps", "nan"], "OptionError", "--fps 'nan'"),
    (["animate", "{tmp}/run.npz", "--fps", "0"], "OptionError", "positive"),
    (["animate", "{tmp}/run.npz", "--fps", "abc"], "OptionError", "expected a number"),
    (["animate", "{tmp}/run.npz", "--speed", "0"], "OptionError", "--speed '0'"),
    (["animate", "{tmp}/run.npz", "--out", "{tmp}/x.avi"], "AnimationError", ".gif"),
    (["simulate", "cartpole", "--plant-set", "nope=1"], "ParameterError", "unknown plant parameter(s) ['nope']"),
    (["simulate", "bouncing_ball", "--plant-set", "nope=1"], "ParameterError", "unknown plant parameter(s)"),
    (["pipeline", "compliant_wrist", "--plant-set", "kt=2"], "OptionError", "not applicable"),
    (["simulate", "cartpole", "--plant-set", "l=1e50", "--quiet"], "ParameterError", "--plant-set l=1e+50: the plant"),
    (["simulate", "prismatic_clearance", "--plant-set", "m2=1e-20", "--quiet"], "ParameterError",
     "--plant-set m2=1e-20"),
    (["invert", "{wrong_ref}", "--quiet"], "DimensionError", "2 components, but the model has 1 outputs"),
    (["invert", "cartpole", "--set", "l=1e50"], "ParameterError", "l = 1e+50 (default 0.5)"),
    (["invert", "cartpole", "--set", "mp=0.3", "--set", "l=1e-20"], "ParameterError", "with l = 1e-20 (default 0.5): "),
    (["invert", "cartpole", "--dt", "1e-12", "--out", "{tmp}/x.npz", "--quiet"], "ResourceLimitError", "--dt"),
    (["invert", "cartpole", "--dt", "0.01"], "OptionError", "give --out"),
    (["invert", "cartpole", "--N", "abc"], "OptionError", "--N 'abc'"),
    (["invert", "cartpole", "--tol", "0"], "OptionError", "--tol 0.0"),
    (["invert", "cartpole", "--energy", "1"], "OptionError", "--minimum-time"),
    (["simulate", "bouncing_ball", "--inverse", "{tmp}/x.npz"], "OptionError", "tracking scenes only"),
    (["simulate", "cartpole", "--record-every", "2"], "OptionError", "contact scenes only"),
    (["analyze", "stiff_wall", "--samples", "3"], "OptionError", "at least 8"),
    (["design", "cartpole", "--plot", "{tmp}/f.jpg"], "OutputPathError", ".png"),
    (["generate", "cartpole"], "OptionError", "--grid"),
]


@pytest.fixture
def solve_forbidden(monkeypatch):
    """Any stable inversion fails the test: the cases are decided before the solve."""
    from invctl.studies import tracking_report

    def fail(*a, **k):
        raise AssertionError("an inversion ran although the input was known to be wrong")

    monkeypatch.setattr(tracking_report, "invert_tracking", fail)


@pytest.mark.parametrize("argv, error, words", CASES, ids=[" ".join(c[0][:4]) for c in CASES])
def test_errors_name_their_cause_and_only_existing_options(tmp_path, capsys, solve_forbidden, argv, error, words):
    argv = [a.format(tmp=tmp_path, wrong_ref=_wrong_reference_scene(tmp_path) if "{wrong_ref}" in a else "")
            for a in argv]
    rc, d = run_cli(capsys, *argv)
    assert rc == 2 and d["error"] == error and words in d["message"], d
    named = set(OPTION.findall(d["message"]))
    assert named <= OPTIONS[argv[0]], f"{argv}: the message names {sorted(named - OPTIONS[argv[0]])}, which " \
                                      f"invctl {argv[0]} does not take: {d['message']}"


def test_the_option_check_sees_a_wrong_option():
    """The check above fails for an option another command has (so it can fail)."""
    msg = "ran out of memory; shorten the run (--t-end)"
    assert set(OPTION.findall(msg)) - OPTIONS["invert"] == {"--t-end"}


def test_memory_advice_names_only_options_of_the_command():
    for command in (*SCENE_COMMANDS, "generate", "animate"):
        named = set(OPTION.findall(_memory_advice(command)))
        assert named and named <= OPTIONS[command], (command, named)
    assert "--t-end" in _memory_advice("simulate") and "--dt" in _memory_advice("invert")


def test_every_option_in_the_sources_exists():
    """Each ``--name`` written anywhere in invctl/ (messages, help) is an option of some command."""
    every = set().union(*OPTIONS.values())
    stray = {}
    for f in sorted((ROOT / "invctl").rglob("*.py")):
        for i, line in enumerate(f.read_text().splitlines(), 1):
            for name in set(OPTION.findall(line)) - every:
                stray.setdefault(name, []).append(f"{f.relative_to(ROOT)}:{i}")
    assert stray == {}


def test_the_conditioning_limit_is_double_precision():
    """l = 1e-6 gives a mass matrix of condition number ~5e12 (it still inverts: the limit is not
    tighter than double precision); l = 1e-8 one of ~5e16 (IPOPT diverged there before)."""
    from invctl.errors import ParameterError
    from invctl.scenes import load_scene

    scene = load_scene("cartpole")
    assert scene.model({"l": 1e-6}).values["l"] == 1e-6
    with pytest.raises(ParameterError, match=r"(?s)l = 1e-08 .*condition number [45]\.\d+e\+16"):
        scene.model({"l": 1e-8, "mp": 0.2})


# ------------------------------------------------------------ scene files in run files
def _evil_scene(tmp: Path) -> tuple[Path, Path]:
    """A copy of the two-link arm that writes a marker file when it is loaded."""
    marker = tmp / "MARKER"
    path = tmp / "evil_scene.py"
    path.write_text((ROOT / "invctl_scenes" / "two_link_arm.py").read_text()
                    + f"\nfrom pathlib import Path\nPath({str(marker)!r}).write_text('ran')\n")
    return path, marker


def test_animate_never_runs_a_scene_file_named_in_a_run(tmp_path, capsys):
    path, marker = _evil_scene(tmp_path)
    run = tmp_path / "run.npz"
    rc, d = run_cli(capsys, "invert", str(path), "--out", str(run), "--quiet")
    assert rc == 0 and marker.exists(), d  # named on the command line: loaded (and run)
    marker.unlink()
    rc, d = run_cli(capsys, "animate", str(run), "--fps", "5")
    assert rc == 2 and d["error"] == "SceneError" and f"--scene {path.resolve()}" in d["message"], d
    assert not marker.exists() and not run.with_suffix(".gif").exists()
    # the library call on the loaded run refuses the same way
    from invctl.errors import SceneError
    from invctl.inversion import Inverse

    with pytest.raises(SceneError, match="pass scene="):
        Inverse.load(run).animate(tmp_path / "lib.gif", fps=5)
    assert not marker.exists()
    rc, d = run_cli(capsys, "animate", str(run), "--fps", "5", "--scene", str(path))
    assert rc == 0 and marker.exists() and Path(d["out"]).stat().st_size > 0, d


def test_animate_loads_a_shipped_scene_by_its_recorded_name(tmp_path, capsys):
    run = tmp_path / "run.npz"
    rc, d = run_cli(capsys, "invert", "two_link_arm", "--out", str(run), "--quiet")
    assert rc == 0, d
    rc, d = run_cli(capsys, "animate", str(run), "--fps", "5")
    assert rc == 0 and d["scene"] == "two_link_arm", d
    # a name that is no shipped scene is refused without importing anything else
    rc, d = run_cli(capsys, "animate", str(run), "--fps", "5", "--scene", "no_such_scene", "--force")
    assert rc == 2 and d["error"] == "SceneError" and "no scene named" in d["message"], d


def test_invert_dt_is_checked_again_over_the_solved_horizon(tmp_path, monkeypatch):
    """The reference's transition fits the memory, the horizon with its pre- and post-actuation does
    not: the error comes after the solve, names --dt, and keeps the inverse."""
    from invctl.errors import ResourceLimitError
    from invctl.inversion import Inverse
    from invctl.studies import commands

    rows, dt = 8, 1e-5  # cart-pole: t, q (2), v (2), u, u_causal, y_ref
    monkeypatch.setenv("INVCTL_MAX_MEMORY", str(16 * rows * 2.5 / dt))  # room for 2.5 s; the transition takes 2
    with pytest.raises(ResourceLimitError, match=r"invert --dt 1e-05: .* of the horizon \[.*use --dt") as info:
        commands.invert("cartpole", out=str(tmp_path / "x.npz"), dt=dt, quiet=True)
    assert isinstance(info.value.partial, Inverse) and info.value.partial.Tf - info.value.partial.T0 > 2.5
    assert not (tmp_path / "x.npz").exists()


def test_a_scene_may_declare_ranges():
    import invctl_scenes.cartpole as cp

    from invctl.errors import ParameterError, SceneError
    from invctl.scenes import Scene

    scene = Scene("ranged", cp.build, params=cp.PARAMS, ranges={"l": (0.01, 100)})
    assert scene.split({"l": 100.0})[0] == {"l": 100.0}
    with pytest.raises(ParameterError, match=r"l = 1000.0 is outside \[0.01, 100\], the range the scene declares"):
        scene.split({"l": 1e3})
    with pytest.raises(SceneError, match="ranges must map"):
        Scene("ranged", cp.build, params=cp.PARAMS, ranges={"l": (1, 0)})
    with pytest.raises(SceneError, match="ranges must map"):
        Scene("ranged", cp.build, params=cp.PARAMS, ranges={"nope": (0, 1)})


def _bad_values():
    """(command, option, value) for every checked option of the option table: a non-number for numbers,
    an unknown word for choices, a value its check rejects."""
    from invctl.studies.commands import OPTIONS as TABLE

    for name, opt in sorted(TABLE.items()):
        if opt.flag or opt.repeat:
            continue
        values = (["abc"] if opt.type in (int, float) else []) + (["nope"] if opt.choices else []) \
            + (["0", "-1"] if opt.check and opt.type in (int, float) else [])
        for command in opt.commands:
            for v in values:
                yield command, name, v


@pytest.mark.parametrize("command, name, value", list(_bad_values()))
def test_every_option_value_error_names_options_of_its_command(capsys, solve_forbidden, command, name, value):
    from invctl.studies.commands import OPTIONS as TABLE

    flag = "--" + name.replace("_", "-")
    argv = [command] + (["tradeoff"] if command == "study" else []) + ["cartpole", flag, value]
    rc, d = run_cli(capsys, *argv)
    if rc == 0 or (value in ("0", "-1") and d["error"] != "OptionError"):
        assert TABLE[name].check(float(value)) is None  # a value its check accepts (e.g. --energy 0)
        return
    assert rc == 2 and d["error"] == "OptionError" and flag in d["message"], d
    assert set(OPTION.findall(d["message"])) <= OPTIONS[command], d
