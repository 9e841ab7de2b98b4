"""The C1/C2/C3 study of 003 Sect. 6 (needs the servo-constraint inverse of the reference model)."""
import json

import numpy as np
import pytest

import problems.manipulator as scene
from invctl.cli import main as cli_main
from invctl.studies.tracking import TrackingStudy, run_tracking_study, setup_tracking


@pytest.fixture(scope="module")
def setup():
    return setup_tracking(scene.SCENE, invert=True)


@pytest.fixture(scope="module")
def study(setup):
    return run_tracking_study(scene.SCENE, setup=setup, progress=False)


def test_feedforward_is_causal_and_matches_reference_model(setup):
    """u_ff is zero before t0; on the reference model itself C3 (feedforward only) tracks closely."""
    t, u = setup.u_ff_samples()
    assert np.all(np.isfinite(u))
    assert np.allclose(setup.inverse.u_causal(np.array([-0.5, -0.1])), 0.0)
    from invctl.simulate.closed_loop import ClosedLoop

    exact = ClosedLoop(setup.model, setup.reference, u_ff=(t, u), signals=setup.signals,
                       t_end=setup.t_end).run(setup.q0)
    mismatched = setup.loop("C3").run(setup.q0)
    print(f"C3 on the reference model: cum. error {exact.cumulative_output_error:.3g}; "
          f"on the plant: {mismatched.cumulative_output_error:.3g}")
    # only the clipped pre-actuation separates the reference model from exact tracking: the error
    # of the matched model is a fraction of the mismatched one
    assert exact.cumulative_output_error < 0.5 * mismatched.cumulative_output_error


def test_study_ordering_and_reductions(study):
    runs = study.runs
    print("\n" + study.table())
    for name in ("C1", "C2", "C3"):
        assert runs[name].status == "ok", (name, runs[name].message)
    for kind in ("output", "end effector"):
        e = [runs[c].cumulative_errors[kind] for c in ("C1", "C2", "C3")]
        assert e[0] < e[1] < e[2], (kind, e)
    red = study.reductions
    assert red["output"] >= 0.30 and red["end effector"] >= 0.30, red
    for name in ("C1", "C2"):
        assert runs[name].max_funnel_ratio < 1.0
        assert runs[name].max_constraint_drift < 1e-6
    # C1's feedback works less than C2's: smaller funnel ratio (Fig. 9) and smaller feedback input
    assert runs["C1"].max_funnel_ratio < runs["C2"].max_funnel_ratio
    assert np.abs(runs["C1"].u_fb).max() < np.abs(runs["C2"].u_fb).max()


def test_study_save_load_plot(study, tmp_path):
    study.save(tmp_path)
    back = TrackingStudy.load(tmp_path)
    assert back.reductions == pytest.approx(study.reductions)
    figs = back.plot(tmp_path)
    assert len(figs) == 5 and (tmp_path / "funnel.png").exists()


def test_cli_simulate_json(capsys):
    rc = cli_main(["simulate", "manipulator", "--controller", "C2", "--plant-set", "m3=0.55", "--json"])
    out = capsys.readouterr().out.strip().splitlines()
    assert rc == 0
    data = json.loads(out[-1])
    for key in ("cumulative_output_error", "max_funnel_ratio",
                "max_constraint_drift", "wall_s"):
        assert key in data
    assert data["plant"]["m3"] == pytest.approx(0.55)
    assert data["max_funnel_ratio"] < 1


def test_c1_on_the_reference_model_is_nearly_exact(setup):
    """Along the inverse's trajectory every error level of C1 vanishes; on the reference model only the
    clipped pre-actuation remains, which the feedback removes: C1 error << C3 error, small u_fb."""
    from invctl.simulate.closed_loop import ClosedLoop

    uff = setup.u_ff_samples()
    c1 = ClosedLoop(setup.model, setup.reference, controller=setup.c1_controller(), u_ff=uff,
                    signals=setup.signals).run(setup.q0)
    c3 = ClosedLoop(setup.model, setup.reference, u_ff=uff, signals=setup.signals).run(setup.q0)
    print(f"reference model: C1 {c1.cumulative_output_error:.3g}, C3 {c3.cumulative_output_error:.3g}, "
          f"max |u_fb| {np.abs(c1.u_fb).max():.3g}")
    assert c1.cumulative_output_error < 0.05 * c3.cumulative_output_error
    assert np.abs(c1.u_fb).max() < 0.5 * np.abs(c1.u_ff).max()


