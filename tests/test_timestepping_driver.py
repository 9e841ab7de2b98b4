"""The C driver loop of the Moreau-Jean stepper (run numbers as a held input, the parametric part
hoisted, one compiled step per active set, rows written only when kept): the same numbers as the
VM loop to the last bit, the numpy reference after new parameters, statistics equal to a numpy
recomputation from an every-step record, and the failure paths."""
import casadi as ca
import numpy as np
import pytest

import invctl_scenes.bouncing_ball as bb
import invctl_scenes.prismatic_clearance as prism
from invctl.control.pdplus import pd_gravity
from invctl.errors import ContactError, SimulationFailed
from invctl.model import Gap, Model, ParamSet
from invctl.simulate.codegen import compile_c
from invctl.simulate.timestepping import _LCP_FAILED, _NONFINITE, MoreauJean, _CDriver, _driver_code, c_compiler

pytestmark = pytest.mark.skipif(c_compiler() is None, reason="no C compiler on this machine")
Q0, V0 = [0.0, 0.055], [0.0, 0.3]


@pytest.fixture(scope="module")
def prism_pair():
    model = prism.build(actuators=1)
    p = prism.PARAMS
    law = pd_gravity(model, Kp=p["Kp"], Kv=p["Kv"], q_d=p["qd"], idx=[0])
    return (MoreauJean(model, law, backend="vm", chunk=512), MoreauJean(model, law, backend="c", chunk=512))


def _box(n_walls: int):
    """A point mass under gravity in a box: 2 or 4 unilateral walls (e = 0.6), no input."""
    P = ParamSet(["m", "g"])
    q, v = ca.SX.sym("q", 2), ca.SX.sym("v", 2)
    walls = [Gap("floor", q[1], 0.6), Gap("left", q[0], 0.6), Gap("right", 1 - q[0], 0.6),
             Gap("roof", 1 - q[1], 0.6)][:n_walls]
    return Model("box", q, v, P, {"m": 1.0, "g": 9.81}, M=P["m"] * ca.SX.eye(2),
                 f=ca.vertcat(0, -P["m"] * P["g"]), B=ca.SX.zeros(2, 0), gaps=walls)


