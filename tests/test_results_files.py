"""Result files written before the save/load path was merged (committed in ``tests/data/``) still load, as
the same objects; the merged writer writes the same entries (a switched run's meta merged into the info like
the other kinds')."""
import json
from pathlib import Path

import numpy as np
import pytest

import invctl
from invctl.simulate.closed_loop import ClosedLoopResult
from invctl.simulate.contact_record import ContactTrajectory
from invctl.simulate.switched import SwitchedSimulation

DATA = Path(__file__).parent / "data"
META = {"scene": "demo", "params": {"a": 1.5}}


def small_results() -> dict:
    """One small hand-made result of each kind (non-square shapes, every field set)."""
    K = 5
    t = np.linspace(0.0, 0.4, K)
    r = np.arange(3 * K, dtype=float).reshape(3, K) / 7.0
    closed = ClosedLoopResult(
        t=t, q=r[:2], v=-r[:2], z=np.zeros((0, K)), u=r[:1] + 1, u_ff=r[:1], u_fb=np.ones((1, K)), y=r[1:2],
        y_ref=r[2:3], ratios=r[:2] / 10, e_bar=r[:1] / 3, phi_bar=np.full(K, 2.0), drift_g=np.full(K, 1e-9),
        drift_Gv=np.full(K, 2e-9), cumulative_errors={"output": 0.25, "tip": 0.5}, wall_s=1.25,
        signals={"tip": r[:2] * 2}, signals_ref={"tip": r[:2] * 3}, controller="C1", status="left_region",
        message="left the model's region", ratio_names=["y1 level 0", "bar"], q_names=["x", "th"], y_names=["x"],
        u_names=["F"], stats={"left_region": {"t": 0.3, "coordinates": "th", "region": "|th| < 1"}, "n": 3})
    contact = ContactTrajectory(
        t=t, q=r[:2], v=r[1:3], P=np.abs(r[:2, :-1]), active=r[:2, :-1] > 0.5, gaps=r[:2] - 0.5, energy=r[0],
        V=r[1], h=0.1, names={"q": ["x", "y"], "gaps": ["g1", "g2"]},
        stats={"Un": -r[:2], "u": r[:1], "steps": 4, "backend": "vm", "dV_max": 0.0, "partial": True,
               "step_index": np.arange(K)}, impact_vel_tol=1e-7, status="failed", message="LCP failed")
    switched = SwitchedSimulation(
        t=t, x=r[0], v=r[1], xt=np.zeros(0), vt=np.zeros(0), xd=r[2], xd_dot=-r[2], Fd=r[0] + 1, Fd_desired=r[0],
        Fe=r[1] * 2, Fc=r[2] * 2, wall=np.array([0, 1, 1, 0, 0], bool), ctrl=np.array([0, 0, 1, 1, 0], bool),
        intended=np.array([0, 1, 1, 1, 0], bool), event_t=np.array([0.1, 0.3]), event_surface=np.array([0, 0]),
        event_kind=np.array([1, -1]), peak_force=3.5, contact_phases=1, bounces=2, force_rms_error=0.125,
        wall_time=0.01, label="demo run", status="ok", message="", stats={"modes": 3})
    return {"closed_loop": closed, "contact": contact, "switched": switched}


def small_inverse():
    """A hand-made Legendre-2 inverse (n = 1, l = 1, p = 0, m = 1; three uneven intervals) with a reference."""
    from invctl.inversion import Inverse

    N, nx = 3, 4
    X = np.cos(np.arange(nx * (N + 1), dtype=float)).reshape(nx, N + 1)
    return Inverse("legendre2", np.array([0.0, 0.1, 0.25, 0.4]), X, np.zeros_like(X),
                   np.sin(np.arange(nx * 2 * N, dtype=float)).reshape(nx, 2 * N), {"n": 1, "l": 1, "p": 0, "m": 1},
                   0.1, 0.3, names={"q": ["x"], "u": ["F"]},
                   diagnostics={"success": True, "status": "Solve_Succeeded", "iterations": 7, "residual": 1e-9},
                   y_ref_fn=lambda t: np.atleast_2d(np.sin(np.atleast_1d(t))))


def _same(a, b):
    assert type(a) is type(b)
    for k, x in vars(a).items():
        y = vars(b)[k]
        if isinstance(x, np.ndarray):
            assert x.shape == y.shape and x.dtype.kind == np.asarray(y).dtype.kind, k
            np.testing.assert_array_equal(x, y, err_msg=k)
        elif isinstance(x, dict):
            assert set(x) == set(y), k
            for kk in x:
                np.testing.assert_array_equal(x[kk], y[kk], err_msg=f"{k}[{kk!r}]")
        else:
            assert x == y, k


@pytest.mark.parametrize("name", ["closed_loop", "contact", "switched"])
def test_files_of_the_earlier_writer_load_as_the_same_object(name):
    expected = small_results()[name]
    expected.meta = dict(META)
    _same(invctl.load(DATA / f"{name}.npz"), expected)