def _run_or_violation(s, name):
    from invctl.errors import FunnelViolation
    from invctl.studies.tracking import run_controller

    try:
        r = run_controller(s, name)
        return "inside", r
    except FunnelViolation as exc:
        assert exc.partial is not None and exc.diagnostics["t"] == pytest.approx(exc.partial.t[-1])
        return "violation", exc.partial


@pytest.mark.parametrize("case", ["m3x1.5", "tight", "tf=0.5"])
def test_c1_extremes(setup, case):
    opts = {"m3x1.5": dict(inverse=setup.inverse, plant_factors={"m3": 1.5}),
            "tight": dict(inverse=setup.inverse, feedback={"phi_bar": (1.0, 3.0, 0.002),
                                                           "funnels": [(1.0, 3.0, 0.005)] * 2}),
            "tf=0.5": dict(reference=lambda m: scene.reference(m, tf=0.5))}[case]
    s = setup_tracking(scene.SCENE, **opts)
    kinds = {}
    for name in ("C1", "C2"):
        kind, r = _run_or_violation(s, name)
        kinds[name] = kind
        print(f"{case} {name}: {kind} (t = {r.t[-1]:.3f}), cum. err {r.cumulative_output_error:.4g}, "
              f"max ratio {r.max_funnel_ratio:.3f}, input peaks {r.input_peaks.round(2)}")
    # with the feedforward the feedback has less to do: C1 never fails where C2 succeeds
    assert not (kinds["C1"] == "violation" and kinds["C2"] == "inside")


def test_cli_set_options_and_bad_controller(capsys):
    """--set (reference model), --t-end and --plant-set together; an unknown controller is a SceneError (exit 2)."""
    rc = cli_main(["simulate", "manipulator", "--controller", "C2", "--set", "L3=0.5", "--t-end", "0.3",
                   "--plant-set", "c=5", "--json"])
    assert rc == 0
    bad = cli_main(["simulate", "manipulator", "--controller", "C9", "--json"])
    assert bad == 2
    err = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert err["error"] == "SceneError" and "C1" in err["message"]


def test_cli_pipeline(tmp_path, capsys):
    import matplotlib.pyplot as plt

    open_before = set(plt.get_fignums())
    rc = cli_main(["pipeline", "manipulator", "--out-dir", str(tmp_path), "--quiet", "--json"])
    out = capsys.readouterr().out.strip().splitlines()
    assert rc == 0
    data = json.loads(out[-1])
    assert set(data["runs"]) == {"C1", "C2", "C3", "C1-42"}
    assert data["reductions"]["output"] >= 0.3
    assert any("C1 reduces C2" in line for line in out)
    for f in ("states", "path_end_effector", "errors", "inputs", "funnel"):
        assert (tmp_path / f"{f}.png").exists()
    assert set(plt.get_fignums()) == open_before  # written figures are closed


def test_a1_for_our_gains(setup, study):
    """(A1) for FEEDBACK: holds at the design point and along every simulated trajectory (it is only local:
    the whole region U is not covered, as for the paper's own choice)."""
    fb = scene.FEEDBACK
    rep = setup.lin.check_A1(fb["K"], rho=fb["rho"], k_i=fb["k_i"], samples=200)
    assert rep.zero_conditions_residual == 0.0
    assert rep.min_eig_at_design_point > 0.1
    assert 0.5 < rep.fraction_satisfied < 1.0
    for name, a1 in study.info["a1_along_trajectory"].items():
        assert a1["fraction_positive"] == 1.0 and a1["min_eig"] > 0.3, name
