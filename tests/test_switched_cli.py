"""Command line of the switched-contact scenes and the wrist design (002 Sect. 5.3)."""
import json
import math

import numpy as np
import pytest

from invctl.cli import main
from invctl.errors import ParameterError
from invctl.simulate.switched import SwitchedSimulation
from invctl.stability.conewise import lambda_numerical
from invctl.studies.switched import (design_bt_min, design_kt_max, effective_wall, error_system, lambda_map,
                                     lambda_point, lambda_sweep, reduction_check, visible_region)

import invctl_scenes.compliant_wrist as wrist
import invctl_scenes.stiff_wall as wall


def _run(capsys, *argv):
    rc = main(list(argv))
    out = capsys.readouterr()
    data = json.loads(out.out.strip().splitlines()[-1]) if "--json" in argv else None
    return rc, data, out


def test_analyze_stiff_wall_json(capsys):
    rc, d, _ = _run(capsys, "analyze", "stiff_wall", "--json", "--samples", "16")
    assert rc == 0
    assert d["visible_eigenvector"] is False and d["guas"] is False
    assert d["Lambda"] == pytest.approx(d["Lambda_numerical"], rel=1e-6)
    rc, d9, _ = _run(capsys, "analyze", "stiff_wall", "--set", "bf=9000", "--json", "--samples", "16")
    assert d9["Lambda"] < d["Lambda"]


def test_analyze_compliant_wrist_json(capsys):
    rc, d, _ = _run(capsys, "analyze", "compliant_wrist", "--json", "--samples", "16")
    assert rc == 0 and d["guas"] is True and d["Lambda"] < 1
    kb, bb = effective_wall(5e4, 171.0, 1e6)
    assert d["ke_bar"] == pytest.approx(kb) and d["be_bar"] == pytest.approx(bb)
    assert d["K2"] == pytest.approx(2 * kb) and d["B2"] == pytest.approx(2 * bb + 5)
    assert d["iss"]["rate"] > 0 and d["iss"]["gain"] > 0


def test_analyze_unstable_parameters_clear_error(capsys):
    rc, d, out = _run(capsys, "analyze", "stiff_wall", "--set", "bf=-100", "--json")
    assert rc == 2 and d["error"] == "StabilityError" and "not Hurwitz" in d["message"]


def test_design_compliant_wrist(capsys):
    rc, d, _ = _run(capsys, "design", "compliant_wrist", "--json")
    assert rc == 0
    p = wrist.build().params
    # Lambda(bt_min) = 1 by both computations; GUAS just above, not just below
    for key, method in (("bt_min", "closed"), ("bt_min_numerical", "numerical")):
        q = lambda_point({**p, "bt": d[key]}, method=method)
        assert q.Lambda == pytest.approx(1.0, abs=1e-8)
    assert d["bt_min"] == pytest.approx(d["bt_min_numerical"], rel=1e-6)
    assert lambda_point({**p, "bt": d["bt_min"] * 1.001}).guas
    assert not lambda_point({**p, "bt": d["bt_min"] * 0.999}).guas
    assert d["kt_max"] == pytest.approx(d["kt_max_numerical"], rel=1e-6)
    assert lambda_point({**p, "kt": d["kt_max"]}).Lambda == pytest.approx(1.0, abs=1e-8)


def test_design_stiff_wall_bf_min(capsys):
    rc, d, _ = _run(capsys, "design", "stiff_wall", "--json")
    assert rc == 0 and d["bf_min"] == pytest.approx(d["bf_min_numerical"], rel=1e-6)
    assert lambda_point({**wall.build().params, "bf": d["bf_min"]}).Lambda == pytest.approx(1.0, abs=1e-8)


def test_simulate_stiff_wall_json_out_plot(capsys, tmp_path):
    out, fig = tmp_path / "sim.npz", tmp_path / "sim.png"
    rc, d, _ = _run(capsys, "simulate", "stiff_wall", "--json", "--t-end", "0.4", "--out", str(out),
                    "--plot", str(fig))
    assert rc == 0
    for key in ("peak_force", "bounces", "force_rms_error"):
        assert key in d
    assert d["bounces"] >= 1 and d["t_end"] == pytest.approx(0.4)
    sim = SwitchedSimulation.load(out)
    assert sim.peak_force == pytest.approx(d["peak_force"]) and fig.stat().st_size > 1000


def test_simulate_wrist_reports_reduced_model(capsys):
    rc, d, _ = _run(capsys, "simulate", "compliant_wrist", "--json", "--t-end", "0.3")
    assert rc == 0 and "reduced" in d and d["reduced"]["bounces"] == 0


@pytest.mark.parametrize("opt, error", [(["--controller", "C1"], "SceneError"), (["--plant-set", "M=2"], "OptionError")])
def test_simulate_rejects_meaningless_options(capsys, opt, error):
    rc, d, _ = _run(capsys, "simulate", "stiff_wall", "--json", *opt)
    assert rc == 2 and d["error"] == error


