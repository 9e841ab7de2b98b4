"""Long Moreau-Jean runs in bounded memory: decimated and event records streamed from the compiled
loop, exact statistics under decimation, the memory estimate and its errors."""
import tracemalloc

import casadi as ca
import numpy as np
import pytest

import invctl_scenes.bouncing_ball as bb
import invctl_scenes.prismatic_clearance as prism
from invctl.control.pdplus import pd_gravity
from invctl.errors import ParameterError, RecordingError, ResourceLimitError, SimulationFailed
from invctl.model import Gap, Model, ParamSet
from invctl.simulate.contact_record import ChunkRecorder
from invctl.simulate.timestepping import ContactTrajectory, MoreauJean, c_compiler


@pytest.fixture(scope="module")
def ball():
    m = bb.build()
    return MoreauJean(m, potential=bb.potential(m), backend="vm", chunk=256)


@pytest.fixture(scope="module")
def prism_pd():
    model = prism.build(actuators=1)
    p = prism.PARAMS
    law = pd_gravity(model, Kp=p["Kp"], Kv=p["Kv"], q_d=p["qd"], idx=[0])
    return MoreauJean(model, law, backend="vm", chunk=512)


def _same_stats(full, part):
    """Statistics of a reduced record equal those of the complete record (exactly: the
    same floating-point operations on the same values, in the loop instead of on arrays)."""
    assert part.max_gap_violation == full.max_gap_violation
    assert part.max_V_increase == full.max_V_increase
    assert part.max_energy_increase == full.max_energy_increase
    assert part.rest_time() == full.rest_time() or (np.isnan(part.rest_time()) and np.isnan(full.rest_time()))
    a, b = full.impacts(), part.impacts()
    assert a[0].size == b[0].size > 0
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(full.impact_times, part.impact_times)
    assert part.stats["n_impacts"] == a[0].size


@pytest.mark.parametrize("every", [7, 100, 10**6])
def test_decimated_rows_and_exact_statistics(ball, every):
    """Row j of a decimated record is step j*every of the full record (plus the final state);
    max gap violation, V/energy increase, impacts, rest time are those of every step."""
    full = ball.run([1.0], [0.0], 5.0, 1e-3)
    part = ball.run([1.0], [0.0], 5.0, 1e-3, record_every=every)
    N = full.stats["steps"]
    idx = np.r_[np.arange(0, N, every), N]
    np.testing.assert_array_equal(part.stats["step_index"], idx)
    np.testing.assert_array_equal(part.q, full.q[:, idx])
    np.testing.assert_array_equal(part.v, full.v[:, idx])
    np.testing.assert_array_equal(part.t, full.t[idx])
    np.testing.assert_array_equal(part.energy, full.energy[idx])
    np.testing.assert_array_equal(part.P, full.P[:, idx[:-1]])
    assert part.P.shape[1] == part.t.size - 1 and not part.complete and full.complete
    _same_stats(full, part)
    assert abs(part.rest_time() - bb.exact_impacts(1.0, 9.81, 0.8, 10.0)[3]) < 0.01


def test_event_record_two_contacts(prism_pd):
    """Events: impacts and active/loaded-set changes (and step 0) recorded, each row equal to the full
    record's row; the impact table equals the one derived from every step; dV at impacts exact."""
    full = prism_pd.run([0.0, 0.055], [0.0, 0.3], 1.0, 1e-4)
    ev = prism_pd.run([0.0, 0.055], [0.0, 0.3], 1.0, 1e-4, record="events")
    N = full.stats["steps"]
    loaded = full.P > 0
    change = np.r_[True, np.any(loaded[:, 1:] != loaded[:, :-1], axis=0)
                   | np.any(full.active[:, 1:] != full.active[:, :-1], axis=0)]  # step 0 is always recorded
    expect = np.union1d(np.flatnonzero(change | np.any(full.impact_mask(), axis=0)), [0])
    np.testing.assert_array_equal(ev.stats["step_index"], np.r_[expect, N])
    np.testing.assert_array_equal(ev.q, full.q[:, np.r_[expect, N]])
    np.testing.assert_array_equal(ev.P, full.P[:, expect])
    assert ev.t.size < full.t.size / 50
    _same_stats(full, ev)
    k = np.flatnonzero(np.any(full.impact_mask(), axis=0))
    dV = np.repeat(full.V[k + 1] - full.V[k], full.impact_mask()[:, k].sum(axis=0))
    np.testing.assert_array_equal(ev.stats["impact_dV"], dV)
    assert ev.stats["dV_max_impact"] == max(0.0, dV.max())


