"""Trajectory libraries (invctl generate): grids, continuation against cold solves, executors, failures,
resuming after an interruption, files, bad input."""
import json
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pytest

import problems.manipulator as scene
from invctl.cli import main
from invctl.errors import LibraryError, OutputPathError, ParameterError
from invctl.inversion import Inverse, invert
from invctl.studies.library import Library, generate, parse_grid, reference_arguments, resolve_axes

def _plan():
    from invctl.inversion import plan_inversion

    m = scene.build()
    return plan_inversion(m, scene.reference(m), q_guess=scene.initial_configuration(m))


#: the automatic setup of the scene's default transition: the selection every point of a library shares
PLAN = _plan()

GRID = ["rf[0]=0.88:0.92:2", "rf[1]=-0.92:-0.88:2"]


@pytest.fixture(scope="module")
def lib():
    return generate("manipulator", GRID, executor="serial", N=60, verify="all", progress=False)


def test_parse_grid_and_axes():
    assert parse_grid("m3=0.4:0.6:3")[1].tolist() == pytest.approx([0.4, 0.5, 0.6])
    assert parse_grid("tf=1,1.5")[1].tolist() == [1.0, 1.5]
    for bad, msg in (("m3", "expected NAME="), ("m3=1:2", "three fields"), ("m3=1:2:x", "not an integer"),
                     ("m3=1:2:1", "COUNT"), ("m3=__import__('os')", "not a number"), ("m3=1,1", "repeated"),
                     ("m3=nan", "finite")):
        with pytest.raises(ParameterError, match=msg):
            parse_grid(bad)
    sc = scene.SCENE
    assert reference_arguments(sc) == {"t0": 0.0, "tf": 1.0, "r0": (1.6, -0.6), "rf": (0.9, -0.9)}
    axes = resolve_axes(sc, ["m3=0.4:0.6:3", "rf[1]=-0.9,-0.8", "ref:tf=1,2"])
    assert [(a.name, a.kind, a.key, a.index) for a in axes] == [("m3", "param", "m3", None),
                                                                 ("rf[1]", "reference", "rf", 1),
                                                                 ("tf", "reference", "tf", None)]
    for bad, msg in (("m4=1,2", "grid-able: .*rf\\[i\\]"), ("rf=1,2", "grid one component"),
                     ("rf[2]=1,2", "has 2 components"), ("tf[0]=1,2", "not a sequence")):
        with pytest.raises(ParameterError, match=msg):
            resolve_axes(sc, [bad])
    with pytest.raises(ParameterError, match="given twice"):
        resolve_axes(sc, ["tf=1,2", "tf=3,4"])


def test_library_points_equal_cold_inversions(lib):
    # every point, continued from a neighbour, is the solution of the same discretization that invert()
    # finds from its own quasi-static guess (both stop at max |g| < 1e-10: agreement ~1e-8 relative)
    assert lib.counts() == {"solved": 4, "inaccurate": 0, "failed": 0}
    model = scene.build()
    for i, pt in enumerate(lib.points):
        ref = scene.reference(model, rf=(pt["rf[0]"], pt["rf[1]"]))
        inv = lib.inverse(i)
        cold = invert(model, ref, T0=inv.T0, Tf=inv.Tf, mesh=inv.t_mesh, start=PLAN.start,
                      end=PLAN.end, backend="newton", q_guess=scene.initial_configuration(model))
        t = np.linspace(inv.T0, inv.Tf, 801)
        assert np.max(np.abs(inv.X(t) - cold.X(t))) < 1e-7 * np.max(np.abs(cold.X(t)))
    # the forward check (an independent simulation) of every point: HS N = 60 measured ~1e-5
    assert np.all(lib.stats["error"] < 1e-4)
    assert set(lib.stats["initial_guess"]) == {"continuation"}
    # every point started from the base (-1) or from a grid neighbour
    src = lib.stats["source"].astype(int)
    shape_idx = [np.unravel_index(i, lib.shape) for i in range(4)]
    for i, s in enumerate(src):
        assert s == -1 or sum(abs(a - b) for a, b in zip(shape_idx[i], shape_idx[s])) == 1