def test_unknown_parameter(capsys):
    rc, d, _ = _run(capsys, "analyze", "stiff_wall", "--set", "nope=1", "--json")
    assert rc == 2 and d["error"] == "ParameterError"
    with pytest.raises(ParameterError):
        wall.build(nope=1.0)


def test_scene_objects():
    sc = wrist.build(bt=300.0)
    assert sc.params["be_hat"] == pytest.approx(300.0 * 1e6 / (1e6 + 5e4))  # derived follows bt
    rep = sc.analyze(with_iss=False)
    assert rep.guas
    assert sc.with_params(bt=50.0).analyze(with_iss=False).guas is False


# --- sweeps and maps ----------------------------------------------------------------------------
def test_lambda_sweep_over_bf_is_monotone_and_crosses_one_once():
    sw = lambda_sweep(wall.build().params, "bf", np.geomspace(1, 1e5, 40))
    lam = sw["Lambda"]
    ok = np.isfinite(lam)
    assert np.all(np.diff(lam[ok]) < 0)
    assert np.sum(np.diff((lam[ok] < 1).astype(int)) != 0) == 1


def test_lambda_map_and_visible_region():
    p = wrist.build().params
    kt = np.geomspace(3e3, 3e5, 6)
    bt = np.geomspace(10, 3000, 6)
    m = lambda_map(p, kt, bt)
    assert m["Lambda"].shape == (6, 6)
    # a numerical spot check of the map
    i, j = 2, 3
    s = error_system({**p, "kt": kt[i], "bt": bt[j]})
    if not m["visible"][i, j]:
        assert m["Lambda"][i, j] == pytest.approx(lambda_numerical(s).Lambda, rel=1e-6)
    # with real free-motion eigenvalues (kd large) a bounce-free region exists
    q = {**p, "kd": 400.0}
    border = visible_region(q, [1e4, 3e4])
    assert np.all(np.isfinite(border))
    from invctl.stability.conewise import visible_eigenvectors

    for kt_i, b in zip([1e4, 3e4], border):
        assert visible_eigenvectors(error_system({**q, "kt": kt_i, "bt": b * 1.0001}))
        assert not visible_eigenvectors(error_system({**q, "kt": kt_i, "bt": b * 0.9999}))


def test_design_kt_max_is_border():
    p = wrist.build().params
    kt = design_kt_max(p)
    assert lambda_point({**p, "kt": kt * 0.999}).guas and not lambda_point({**p, "kt": kt * 1.001}).guas
    assert math.isfinite(design_bt_min(p))


def test_reduction_check_poles():
    # rigid wall: the closed loop is the error system itself
    rc = reduction_check(wall.build().params)
    assert rc["free"]["rel_error"] < 1e-12 and rc["contact"]["rel_error"] < 1e-12
    # wrist at the paper's design: slow poles of the 4-state loop within 5 % of (27)-(28)
    rc = reduction_check(wrist.build().params)
    assert rc["free"]["rel_error"] < 0.05 and rc["contact"]["rel_error"] < 0.05
    # much more wrist damping: mu4 = (bt + be)/(kt + ke) no longer small for the contact pole
    assert reduction_check(wrist.build(bt=500.0).params)["contact"]["rel_error"] > 0.1


def test_analyze_wrist_warns_when_reduction_is_poor(capsys):
    rc, d, out = _run(capsys, "analyze", "compliant_wrist", "--set", "bt=500", "--json", "--samples", "16")
    assert rc == 0 and d["reduction_ok"] is False and "WARNING" in out.out


def test_ctrl_c_in_the_reduced_run_of_a_wrist_keeps_the_full_run(tmp_path, monkeypatch, capsys):
    """The compliant wrist simulates the full loop, then its reduced model (27)-(28): a Ctrl-C in the
    second run writes the complete first one as the partial result (exit 130, listed in the JSON)."""
    from invctl.errors import RunInterrupted
    from invctl.studies import switched_report

    real = switched_report.simulate_scenario

    def interrupted_reduced(p, *, reduced=False, **kw):
        if reduced:
            raise RunInterrupted("switched simulation interrupted", partial=None)
        return real(p, reduced=reduced, **kw)

    monkeypatch.setattr(switched_report, "simulate_scenario", interrupted_reduced)
    out = tmp_path / "w.npz"
    rc = main(["simulate", "compliant_wrist", "--t-end", "0.2", "--out", str(out), "--json"])
    d = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert rc == 130 and d["error"] == "RunInterrupted" and "reduced model" in d["message"], d
    assert d["partial"] == [str(tmp_path / "w.partial.npz")] and not out.exists()
    full = SwitchedSimulation.load(tmp_path / "w.partial.npz")
    assert full.status == "ok" and full.t[-1] == pytest.approx(0.2) and full.xt.size == full.t.size
