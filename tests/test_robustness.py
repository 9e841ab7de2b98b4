"""Ready-made robustness sweeps, small, on a local process pool and on a local Dask cluster."""
import numpy as np
import pytest

from invctl.studies.robustness import contact_grid, plant_mismatch, plot_sweep, switched_lambda_map


def test_wrist_lambda_map_process_pool(tmp_path):
    res = switched_lambda_map("compliant_wrist", kt=[1e3, 5e4, 1e6], bt=[10.0, 171.0, 1e4], max_workers=2,
                              progress=False)
    assert res.shape == (3, 3)
    # kt = 1e3 makes the wall softer than the position loop (K2 < K1): Theorem 1 does not apply,
    # and every such point is reported with the reason, not dropped
    assert res.n_failed == 3
    assert all(p["kt"] == 1e3 and "StabilityError" in e and "K2 > K1" in e for p, e in res.failed)
    lam, num = res.array("Lambda"), res.array("Lambda_numerical")
    ok = np.isfinite(lam)
    assert ok.sum() >= 4
    # closed form (14)-(16) against the numerically integrated return map (issue 5: 1e-6 relative)
    np.testing.assert_allclose(lam[ok], num[ok], rtol=1e-6)
    assert np.array_equal(res.array("guas")[ok] == 1, lam[ok] < 1)
    # more wrist damping lowers Lambda at fixed stiffness
    for row in lam[1:]:
        r = row[np.isfinite(row)]
        assert np.all(np.diff(r) < 0)
    fig = plot_sweep(res, ["Lambda", "closed_vs_numerical"], tmp_path / "wrist.png", log=["Lambda"],
                     contour={"Lambda": 1.0})
    assert "3 failed of 9" in fig.axes[0].get_title()
    assert (tmp_path / "wrist.png").stat().st_size > 0


def test_funnel_mismatch_process_pool(tmp_path):
    res = plant_mismatch("manipulator", m3=[1.0, 1.5, 10.0], m2=[1.0, 1.3], controller="C2", max_workers=2,
                         progress=False)
    assert res.shape == (3, 2)
    # m3 x 10: pure feedback reaches the funnel boundary (or the integrator gives up just before it);
    # reported with the reason, not dropped
    assert res.n_failed == 2
    assert all(p["m3"] == 10.0 and e.startswith(("FunnelViolation", "SimulationFailed")) for p, e in res.failed)
    err = res.array("cumulative_output_error")
    assert np.all(np.isnan(err[2]))
    # the mismatch in the mass carried on the unstable internal dynamics costs accuracy
    assert np.all(err[1] > err[0])
    # every other run stays inside its funnels (ratio < 1), constraints held by the Baumgarte plant
    assert np.all(res.array("max_funnel_ratio")[:2] < 1)
    assert np.all(res.array("max_constraint_drift")[:2] < 1e-5)
    fig = plot_sweep(res, ["cumulative_output_error", "max_funnel_ratio"], tmp_path / "funnel.png")
    assert "2 failed of 6" in fig.axes[0].get_title()


def test_funnel_mismatch_rejects_unknown_parameter():
    from invctl.errors import ParameterError

    with pytest.raises(ParameterError, match="known"):
        plant_mismatch("manipulator", no_such=[1.0], executor="serial", progress=False)


def test_sweeps_reject_unknown_controllers_and_parameters_before_any_run():
    from invctl.errors import ParameterError, SceneError

    with pytest.raises(SceneError, match=r"unknown controller 'C9'.*C1-inv"):
        plant_mismatch("cartpole", controller="C9", mp=[1.0], executor="serial", progress=False)
    with pytest.raises(ParameterError, match=r"compliant_wrist: give grids of its parameters; unknown \['nope'\]"):
        switched_lambda_map("compliant_wrist", kt=[1e4], nope=[1.0], executor="serial", progress=False)


def test_clearance_grid_dask_local_cluster(tmp_path):
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        # the slot is L = 2 l + c with l = 0.05: clearances c = 1e-6, 1e-3 and 2 m
        res = contact_grid("prismatic_clearance", controller="pd", t_end=1.0, e=[0.0, 1.0],
                           L=[0.1 + 1e-6, 0.1 + 1e-3, 2.1], executor=client, progress=False)
    assert res.shape == (2, 3)
    assert res.n_failed == 0
    # PD (36): V never jumps up at an impact (000 Prop. 2; round-off allowance 1e-12 J)
    assert np.all(res.array("max_V_jump_at_impacts") <= 1e-12)
    # Moreau-Jean penetration is O(h v): h = 1e-4, |v| < 0.5 m/s
    assert np.all(res.array("max_gap_violation") < 5e-5)
    # a 2 m slot is never reached within 1 s: no impact at all
    assert np.all(res.array("n_impacts")[:, 2] == 0)
    # regulation of body 1 to qd = 0.2 m within 1 s whatever the clearance and restitution
    assert np.all(res.array("regulation_error_final") < 5e-3)
    res.to_csv(tmp_path / "grid.csv")
    assert (tmp_path / "grid.csv").read_text().count("\n") == 7


def test_every_error_class_is_documented_for_users():
    from pathlib import Path

    import invctl.errors as errors

    doc = (Path(__file__).resolve().parents[1] / "docs" / "errors.md").read_text()
    classes = [n for n in errors.__all__ if isinstance(getattr(errors, n), type)
               and issubclass(getattr(errors, n), errors.InvctlError)]
    assert len(classes) > 20
    assert [n for n in classes if f"`{n}`" not in doc] == []


@pytest.mark.parametrize("study, scene", [(plant_mismatch, "stiff_wall"), (switched_lambda_map, "cartpole"),
                                          (contact_grid, "manipulator")])
def test_a_study_refuses_a_scene_of_another_kind_before_any_point(study, scene):
    from invctl.errors import SceneError

    with pytest.raises(SceneError, match="needs a (tracking|switched|contact) scene"):
        study(scene, progress=False)