def test_library_over_parameters_and_durations_on_a_process_pool():
    # a scene parameter (m3) and the transition time (tf: the pre- and post-actuation spans are kept);
    # a process pool gives the serial results (the same Newton solutions, to ~1e-8)
    grid = {"m3": [0.45, 0.55], "tf": [0.9, 1.2]}
    with ProcessPoolExecutor(max_workers=2) as ex:
        par = generate("manipulator", grid, executor=ex, N=60, verify="none", progress=False)
    ser = generate("manipulator", grid, executor="serial", N=60, verify="none", progress=False)
    assert par.counts()["solved"] == ser.counts()["solved"] == 4
    for i, pt in enumerate(ser.points):
        a, b = par.inverse(i), ser.inverse(i)
        # the pre- and post-actuation spans of the default point's automatic setup (tf = 1) are kept
        assert a.tf == pytest.approx(pt["tf"]) and a.Tf - a.tf == pytest.approx(PLAN.Tf - 1.0)
        assert a.t0 - a.T0 == pytest.approx(-PLAN.T0)
        t = np.linspace(a.T0, a.Tf, 401)
        assert np.max(np.abs(a.u(t) - b.u(t))) < 1e-7 * np.max(np.abs(b.u(t)))
    # the point's model carries the grid value: m3 = 0.55 needs a different feedforward than m3 = 0.45
    t = np.linspace(0, 1, 201)
    assert not np.allclose(ser.inverse({"m3": 0.45, "tf": 0.9}).u(t), ser.inverse({"m3": 0.55, "tf": 0.9}).u(t))


def test_failed_points_are_reported_and_the_others_kept():
    # rf[1] = -1.05 lies outside the workspace |r_y| < L2/2 + L3 = 1: the scene's reference refuses it
    lib = generate("manipulator", {"rf[1]": [-0.9, -1.05, -0.85]}, executor="serial", N=60, verify="none",
                   progress=False)
    assert lib.status == ["solved", "failed", "solved"]
    f = lib.failures
    assert len(f) == 1 and f[0]["index"] == 1 and "outside the reachable workspace" in f[0]["message"]
    assert "#1 (rf[1]=-1.05): failed: ReferenceSignalError" in lib.table()
    with pytest.raises(LibraryError, match="has no trajectory"):
        lib.inverse(1)
    assert np.isnan(lib.peak_inputs()[1]).all() and np.isfinite(lib.peak_inputs()[[0, 2]]).all()


def test_interrupted_library_resumes_without_solving_points_again(tmp_path):
    out = tmp_path / "lib.npz"
    seen = []

    def stop_after_two(rec):
        seen.append(rec["index"])
        if len(seen) == 2:
            raise KeyboardInterrupt

    grid = {"rf[0]": [0.88, 0.9, 0.92]}
    with pytest.raises(KeyboardInterrupt):
        generate("manipulator", grid, executor="serial", N=60, verify="none", out=out, progress=False,
                 callback=stop_after_two)
    assert not out.exists() and len(list((tmp_path / "lib.npz.parts").glob("point_*.npz"))) == 2
    again = []
    lib = generate("manipulator", grid, executor="serial", N=60, verify="none", out=out, progress=False,
                   callback=lambda r: again.append(r["index"]))
    assert lib.info["resumed"] == 2 and lib.info["solved_now"] == 1 and again == sorted(set(range(3)) - set(seen))
    assert out.exists() and not (tmp_path / "lib.npz.parts").exists()
    full = generate("manipulator", grid, executor="serial", N=60, verify="none", progress=False)
    t = np.linspace(-1, 2, 301)
    for i in range(3):
        assert np.max(np.abs(lib.inverse(i).u(t) - full.inverse(i).u(t))) < 1e-7
    # a finished library: everything is read back; other settings are refused without force
    assert generate("manipulator", grid, executor="serial", N=60, verify="none", out=out,
                    progress=False).info["solved_now"] == 0
    with pytest.raises(OutputPathError, match="other settings"):
        generate("manipulator", {"rf[0]": [0.88, 0.9]}, executor="serial", N=60, out=out, progress=False)