@pytest.mark.parametrize("name", ["closed_loop", "contact", "switched"])
def test_writer_keeps_the_file_layout(name, tmp_path):
    """Same entries (names, shapes, dtypes) and the same JSON info as the committed file, and a round trip."""
    res = small_results()[name]
    path = res.to_npz(tmp_path / name, meta=META)
    with np.load(path) as new, np.load(DATA / f"{name}.npz") as old:
        assert sorted(new.files) == sorted(old.files)
        for k in old.files:
            if k == "__invctl__":
                was = json.loads(str(old[k]))
                was["info"].update(was["info"].pop("meta", {}))  # switched runs nested their meta (now merged)
                assert json.loads(str(new[k])) == was
            else:
                assert new[k].shape == old[k].shape and new[k].dtype == old[k].dtype, k
                np.testing.assert_array_equal(new[k], old[k], err_msg=k)
    res.meta = dict(META)
    _same(invctl.load(path), res)


def test_contact_statistics_that_are_not_arrays_are_kept(tmp_path):
    """Statistics that are neither arrays nor numbers (an event-driven run's event list) go into the JSON info."""
    res = small_results()["contact"]
    res.stats["events"] = [(0.1, "impact", 0, -1.0, 0.5)]
    back = invctl.load(res.to_npz(tmp_path / "c"))
    assert back.stats["events"] == [[0.1, "impact", 0, -1.0, 0.5]]


@pytest.mark.parametrize("name", ["closed_loop", "contact", "switched"])
def test_a_file_without_a_declared_array_is_refused(name, tmp_path):
    from invctl.errors import ResultFileError

    path = small_results()[name].to_npz(tmp_path / name)
    with np.load(path) as z:
        d = dict(z)
    del d["t"]
    np.savez(tmp_path / "cut.npz", **d)
    with pytest.raises(ResultFileError, match=r"incomplete \w+ file \(missing \['t'\]\)"):
        invctl.load(tmp_path / "cut.npz")


def _same_inverse(a, b, t):
    """Same collocation data and info, the same reference at the stored times ``t``."""
    assert type(a) is type(b)
    for k in ("scheme", "t_mesh", "X_mesh", "dX_mesh", "X_col", "sizes", "t0", "tf", "names", "diagnostics", "meta"):
        x, y = getattr(a, k), getattr(b, k)
        if isinstance(x, np.ndarray):
            assert x.shape == y.shape, k
            np.testing.assert_array_equal(x, y, err_msg=k)
        else:
            assert x == y, k
    np.testing.assert_allclose(a.y_ref(t), b.y_ref(t), rtol=0, atol=1e-15)


def test_inverse_file_of_the_earlier_writer_loads_as_the_same_object():
    expected = small_inverse()
    expected.meta = dict(META)
    back = invctl.load(DATA / "inverse.npz")
    with np.load(DATA / "inverse.npz") as z:
        _same_inverse(back, expected, z["t"])


def test_inverse_writer_keeps_the_file_layout(tmp_path):
    """The same entries (the samples on a grid of step ``dt`` and the collocation data) and the same info."""
    inv = small_inverse()
    path = inv.to_npz(tmp_path / "inverse", 0.05, meta=META)
    with np.load(path) as new, np.load(DATA / "inverse.npz") as old:
        assert sorted(new.files) == sorted(old.files)
        for k in old.files:
            if k == "__invctl__":
                assert json.loads(str(new[k])) == json.loads(str(old[k]))
            else:
                assert new[k].shape == old[k].shape and new[k].dtype == old[k].dtype, k
                np.testing.assert_array_equal(new[k], old[k], err_msg=k)
        t = old["t"]
    inv.meta = dict(META)
    _same_inverse(invctl.load(path), inv, t)


def test_a_contact_file_without_statistics_is_refused(tmp_path):
    """The info's ``stats`` is written even when every statistic is an array, and a file without it is refused."""
    from invctl.errors import ResultFileError

    res = small_results()["contact"]
    res.stats = {"Un": res.stats["Un"]}
    path = res.to_npz(tmp_path / "c")
    with np.load(path) as z:
        d = dict(z)
    tag = json.loads(str(d["__invctl__"]))
    assert tag["info"]["stats"] == {}
    del tag["info"]["stats"]
    d["__invctl__"] = np.asarray(json.dumps(tag))
    np.savez(tmp_path / "cut.npz", **d)
    with pytest.raises(ResultFileError, match=r"incomplete ContactTrajectory file \(missing \['stats'\]\)"):
        invctl.load(tmp_path / "cut.npz")


def test_closed_loop_csv_columns(tmp_path):
    """One column per row of every signal, named after the result's names (non-identifier characters as ``_``)."""
    res = small_results()["closed_loop"]
    res.to_csv(tmp_path / "r.csv")
    with open(tmp_path / "r.csv") as fh:
        header = fh.readline().strip().split(",")
    assert header == ["t", "x", "th", "dx", "dth", "u1", "u_ff1", "u_fb1", "y1", "y_ref1", "tip1", "tip2", "tip_ref1",
                      "tip_ref2", "ratio_y1_level_0", "ratio_bar"]
    table = np.loadtxt(tmp_path / "r.csv", delimiter=",", skiprows=1)
    expected = np.vstack([res.t, res.q, res.v, res.u, res.u_ff, res.u_fb, res.y, res.y_ref, res.signals["tip"],
                          res.signals_ref["tip"], res.ratios]).T
    np.testing.assert_allclose(table, expected, rtol=1e-15)