def test_events_plus_decimation_is_the_union(prism_pd):
    a = prism_pd.run([0.0, 0.055], [0.0, 0.3], 0.5, 1e-4, record="events")
    b = prism_pd.run([0.0, 0.055], [0.0, 0.3], 0.5, 1e-4, record_every=250)
    c = prism_pd.run([0.0, 0.055], [0.0, 0.3], 0.5, 1e-4, record="events", record_every=250)
    np.testing.assert_array_equal(c.stats["step_index"], np.union1d(a.stats["step_index"], b.stats["step_index"]))


@pytest.mark.parametrize("chunk,substeps", [(64, 4), (256, 2), (8192, 4)])
def test_chunking_does_not_change_the_result(chunk, substeps):
    """Chunk boundaries, partial last chunks and the single-step replay inside a fused group
    (N = 4999 is not a multiple of the chunk or of substeps) leave rows and statistics unchanged."""
    m = bb.build()
    ref = MoreauJean(m, potential=bb.potential(m), backend="vm", chunk=64, substeps=1)
    mj = MoreauJean(m, potential=bb.potential(m), backend="vm", chunk=chunk, substeps=substeps)
    a = ref.run([1.0], [0.0], 4.999, 1e-3, record_every=13)
    b = mj.run([1.0], [0.0], 4.999, 1e-3, record_every=13)
    assert a.stats["steps"] == 4999
    np.testing.assert_array_equal(a.q, b.q)
    for key in ("gap_min", "dE_max", "dV_max", "rest_last_bad", "n_impacts", "impact_t", "impact_v_plus"):
        np.testing.assert_array_equal(a.stats[key], b.stats[key])


def test_million_steps_in_bounded_memory():
    """1e6 steps decimated by 1000: the record holds 1000 rows and the final state, Python-side
    allocations during the run stay below the estimate, a few per cent of what the undecimated
    record needs, and the statistics are exact: with
    e = 1 and theta = 1/2 the energy is conserved to round-off through ~1100 impacts, whose count
    and times follow the closed form (period 2 sqrt(2 H / g) to first order in h)."""
    model = bb.build(e=1.0)
    mj = MoreauJean(model, potential=bb.potential(model))
    h, N = 1e-3, 10**6
    mj.run([1.0], [0.0], 0.01, h)  # build (and compile) before measuring
    tracemalloc.start()
    tracemalloc.reset_peak()
    tr = mj.run([1.0], [0.0], N * h, h, record_every=1000)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    full = (N + 1) * ChunkRecorder.row_bytes_of(mj.rows)
    assert tr.t.size == N // 1000 + 1 and tr.stats["steps"] == N
    # the estimate (records + chunk buffers) bounds what the run allocated, and both are constant
    # (chunk buffers, ~2 MB) plus 1000 rows: a few per cent of the 81 MB an undecimated record needs
    assert peak <= tr.stats["memory_estimate_bytes"] < 0.05 * full, (peak, tr.stats["memory_estimate_bytes"], full)
    T = 2 * np.sqrt(2 / 9.81)
    ti = tr.impact_times
    period = np.diff(ti)
    # event capturing: the discrete motion is periodic (same number of steps per bounce, to round-off
    # of the step mid-points) with a period within 2 h of the exact one (first order)
    assert np.ptp(period) < 1e-9 and abs(period[0] - T) <= 2 * h
    assert abs(ti[0] - T / 2) <= h and ti.size == int(np.floor((N * h - ti[0]) / period[0])) + 1
    assert tr.max_energy_increase <= 1e-12 * tr.energy[0]
    assert np.max(np.abs(tr.energy - tr.energy[0])) <= 1e-11 * tr.energy[0]


def test_run_that_does_not_fit_raises_with_the_settings_that_fit():
    """The failing runs of the issue (t_end = 1e6 on the ball; h = 1e-9 on the prismatic clearance)
    raise before allocating, naming record_every, record='events' and t_end; the suggestion fits."""
    m = bb.build()
    mj = MoreauJean(m, potential=bb.potential(m), backend="vm")
    budget = 2 << 30
    with pytest.raises(ResourceLimitError) as ei:
        mj.run([1.0], [0.0], 1e6, 1e-3, memory_budget=budget)
    msg = str(ei.value)
    assert "record_every=" in msg and 'record="events"' in msg and "t_end <=" in msg
    d = ei.value.diagnostics
    assert d["estimate_bytes"] > budget >= d["buffer_bytes"]
    k = d["fits"]["record_every"]
    rows = ChunkRecorder.rows_needed(10**9, k, False)
    assert rows * d["row_bytes"] + d["buffer_bytes"] <= budget < ChunkRecorder.rows_needed(10**9, k - 1, False) * \
        d["row_bytes"] + d["buffer_bytes"]
    model = prism.build(actuators=1)
    law = pd_gravity(model, Kp=100.0, Kv=20.0, q_d=0.2, idx=[0])
    with pytest.raises(ResourceLimitError, match="record_every="):
        MoreauJean(model, law, backend="vm").run([0.0, 0.055], [0.0, 0.3], 2.0, 1e-9)