def test_library_files_round_trip(lib, tmp_path):
    path = lib.save(tmp_path / "lib.npz")
    back = Library.load(path)
    assert back.status == lib.status and back.shape == lib.shape
    assert np.array_equal(back.X_mesh, lib.X_mesh) and back.points == lib.points
    # a folder: one Inverse file per point (loadable alone) and library.json
    d = tmp_path / "libdir"
    lib2 = generate("manipulator", {"tf": [0.9, 1.1]}, executor="serial", N=60, verify="none", out=d,
                    progress=False)
    inv = Inverse.load(d / "point_00001.npz")
    t = np.linspace(inv.T0, inv.Tf, 101)
    assert np.max(np.abs(inv.u(t) - lib2.inverse(1).u(t))) < 1e-12 and inv.meta["scene"] == "manipulator"
    assert Library.load(d).counts()["solved"] == 2


def test_generate_command_line(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    rc = main(["generate", "manipulator", "--grid", "rf[0]=0.88:0.9:2", "--N", "60", "--workers", "1",
               "--verify", "none", "--out", "lib.npz", "--quiet", "--json"])
    out = capsys.readouterr().out
    data = json.loads(out.strip().splitlines()[-1])
    assert rc == 0 and data["counts"]["solved"] == 2 and (tmp_path / "lib.npz").exists()
    rc = main(["generate", "manipulator", "--grid", "m3=1+1", "--json"])
    data = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert rc == 2 and data["error"] == "ParameterError" and "not a number" in data["message"]
    rc = main(["generate", "manipulator", "--json"])
    data = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert rc == 2 and "--grid" in data["message"]


@pytest.mark.slow
def test_library_on_a_dask_cluster():
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        lib = generate("manipulator", {"rf[0]": [0.88, 0.92]}, executor=client, N=60, verify="none",
                       progress=False)
    assert lib.counts()["solved"] == 2


def test_ipopt_backend_agrees_with_newton():
    # backend="ipopt": every point through invert() (warm-started, the mesh carried to the point's
    # transition): the same discrete solutions as the Newton continuation (both to ~1e-10 residual)
    grid = {"tf": [0.9, 1.1]}
    a = generate("manipulator", grid, executor="serial", N=60, backend="ipopt", verify="none", progress=False)
    b = generate("manipulator", grid, executor="serial", N=60, verify="none", progress=False)
    t = np.linspace(-1, 2.1, 401)
    for i in range(2):
        assert np.max(np.abs(a.inverse(i).u(t) - b.inverse(i).u(t))) < 1e-7


def test_force_starts_over(tmp_path):
    out = tmp_path / "lib.npz"
    generate("manipulator", {"tf": [0.9, 1.1]}, executor="serial", N=60, verify="none", out=out, progress=False)
    lib = generate("manipulator", {"tf": [0.8, 1.0]}, executor="serial", N=60, verify="none", out=out, force=True,
                   progress=False)
    assert lib.info["resumed"] == 0 and Library.load(out).points == [{"tf": 0.8}, {"tf": 1.0}]


def test_compiled_and_virtual_machine_newton_give_the_same_library(lib):
    # the module fixture compiles when a C compiler exists; the virtual machine evaluates the same
    # expressions (round-off apart): both Newton runs stop at max |g| < 1e-10, so u_ff agrees to ~1e-8
    from invctl.inversion.compiled import compiler

    vm = generate("manipulator", GRID, executor="serial", N=60, verify="none", progress=False, compiled=False)
    assert vm.info["compiled"] == "no" and vm.info["compile_s"] == 0.0
    assert lib.info["compiled"] == ("yes" if compiler() is not None else "no")
    t = np.linspace(lib.info["base"]["T0"], lib.info["base"]["Tf"], 301)
    for i in range(len(lib.points)):
        u_c, u_vm = lib.inverse(i).u(t), vm.inverse(i).u(t)
        assert np.max(np.abs(u_c - u_vm)) <= 1e-7 * max(1.0, np.max(np.abs(u_vm)))
