"""One shape for every result type: time along the LAST axis.

``Inverse`` (mesh arrays and the trajectories it evaluates), ``ClosedLoopResult``, ``SwitchedSimulation``
(1-D signals) and ``ContactTrajectory`` (q, v, gaps: ``(., len(t))``; P, active: ``(m_u, steps)``), checked
on small real runs whose shapes are not square.  ContactTrajectory files of format version 2 (time along
the first axis) still load, transposed to the same object.
"""
import dataclasses
import json

import numpy as np
import pytest

import invctl_scenes.bouncing_ball as bb
import invctl_scenes.prismatic_clearance as prism
from invctl.control.pdplus import pd_gravity
from invctl.errors import ResultFileError
from invctl.simulate.contact_record import CONTACT_FORMAT_VERSION, ContactTrajectory
from invctl.simulate.event_driven import simulate_event_driven
from invctl.simulate.timestepping import MoreauJean


# ------------------------------------------------------------------ contact runs
@pytest.fixture(scope="module")
def prism_run():
    """2 bodies, 2 contacts (impacts on both walls), 501 samples, 1 input."""
    model = prism.build(actuators=1)
    p = prism.PARAMS
    law = pd_gravity(model, Kp=p["Kp"], Kv=p["Kv"], q_d=p["qd"], idx=[0])
    mj = MoreauJean(model, law, backend="vm")
    tr = mj.run([0.0, 0.055], [0.0, 0.3], 0.5, 1e-3)
    return model, mj, tr


def _check_contact_time_last(tr, n, mu, m):
    N = tr.t.size
    assert tr.t.ndim == 1 and tr.energy.shape == (N,) and tr.V.shape == (N,)
    assert tr.q.shape == (n, N) and tr.v.shape == (n, N) and tr.gaps.shape == (mu, N)
    assert tr.P.shape == (mu, N - 1) and tr.active.shape == (mu, N - 1) and tr.active.dtype == bool
    assert tr.stats["Un"].shape == (mu, N)
    if "u" in tr.stats:
        assert tr.stats["u"].shape == (m, N)


def test_contact_trajectory_is_time_last(prism_run):
    model, mj, tr = prism_run
    assert tr.t.size == 501 and model.n == 2 and len(model.gaps) == 2
    _check_contact_time_last(tr, model.n, 2, model.m)
    # the columns are the states at t[k]: the first is the initial state, gaps are those of q[:, k]
    np.testing.assert_array_equal(tr.q[:, 0], [0.0, 0.055])
    np.testing.assert_array_equal(tr.v[:, 0], [0.0, 0.3])
    from invctl.contact.mechanics import ContactSystem

    cs = ContactSystem(model)
    for k in (0, 137, 500):
        np.testing.assert_allclose(tr.gaps[:, k], cs.gaps(tr.q[:, k]), atol=1e-15)
    # impacts: one row per impact, post-impact velocities (n_impacts, n)
    ti, ii, pre, post, vp = tr.impacts()
    assert ti.size >= 2 and vp.shape == (ti.size, model.n)
    assert tr.impact_mask().shape == (2, 500)
    # the reference (numpy) loop has the same layout
    Q, V = mj.reference_run([0.0, 0.055], [0.0, 0.3], 50, 1e-3)
    assert Q.shape == V.shape == (2, 51)
    np.testing.assert_allclose(Q, tr.q[:, :51], atol=1e-12)


def test_reduced_and_event_driven_records_are_time_last(prism_run):
    model, mj, tr = prism_run
    part = mj.run([0.0, 0.055], [0.0, 0.3], 0.5, 1e-3, record_every=7)
    assert part.t.size == 73
    _check_contact_time_last(part, 2, 2, model.m)
    np.testing.assert_array_equal(part.q, tr.q[:, part.stats["step_index"]])
    ev = mj.run([0.0, 0.055], [0.0, 0.3], 0.5, 1e-3, record="events")
    _check_contact_time_last(ev, 2, 2, model.m)
    ball = bb.build()
    ed = simulate_event_driven(ball, [1.0], [0.0], 1.0, potential=bb.potential(ball), dt_out=0.01)
    assert ed.t.size > 50
    _check_contact_time_last(ed, 1, 1, 0)


def _old_layout_copy(path, old_path):
    """What invctl wrote before the layout change: the same entries, time along the first axis, version 2."""
    with np.load(path) as z:
        d = dict(z)
    meta = json.loads(str(d["__invctl__"]))
    assert meta["version"] == CONTACT_FORMAT_VERSION == 3
    for k in ("q", "v", "P", "active", "gaps", "stats:Un", "stats:u"):
        if k in d:
            d[k] = np.ascontiguousarray(d[k].T)
    meta["version"] = 2
    d["__invctl__"] = np.asarray(json.dumps(meta))
    np.savez(old_path, **d)


