"""Tracking scenes as new users meet them: a reference with a constant component (a scene file in
tests/scenes/, loaded by path as ``invctl <command> path/to/scene.py`` does) and runs that leave the
model's region or their funnel (reported as such everywhere).
"""
import dataclasses
import json
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pytest

from invctl.cli import main as cli_main
from invctl.scenes import load_scene
from invctl.simulate.closed_loop import ClosedLoopResult
from invctl.studies.tracking import TrackingStudy, run_controller, setup_tracking

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
    assert len(design["K"]) == 2 and design["a1_design_point"] > 0   # one eta2 row, the slider row
    rc = cli_main(["pipeline", str(SLIDER), "--out-dir", str(tmp_path), "--quiet", "--json", "--no-animation"])
    out = capsys.readouterr().out.strip().splitlines()
    assert rc == 0
    data = json.loads(out[-1])
    assert set(data["runs"]) == {"C1", "C2", "C3"}
    for name in ("C1", "C2"):
        assert data["runs"][name]["status"] == "ok"
    assert data["reductions"]["output"] > 0
    assert (tmp_path / "errors.png").exists()


def test_a_run_that_leaves_the_region_is_not_ok_anywhere(tmp_path, capsys):
    """cartpole: C3 (feedforward only) lets the pole fall; it leaves the model's region (|theta| < pi/2) at
    t = 1.16 s.  The table, the JSON status and the figures say so; the figures' axes are set by the runs
    that stayed inside (and C3 up to its exit), C3 is drawn clipped with a marker at its exit."""
    rc = cli_main(["pipeline", "cartpole", "--out-dir", str(tmp_path), "--quiet", "--json", "--no-animation"])
    out = capsys.readouterr().out.strip().splitlines()
    assert rc == 0
    runs = json.loads(out[-1])["runs"]
    assert runs["C1"]["status"] == runs["C2"]["status"] == "ok"
    c3 = runs["C3"]
    assert c3["status"] == "left_region" and not c3["success"]
    assert c3["left_region"]["t"] == pytest.approx(1.16, abs=0.01) and "theta" in c3["left_region"]["coordinates"]
    line = next(s for s in out if s.startswith("C3 "))
    assert "left the model's region at t = 1.16 s" in line
    assert not any("left" in s for s in out if s.startswith(("C1 ", "C2 ")))

    study = TrackingStudy.load(tmp_path)      # the status and the exit survive save/load
    assert study.runs["C3"].status == "left_region"
    assert study.runs["C3"].departure == (pytest.approx(1.158), "left region")
    old = dataclasses.replace(study.runs["C3"], status="ok", message="")   # as written before the status existed
    back = ClosedLoopResult.load(old.to_npz(tmp_path / "old_C3.npz"))
    assert back.status == "left_region" and "left the model's region at t = 1.16 s" in back.message
    figs = study.plot()
    try:
        ax = figs["errors"].axes[0]
        labels = [t.get_text() for t in ax.get_legend().get_texts()]
        assert any(s.startswith("C3") and "(left region at t = 1.16 s)" in s for s in labels), labels
        assert not any("left" in s for s in labels if not s.startswith("C3"))
        c3r, t = study.runs["C3"], study.runs["C3"].t
        good = np.concatenate([study.runs[n].output_error for n in ("C1", "C2")])
        before = c3r.output_error[t <= 1.158]
        lo, hi = ax.get_ylim()
        assert lo <= good.min() and hi >= good.max()
        assert hi <= 1.1 * max(good.max(), before.max())      # not stretched by the fallen pole
        assert c3r.output_error[t > 1.158].max() > hi           # ... which is drawn clipped
        marks = [ln for ln in ax.get_lines() if ln.get_marker() == "X"]
        assert len(marks) == 1 and marks[0].get_xdata()[0] == pytest.approx(1.158, abs=2e-3)
        states = figs["states"].axes[0]
        assert "left" not in states.get_title()                 # C1 stayed inside
    finally:
        for f in figs.values():
            plt.close(f)


def test_a_run_that_leaves_its_funnel_is_marked_and_not_compared(tmp_path):
    """A run cut at a funnel violation (constructed from a stored run): the table's comparison says it is not
    comparable, the figures label it with the time it left."""
    setup = setup_tracking(load_scene("cartpole"), invert=False, t_end=1.0)
    c2 = run_controller(setup, "C2")
    k = int(np.searchsorted(c2.t, 0.5 - 1e-9)) + 1
    arrays = {f.name: getattr(c2, f.name) for f in dataclasses.fields(ClosedLoopResult)}
    cut = dataclasses.replace(c2, status="funnel_violation", message=f"left the funnel at t = {c2.t[k - 1]:.4g} s",
                              **{n: a[..., :k] for n, a in arrays.items()
                                 if isinstance(a, np.ndarray) and a.ndim and a.shape[-1] == c2.t.size})
    assert cut.departure == (pytest.approx(0.5, abs=2e-3), "left its funnel")
    study = TrackingStudy({"C1": c2, "C2": cut})
    table = study.table()
    assert "(funnel_violation: left the funnel at t = 0.5" in table
    assert "not comparable: C2 left its funnel at t = 0.5 s" in table
    figs = study.plot()
    try:
        labels = [t.get_text() for t in figs["funnel"].axes[0].get_legend().get_texts()]
        assert any(s.startswith("C2 ") and s.endswith("(left its funnel at t = 0.5 s)") for s in labels)
        assert any(s.startswith("C1 ") and "left" not in s for s in labels)
    finally:
        for f in figs.values():
            plt.close(f)
    # a feedback run that left the region (marked on a stored run): the funnel boundary stays in view
    exit_ = {"t": 0.3, "coordinates": "theta = -1.6", "region": "|theta| < pi/2"}
    left = dataclasses.replace(c2, status="left_region", stats={"left_region": exit_})
    figs = TrackingStudy({"C1": c2, "C2": left}).plot()
    try:
        ax = figs["funnel"].axes[0]
        lo, hi = ax.get_ylim()
        assert lo <= 0 and hi >= 1        # the boundary (ratio 1) stays in view
        assert any(t.get_text().startswith("C2 ") and t.get_text().endswith("(left region at t = 0.3 s)")
                   for t in ax.get_legend().get_texts())
        assert any(ln.get_marker() == "X" for ln in ax.get_lines())
    finally:
        for f in figs.values():
            plt.close(f)
