"""The CLI frame and the trade-off framework, on a small scene given by path."""
import json
import textwrap

import numpy as np
import pytest

from invctl.cli import main
from invctl.studies.tradeoff import TradeoffResult, TradeoffSpec, run_tradeoff

SCENE = textwrap.dedent('''
    """A mass on a spring, position output; a user study: explicit Euler on x' = -a x against exp(-a T)."""
    import math
    import time

    import casadi as ca

    from invctl.model import Model, ParamSet
    from invctl.scenes import Scene, Tracking
    from invctl.studies.tradeoff import TradeoffSpec

    PARAMS = {"m": 1.0, "k": 4.0}

    def build(**overrides):
        P = ParamSet(list(PARAMS))
        q, v = ca.SX.sym("q", 1), ca.SX.sym("v", 1)
        return Model("spring_mass", q, v, P, PARAMS, M=ca.reshape(P["m"], 1, 1), f=-P["k"] * q,
                     B=ca.DM([[1.0]]), h=q, overrides=overrides)

    def euler_study(scene, params, settings, smoke):
        a, T = settings["a"], settings["T"]
        exact = math.exp(-a * T)

        def run(h):
            t0 = time.perf_counter()
            x = (1 - a * h) ** int(round(T / h))
            return {"error": abs(x - exact), "time_s": time.perf_counter() - t0 + 1e-9}

        return TradeoffSpec("h", [0.1, 0.01, 0.001], run, "closed form exp(-a T)", "|x(T) - exact|")

    SCENE = Scene("spring_mass", build, params=PARAMS, settings={"a": 2.0, "T": 1.0}, positive=("m",),
                  tracking=Tracking(point=[0.0]), studies={"euler": euler_study})
''')


@pytest.fixture
def scene_file(tmp_path):
    path = tmp_path / "spring_mass.py"
    path.write_text(SCENE)
    return str(path)


def test_json_is_last_line_and_params_apply(scene_file, capsys):
    assert main(["analyze", scene_file, "--set", "k=9", "--json", "--samples", "10"]) == 0
    data = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert data["params"]["k"] == 9.0 and data["relative_degree"] == [2] and data["internal_dim"] == 0


def test_unknown_scene_and_command_are_explained(scene_file, capsys):
    assert main(["simulate", "no_such_scene"]) == 2
    assert "no scene named 'no_such_scene'" in capsys.readouterr().err
    assert main(["design", scene_file]) == 2
    assert "does not offer 'design'" in capsys.readouterr().err
    assert main(["analyze", scene_file, "--set", "m=-1"]) == 2
    assert "m must be positive" in capsys.readouterr().err


def test_bad_assignment_is_not_evaluated(scene_file, capsys):
    assert main(["analyze", scene_file, "--set", "k=__import__('os').getcwd()"]) == 2
    assert "is not a number" in capsys.readouterr().err


def test_study_tradeoff_writes_table_and_figure(scene_file, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["study", "tradeoff", scene_file, "--out-dir", str(out), "--json", "--job", "euler"]) == 0
    data = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert data["reference"] == "closed form exp(-a T)"
    errs = [r["error"] for r in data["rows"]]
    # first order: error drops ~10x per 10x smaller step
    slopes = np.diff(np.log10(errs))
    np.testing.assert_allclose(slopes, -1.0, atol=0.1)
    assert all(r["knob"] == "h" for r in data["rows"])
    for ext in ("csv", "json", "png"):
        assert (out / f"tradeoff_spring_mass.{ext}").stat().st_size > 0
    back = TradeoffResult.from_json(out / "tradeoff_spring_mass.json")
    assert back.recommend(1e-3)["value"] == 0.001


def test_failed_setting_is_reported_not_dropped():
    def run(v):
        if v < 0:
            raise ValueError("negative step")
        return {"error": v, "time_s": 1.0 / (1 + v)}

    res = run_tradeoff(TradeoffSpec("h", [0.5, -1.0, 0.1], run, "none"), progress=False)
    assert [r["value"] for r in res.rows] == [0.5, 0.1]
    assert res.failures[0]["message"] == "ValueError: negative step"
    # 0.5 is slower-but-worse? time 0.667 vs 0.909: 0.5 is faster, 0.1 more accurate: both Pareto
    assert res.pareto().tolist() == [True, True]
    assert "failed: ValueError" in res.table()


def test_jsonable_gives_strict_json():
    import json

    import numpy as np

    from invctl.scenes import jsonable

    data = {"x": np.array([1.0, np.inf]), 2: np.complex128(1 - 2j), "ok": np.bool_(False), "n": np.int32(4),
            "t": (np.float32(0.5), None, "s"), "other": object()}
    out = json.loads(json.dumps(jsonable(data), allow_nan=False))
    assert out["x"] == [1.0, "inf"] and out["2"] == [1.0, -2.0] and out["ok"] is False and out["n"] == 4
    assert out["t"] == [0.5, None, "s"] and out["other"].startswith("<object")