def _same_run(a, b):
    """Two runs with the same record and statistics, to the last bit."""
    for name in ("t", "q", "v", "P", "active", "gaps", "energy", "V"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    for k, va in a.stats.items():
        if k in ("wall_s", "steps_per_s", "backend", "memory_estimate_bytes", "memory_budget_bytes"):
            continue
        np.testing.assert_array_equal(np.asarray(va), np.asarray(b.stats[k]), err_msg=k)


@pytest.mark.parametrize("record,every", [("steps", 1), ("steps", 7), ("events", 1), ("events", 50)])
def test_driver_equals_vm_bit_for_bit(prism_pair, record, every):
    """Every record mode (the driver keeps every ``every``-th row and, for the impact table, the
    event rows and the rows after them): records, statistics and impact tables equal the VM's."""
    vm, c = prism_pair
    a = vm.run(Q0, V0, 0.3, 1e-4, record=record, record_every=every)
    b = c.run(Q0, V0, 0.3, 1e-4, record=record, record_every=every)
    assert b.stats["backend"] == "c" and a.stats["n_impacts"] >= 3
    _same_run(a, b)


@pytest.mark.parametrize("record", ["steps", "events"])
def test_local_loops_equal_the_vm(prism_pair, record):
    """Between two kept rows the driver runs one loop per active-set variant with the state in local
    variables (its first step by the variant, the next ones by the variant's steady form): over
    1000-step stretches with impacts and active-set changes inside them, the records (every 1000th
    step, with the event rows) and every statistic equal the VM's to the last bit."""
    vm, c = prism_pair
    assert "#define MJ_LOCAL_LOOPS 1" in _driver_code(c)
    assert "#define MJ_LOCAL_LOOPS 0" in _driver_code(c, local_loops=False)
    a = vm.run(Q0, V0, 0.45, 1e-4, record=record, record_every=1000)
    b = c.run(Q0, V0, 0.45, 1e-4, record=record, record_every=1000)
    assert a.stats["n_impacts"] >= 3 and a.stats["n_changes"] >= 6
    _same_run(a, b)


def test_unconverged_lcp_steps_inside_the_local_loops():
    """A one-pivot Lemke budget on the piled-up 2-block chain (short steps: the unrecorded ones run in
    the local loops): a loop stops before each flagged step, which is recomputed exactly; the C run
    equals the VM run to the last bit."""
    from test_lcp_compiled import _bench, _piled_up

    model, law, U = _bench().chain(2)
    q0, v0 = _piled_up(2)
    kw = dict(potential=U, lcp="lemke", lcp_iters=1, chunk=128)
    vm, c = MoreauJean(model, law, backend="vm", **kw), MoreauJean(model, law, backend="c", **kw)
    assert "#define MJ_LOCAL_LOOPS 1" in _driver_code(c)
    a = vm.run(q0, v0, 0.3, 1e-3, record_every=50)
    b = c.run(q0, v0, 0.3, 1e-3, record_every=50)
    assert b.stats["lcp_recomputed"] == a.stats["lcp_recomputed"] >= 3
    _same_run(a, b)
    # without the event rows (their steps go through the driver's own path) a local loop itself stops
    # before the flagged step: the same step and state as the driver without local loops
    x, p = c.initial_state(q0, v0, h=1e-3)
    out = [_CDriver(c, compile_c(_driver_code(c, local_loops=ll)), 128)(x, p, 0, 300, 50, 0) for ll in (1, 0)]
    assert out[0][3] == out[1][3] == _LCP_FAILED and out[0][2] == out[1][2] >= 1
    np.testing.assert_array_equal(out[0][4], out[1][4])


@pytest.mark.parametrize("n_walls", [2, 4])
def test_active_set_steps_equal_the_generic_step(n_walls):
    """A ball bouncing into a corner (two contacts active at once, persistent contact at the end):
    the per-active-set steps (2 walls) and the no-contact/generic pair (4 walls) equal the VM's
    generic step to the last bit."""
    model = _box(n_walls)
    q0, v0 = [0.05, 0.3], [-0.4, 0.0]
    a = MoreauJean(model, backend="vm").run(q0, v0, 1.5, 1e-3, record_every=3)
    b = MoreauJean(model, backend="c").run(q0, v0, 1.5, 1e-3, record_every=3)
    assert np.any(np.all(b.P[:2] > 0, axis=0)) or np.sum(a.stats["P_sum"][:2] > 0) == 2
    assert a.stats["n_impacts"] >= 4
    _same_run(a, b)


def test_new_parameters_without_rebuilding_give_the_numpy_reference(prism_pair):
    """Parameters and gains are an input held over the loop: runs with other values reuse the
    compiled driver and give the numpy reference's trajectory for those values."""
    _, c = prism_pair
    law, q0 = c.law, [0.0, 0.059]  # 1 mm from the upper contact: an impact within 4 ms
    c.run(q0, V0, 0.02, 1e-4)
    loops = dict(c._loops)
    times = []
    for gains, params in ((law.values(Kp1=250.0, Kv1=35.0, qd1=0.1), [1.0, 0.3, 0.05, 0.11, 0.7]), (None, None)):
        tr = c.run(q0, V0, 0.02, 1e-4, gains=gains, params=params)
        Q, V = c.reference_run(q0, V0, 200, 1e-4, gains=gains, params=params)
        assert tr.stats["n_impacts"] == 1
        times.append(tr.impact_times[0])
        np.testing.assert_allclose(tr.q, Q, atol=1e-13)
        np.testing.assert_allclose(tr.v, V, atol=1e-11)
    assert times[0] != times[1]  # the parameters changed the motion
    assert c._loops.keys() == loops.keys() and all(c._loops[k] is loops[k] for k in loops)


def test_statistics_equal_a_numpy_recomputation(prism_pair):
    """The running statistics of a decimated C run equal their recomputation with numpy from an
    every-step record (smallest gaps, largest one-step E and V increase, impacts, changes of the
    active or loaded set, summed impulses)."""
    _, c = prism_pair
    full = c.run(Q0, V0, 0.4, 1e-4)
    dec = c.run(Q0, V0, 0.4, 1e-4, record_every=1000)
    vtol = full.stats["rest_vel_tol"] / 10  # impact_vel_tol (default rest_vel_tol = 10 impact_vel_tol)
    np.testing.assert_array_equal(dec.stats["gap_min"], full.gaps.min(axis=1))
    assert dec.stats["dE_max"] == max(0.0, np.diff(full.energy).max())
    assert dec.stats["dV_max"] == max(0.0, np.diff(full.V).max())
    loaded = np.c_[np.zeros(2, bool), full.P > 0]
    act = np.c_[np.zeros(2, bool), full.active]
    U = full.stats["Un"][:, :-1]
    n_imp = np.sum(loaded[:, 1:] & ~loaded[:, :-1] & (U < -vtol))
    n_chg = np.sum(np.any((act[:, 1:] != act[:, :-1]) | (loaded[:, 1:] != loaded[:, :-1]), axis=0))
    assert dec.stats["n_impacts"] == n_imp >= 3
    assert dec.stats["n_changes"] == n_chg
    np.testing.assert_allclose(dec.stats["P_sum"], full.P.sum(axis=1), rtol=1e-12)


def test_projection_steps_equal_the_vm():
    """With the position projection (part of every variant): the bouncing ball's C run equals the VM's."""
    m = bb.build()
    a, b = (MoreauJean(m, potential=bb.potential(m), backend=k, projection=True).run([1.0], [0.0], 3.0, 1e-3,
                                                                                      record_every=3)
            for k in ("vm", "c"))
    assert a.stats["n_impacts"] >= 5 and a.max_gap_violation <= 1e-10
    _same_run(a, b)


def test_non_finite_state_stops_the_driver_with_the_prefix():
    """A force that is infinite below y = 0.5 stops the C run at the same step as the VM run, with
    the same finite prefix in exc.partial."""
    P = ParamSet(["m"])
    q, v = ca.SX.sym("q", 1), ca.SX.sym("v", 1)
    model = Model("pole", q, v, P, {"m": 1.0}, M=ca.reshape(P["m"], 1, 1),
                  f=-9.81 * P["m"] + ca.if_else(q[0] < 0.5, ca.inf, 0), B=ca.SX.zeros(1, 0),
                  gaps=[Gap("ground", q[0], 0.5)])
    out = {}
    for backend in ("vm", "c"):
        with pytest.raises(SimulationFailed) as ei:
            MoreauJean(model, backend=backend, chunk=64, substeps=1).run([1.0], [0.0], 2.0, 1e-3, record_every=10)
        out[backend] = ei.value
    assert out["c"].diagnostics["step"] == out["vm"].diagnostics["step"]
    np.testing.assert_array_equal(out["c"].partial.q, out["vm"].partial.q)
    assert np.all(np.isfinite(out["c"].partial.q))
    # without the event rows a local loop itself stops after the step: as the driver without local loops
    c = MoreauJean(model, backend="c", chunk=64, substeps=1)
    x, p = c.initial_state([1.0], [0.0], h=1e-3)
    runs = [_CDriver(c, compile_c(_driver_code(c, local_loops=ll)), 64)(x, p, 0, 2000, 1000, 0) for ll in (1, 0)]
    assert runs[0][3] == runs[1][3] == _NONFINITE and runs[0][2] == runs[1][2] == out["c"].diagnostics["step"]
    np.testing.assert_array_equal(runs[0][4], runs[1][4])


def test_unconverged_lcp_steps_in_the_driver():
    """A one-iteration pivoting budget on the piled-up 6-block chain (the no-contact step and the
    generic step): the flagged steps are recomputed exactly (the C run equals the VM run and
    follows the numpy reference), or stop the run with the prefix."""
    from test_lcp_compiled import _bench, _piled_up

    model, law, U = _bench().chain(6)
    q0, v0 = _piled_up()
    kw = dict(potential=U, lcp="pivoting", lcp_iters=1, chunk=128)
    vm, c = MoreauJean(model, law, backend="vm", **kw), MoreauJean(model, law, backend="c", **kw)
    a = vm.run(q0, v0, 0.3, 1e-3, record_every=5)
    b = c.run(q0, v0, 0.3, 1e-3, record_every=5)
    assert b.stats["lcp_recomputed"] == a.stats["lcp_recomputed"] >= 3
    _same_run(a, b)
    Q, _ = c.reference_run(q0, v0, 300, 1e-3)
    np.testing.assert_allclose(b.q, Q[:, b.stats["step_index"]], atol=1e-12)
    with pytest.raises(ContactError, match="did not converge") as ei:
        c.run(q0, v0, 0.3, 1e-3, on_lcp_failure="raise")
    part, k = ei.value.partial, ei.value.diagnostics["step"]
    assert part.stats["steps"] == k and part.q.shape[1] == k + 1
    np.testing.assert_allclose(part.q, Q[:, :k + 1], atol=1e-12)


#: the running statistics the benchmark's numba kernel keeps, and a smaller choice
_MONITORS = [("gaps", "impacts", "energy", "lyapunov", "active_set"), ("gaps", "impacts")]


@pytest.mark.parametrize("monitor", _MONITORS)
def test_reduced_monitor_equals_the_vm_and_the_full_run(prism_pair, monitor):
    """A run monitoring fewer statistics: its compiled step variants are shorter, its C run equals its
    VM run to the last bit, and its records (E and V included: computed at the recorded state instead
    of carried), impact table and monitored statistics equal those of the run monitoring everything to
    the last bit; the unmonitored statistics are absent."""
    full_vm, full_c = prism_pair
    vm, c = (MoreauJean(full_c.model, full_c.law, backend=k, chunk=512, monitor=monitor) for k in ("vm", "c"))
    assert all(f.n_instructions() < g.n_instructions() for f, g in zip(c._variants, full_c._variants))
    assert "#define MJ_LOCAL_LOOPS 1" in _driver_code(c)  # the unrecorded steps still run in the local loops
    unmonitored = {"dE_max", "dV_max", "dV_max_impact", "dV_max_smooth", "rest_last_bad", "n_changes",
                   "lcp_res_max", "P_sum"} - ({"dE_max", "dV_max", "dV_max_impact", "dV_max_smooth", "n_changes"}
                                              if "energy" in monitor else set())
    for record, every in (("events", 50), ("steps", 1000)):
        a = vm.run(Q0, V0, 0.3, 1e-4, record=record, record_every=every)
        b = c.run(Q0, V0, 0.3, 1e-4, record=record, record_every=every)
        _same_run(a, b)
        assert b.stats["monitor"] == monitor and b.stats["n_impacts"] >= 3
        f = full_c.run(Q0, V0, 0.3, 1e-4, record=record, record_every=every)
        assert set(f.stats) - set(b.stats) == unmonitored
        b.stats["monitor"] = f.stats["monitor"]
        _same_run(b, f)