def _assert_same(a, b):
    for k in ContactTrajectory._ARRAYS:
        x, y = getattr(a, k), getattr(b, k)
        assert x.shape == y.shape and x.dtype == y.dtype, k
        np.testing.assert_array_equal(x, y)
    assert a.h == b.h and a.names == b.names and a.status == b.status and a.impact_vel_tol == b.impact_vel_tol
    assert set(a.stats) == set(b.stats)
    for k, v in a.stats.items():
        if isinstance(v, np.ndarray):
            assert v.shape == np.asarray(b.stats[k]).shape, k
            np.testing.assert_array_equal(v, b.stats[k])
        else:
            assert v == b.stats[k] or (v != v and b.stats[k] != b.stats[k]), k


@pytest.mark.parametrize("every", [1, 7])
def test_version_2_files_load_transposed(prism_run, tmp_path, every):
    model, mj, tr = prism_run
    if every > 1:
        tr = mj.run([0.0, 0.055], [0.0, 0.3], 0.5, 1e-3, record_every=every)  # impact table stays one row per impact
    new = tr.to_npz(tmp_path / "new.npz", meta={"scene": "prismatic_clearance"})
    _old_layout_copy(new, tmp_path / "old.npz")
    a, b = ContactTrajectory.load(new), ContactTrajectory.load(tmp_path / "old.npz")
    _assert_same(a, b)
    _assert_same(tr, a)
    assert a.meta == b.meta == {"scene": "prismatic_clearance"}
    for x, y in zip(b.impacts(), tr.impacts()):
        np.testing.assert_array_equal(x, y)


def test_contact_files_with_other_versions_or_layouts_are_refused(prism_run, tmp_path):
    _, _, tr = prism_run
    new = tr.to_npz(tmp_path / "new.npz")
    with np.load(new) as z:
        d = dict(z)
    meta = json.loads(str(d["__invctl__"]))
    for version, what in ((4, "newer"), (1, "older")):
        dd, mm = dict(d), dict(meta, version=version)
        dd["__invctl__"] = np.asarray(json.dumps(mm))
        np.savez(tmp_path / f"v{version}.npz", **dd)
        with pytest.raises(ResultFileError, match=what):
            ContactTrajectory.load(tmp_path / f"v{version}.npz")
    # a version-3 file holding time-first arrays (a mislabelled old file) is malformed, not transposed silently
    dd = dict(d)
    dd["q"] = np.ascontiguousarray(d["q"].T)
    np.savez(tmp_path / "mixed.npz", **dd)
    with pytest.raises(ResultFileError, match="time along the last axis"):
        ContactTrajectory.load(tmp_path / "mixed.npz")
    raw = new.read_bytes()
    (tmp_path / "cut.npz").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(ResultFileError):
        ContactTrajectory.load(tmp_path / "cut.npz")
    with pytest.raises(ResultFileError, match="no such file"):
        ContactTrajectory.load(tmp_path / "missing.npz")


# ------------------------------------------------------------------ the other result types
@pytest.fixture(scope="module")
def tracking():
    from invctl.scenes import load_scene
    from invctl.studies.tracking import run_controller, setup_tracking

    setup = setup_tracking(load_scene("two_link_arm"), invert=True)
    return setup, run_controller(setup, "C1")


def test_inverse_is_time_last(tracking):
    setup, _ = tracking
    inv = setup.inverse
    N1 = inv.t_mesh.size
    assert inv.X_mesh.shape[-1] == N1 and inv.dX_mesh.shape[-1] == N1 and inv.X_mesh.shape[0] != N1
    t = np.linspace(inv.t_mesh[0], inv.t_mesh[-1], 37)
    n, m = inv.sizes["n"], inv.sizes["m"]
    assert inv.q(t).shape == (n, t.size) and inv.v(t).shape == (n, t.size) and inv.u(t).shape == (m, t.size)


def test_closed_loop_result_is_time_last(tracking):
    _, res = tracking
    N = res.t.size
    arrays = {f.name: getattr(res, f.name) for f in dataclasses.fields(res)
              if isinstance(getattr(res, f.name), np.ndarray) and f.name != "t"}
    assert {"q", "v", "u", "y"} <= set(arrays)
    for name, a in arrays.items():
        assert a.shape[-1] == N, (name, a.shape)
    assert res.q.shape == (2, N) and N != 2


def test_switched_simulation_signals_share_the_time_axis():
    import invctl_scenes.stiff_wall as wall_scene
    from invctl.studies.switched import simulate_scenario

    sim = simulate_scenario(wall_scene.build().params, t_end=0.1, label="shape")
    N = sim.t.size
    for name in ("x", "v", "xd", "xd_dot", "Fd", "Fd_desired", "Fe", "Fc", "wall", "ctrl", "intended"):
        a = getattr(sim, name)
        assert a.ndim == 1 and a.shape[-1] == N, (name, a.shape)
