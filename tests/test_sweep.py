"""Sweeps on a process pool, serially, and on a local Dask cluster; failed points reported."""
import math

import numpy as np
import pytest

from invctl.studies.sweep import grid, sweep


def damped_peak(zeta, wn):
    """Peak overshoot of a second-order step response (closed form vs simulation)."""
    if zeta >= 1:
        raise ValueError("no overshoot for zeta >= 1")
    from scipy.signal import lti, step

    t, y = step(lti([wn**2], [1, 2 * zeta * wn, wn**2]), N=4000, T=np.linspace(0, 40 / wn, 4000))
    return {"overshoot": y.max() - 1.0, "closed_form": math.exp(-math.pi * zeta / math.sqrt(1 - zeta**2))}


POINTS = grid(zeta=[0.1, 0.3, 1.2], wn=[1.0, 4.0])


def _check(res):
    assert res.shape == (3, 2)
    over = res.array("overshoot")
    cf = res.array("closed_form")
    ok = ~np.isnan(over)
    # tolerance: 4000-point step response resolves the peak to ~1e-4
    np.testing.assert_allclose(over[ok], cf[ok], atol=2e-3)
    assert res.n_failed == 2
    assert all("no overshoot" in e for _, e in res.failed)
    assert all(p["zeta"] == 1.2 for p, _ in res.failed)


def test_sweep_serial():
    _check(sweep(damped_peak, POINTS, executor="serial", progress=False))


def test_sweep_process_pool(tmp_path):
    res = sweep(damped_peak, POINTS, max_workers=2, progress=False)
    _check(res)
    res.to_csv(tmp_path / "s.csv")
    text = (tmp_path / "s.csv").read_text()
    assert "no overshoot" in text and text.count("\n") == 7


def test_sweep_dask_local_cluster():
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        _check(sweep(damped_peak, POINTS, executor=client, progress=False))


def test_sweep_plot_marks_failures():
    import matplotlib

    matplotlib.use("Agg")
    res = sweep(damped_peak, POINTS, executor="serial", progress=False)
    ax = res.plot("overshoot")
    assert "2 failed of 6" in ax.get_title()


def test_sweep_and_library_share_the_executor_choice():
    """A sweep checks its executor as a library does (a ParameterError naming what is accepted, before any point
    runs); one worker runs in this process, a pool of two is owned and shut down by the caller."""
    from invctl.errors import ParameterError
    from invctl.studies.sweep import executor_slots, open_executor

    with pytest.raises(ParameterError, match="concurrent.futures.Executor, a dask.distributed.Client or 'serial'"):
        sweep(damped_peak, POINTS, executor=object(), progress=False)
    assert open_executor(None, 1) == (None, False, 1) and open_executor("serial", 8) == (None, False, 1)
    ex, owned, slots = open_executor(None, 2)
    try:
        assert owned and slots == 2 == executor_slots(None, 2)
    finally:
        ex.shutdown()
    _check(sweep(damped_peak, POINTS, max_workers=1, progress=False))