def test_small_budget_then_suggested_decimation_runs(ball):
    with pytest.raises(ResourceLimitError) as ei:
        ball.run([1.0], [0.0], 20.0, 1e-4, memory_budget=4e6)
    k = ei.value.diagnostics["fits"]["record_every"]
    tr = ball.run([1.0], [0.0], 20.0, 1e-4, memory_budget=4e6, record_every=k)
    assert tr.stats["memory_estimate_bytes"] <= 4e6 and tr.t.size == -(-200000 // k) + 1


def test_event_record_outgrowing_the_budget_stops_with_the_prefix():
    """An elastic ball bouncing from 1 cm makes ~2200 impacts in 200 s, each an event row; the
    estimate cannot foresee them, so the run stops when the record outgrows the budget, with the
    record so far (a valid trajectory prefix) in exc.partial."""
    model = bb.build(e=1.0)
    mj = MoreauJean(model, potential=bb.potential(model), backend="vm", chunk=64, substeps=1)
    est = mj.run([0.01], [0.0], 0.5, 1e-3, record="events").stats["memory_estimate_bytes"]
    with pytest.raises(ResourceLimitError) as ei:
        mj.run([0.01], [0.0], 200.0, 1e-3, record="events", memory_budget=est + 3000)
    part = ei.value.partial
    assert isinstance(part, ContactTrajectory) and 0 < part.stats["steps"] < 200000
    assert part.impacts()[0].size > 0


def test_bad_arguments(ball):
    for kw in ({"record": "all_of_it"}, {"record_every": 0}, {"record_every": 2.5}, {"memory_budget": -1.0},
               {"memory_budget": "lots"}, {"on_lcp_failure": "ignore"}, {"rest_vel_tol": -1.0}):
        with pytest.raises(ParameterError):
            ball.run([1.0], [0.0], 0.1, 1e-3, **kw)


def test_quantities_that_need_every_step(ball, tmp_path):
    tr = ball.run([1.0], [0.0], 5.0, 1e-3, record_every=50)
    with pytest.raises(RecordingError, match="record_every=1"):
        tr.impact_mask()
    with pytest.raises(RecordingError, match="rest_vel_tol"):
        tr.rest_time(vel_tol=1e-3)
    assert tr.rest_time(vel_tol=tr.stats["rest_vel_tol"]) == tr.rest_time()
    tr2 = ContactTrajectory.load(tr.to_npz(tmp_path / "dec.npz"))
    assert not tr2.complete and tr2.max_gap_violation == tr.max_gap_violation
    for a, b in zip(tr.impacts(), tr2.impacts()):
        np.testing.assert_array_equal(a, b)
    assert tr2.rest_time() == tr.rest_time()


def test_non_finite_state_keeps_the_prefix():
    """A force that is infinite below y = 0.5 (a modelling error) stops the run where the body
    gets there, with the steps before it in exc.partial."""
    P = ParamSet(["m"])
    q, v = ca.SX.sym("q", 1), ca.SX.sym("v", 1)
    model = Model("pole", q, v, P, {"m": 1.0}, M=ca.reshape(P["m"], 1, 1),
                  f=-9.81 * P["m"] + ca.if_else(q[0] < 0.5, ca.inf, 0), B=ca.SX.zeros(1, 0),
                  gaps=[Gap("ground", q[0], 0.5)])
    mj = MoreauJean(model, backend="vm", chunk=64, substeps=1)
    with pytest.raises(SimulationFailed) as ei:
        mj.run([1.0], [0.0], 2.0, 1e-3, record_every=10)
    part = ei.value.partial
    assert part is not None and part.stats.get("partial") and np.all(np.isfinite(part.q))
    k = ei.value.diagnostics["step"]
    assert abs(k * 1e-3 - np.sqrt(2 * 0.5 / 9.81)) < 0.01  # where y crosses 0.5


@pytest.mark.skipif(c_compiler() is None, reason="no C compiler on this machine")
def test_c_backend_stream_equals_vm(prism_pd):
    model, law = prism_pd.model, prism_pd.law
    mc = MoreauJean(model, law, backend="c")
    a = prism_pd.run([0.0, 0.055], [0.0, 0.3], 0.3, 1e-4, record="events")
    b = mc.run([0.0, 0.055], [0.0, 0.3], 0.3, 1e-4, record="events")
    assert b.stats["backend"] == "c"
    np.testing.assert_array_equal(a.stats["step_index"], b.stats["step_index"])
    np.testing.assert_allclose(a.q, b.q, atol=1e-14)
    np.testing.assert_allclose(a.stats["impact_t"], b.stats["impact_t"], atol=0)
