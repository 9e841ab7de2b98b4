"""Tracking scenes new users write: a reference with a constant component (tests/scenes/).

The scene file is loaded by path, as ``invctl <command> path/to/scene.py`` does.
"""
import json
from pathlib import Path

import numpy as np
import pytest

from invctl.cli import main as cli_main
from invctl.scenes import load_scene
from invctl.studies.tracking import run_controller, setup_tracking

SLIDER = Path(__file__).parent / "scenes" / "cart_pole_and_slider.py"


@pytest.fixture(scope="module")
def slider_setup():
    return setup_tracking(load_scene(SLIDER), invert=True)


@pytest.mark.parametrize("name", ["C1", "C2", "C3", "C1-inv"])
def test_constant_reference_component_runs(slider_setup, name):
    """y_2 = z is held at 0 while y_1 = x moves: every controller runs to the end (the funnel controllers
    inside their funnels) and the slider stays near 0."""
    r = run_controller(slider_setup, name)
    assert r.t[-1] == pytest.approx(slider_setup.t_end)
    assert np.all(r.y_ref[1] == 0.0) and np.ptp(r.y_ref[0]) == pytest.approx(0.5)
    assert np.all(np.isfinite(r.u))
    if name != "C3":
        assert r.status == "ok" and r.max_funnel_ratio < 1
        assert np.max(np.abs(r.y[1])) < 0.05 and r.output_error[-1] < 0.02


def test_constant_reference_component_from_the_cli(tmp_path, capsys):
    assert cli_main(["design", str(SLIDER), "--json"]) == 0
    design = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert design
    rc = cli_main(["pipeline", str(SLIDER), "--out-dir", str(tmp_path), "--quiet", "--json", "--no-animation"])
    out = capsys.readouterr().out.strip().splitlines()
    assert rc == 0
    data = json.loads(out[-1])
    assert set(data["runs"]) == {"C1", "C2", "C3"}
    for name in ("C1", "C2"):
        assert data["runs"][name]["status"] == "ok"
    assert data["reductions"]["output"] > 0
    assert (tmp_path / "errors.png").exists()
