"""Trajectory libraries (invctl generate): grids, continuation against cold solves, executors, failures,
resuming after an interruption, files, bad input."""
import json
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pytest

import invctl_scenes.manipulator as scene
from invctl.cli import main
from invctl.errors import LibraryError, OutputPathError, ParameterError
from invctl.inversion import Inverse, invert
from invctl.studies.library import Library, generate, reference_arguments, resolve_axes
from invctl.studies.library_data import parse_grid

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
    from invctl.studies import library

    lib = generate("manipulator", {"rf[1]": [-0.9, -1.05, -0.85]}, executor="serial", N=60, verify="none",
                   progress=False)
    assert library._STATE == {}  # the run's held solvers (and model) are not kept by the module after it
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


# ------------------------------------------------------------ one library per output, sizes, Ctrl-C
import os  # noqa: E402
import re  # noqa: E402
import signal  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from invctl.errors import ResourceLimitError, RunInterrupted  # noqa: E402
from invctl.studies.library_data import LibraryStore  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def _cli(args, cwd, code=None):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, "-c", code, *args] if code else [sys.executable, "-m", "invctl.cli", *args]
    return subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _ends_at_its_xf(lib):
    """Every solved point's cart ends at the xf of its grid value (the trajectory belongs to the point)."""
    for i, pt in enumerate(lib.points):
        if lib.status[i] != "failed":
            inv = lib.inverse(i)
            assert inv.q(inv.Tf)[0] == pytest.approx(pt["xf"], abs=1e-6), (i, pt)


def test_concurrent_runs_with_other_grids_into_one_folder_never_mix(tmp_path):
    # two runs started together into one folder: one writes the library, the other is refused (while
    # the first runs: LibraryError; after it: the folder's other settings, OutputPathError); never a mix
    grids = (["--grid", "xf=0.4:0.6:4"], ["--grid", "xf=0.45:0.65:4"])
    procs = [_cli(["generate", "cartpole", *g, "--N", "60", "--workers", "1", "--verify", "none", "--out", "lib",
                   "--quiet", "--json"], tmp_path) for g in grids]
    res = [(p.wait(timeout=600), *p.communicate()) for p in procs]
    rcs = sorted(r[0] for r in res)
    assert rcs == [0, 2], [r[2][-1500:] for r in res]
    win = next(i for i, r in enumerate(res) if r[0] == 0)
    lost = json.loads(res[1 - win][1].strip().splitlines()[-1])
    assert lost["error"] in ("LibraryError", "OutputPathError") and "lib" in lost["message"]
    assert "another --out" in lost["message"] or "another invctl generate" in lost["message"]
    lib = Library.load(tmp_path / "lib")
    lo = (0.4, 0.45)[win]
    assert [p["xf"] for p in lib.points] == pytest.approx(np.linspace(lo, lo + 0.2, 4).tolist())
    _ends_at_its_xf(lib)


_HOLD = ("import sys, time\nfrom invctl.studies.library_data import LibraryStore\n"
         "s = LibraryStore(sys.argv[1], 'someoneelse'); s.acquire(); print('locked', flush=True); time.sleep(600)\n")


def test_a_running_owner_blocks_other_runs_and_a_killed_one_does_not(tmp_path):
    d = tmp_path / "lib"
    holder = _cli([str(d)], tmp_path, code=_HOLD)
    try:
        assert holder.stdout.readline().strip() == "locked"
        for grid in ({"xf": [0.4, 0.5]}, {"xf": [0.3, 0.5]}):
            with pytest.raises(LibraryError, match=rf"--out {re.escape(str(d))}: another invctl generate \(pid "
                                                   rf"{holder.pid} .*someoneelse.*choose another --out"):
                generate("cartpole", grid, executor="serial", N=60, verify="none", out=d, progress=False)
    finally:
        holder.kill()  # SIGKILL: no clean-up runs; the system drops its lock
        holder.wait()
    lib = generate("cartpole", {"xf": [0.4, 0.5]}, executor="serial", N=60, verify="none", out=d, progress=False)
    assert lib.counts()["solved"] == 2
    again = generate("cartpole", {"xf": [0.4, 0.5]}, executor="serial", N=60, verify="none", out=d, progress=False)
    assert again.info["resumed"] == 2 and again.info["solved_now"] == 0  # a resume of the same settings
    # the lock is held only while a run writes: this process can take it again at once
    s = LibraryStore(d, "k")
    s.acquire()
    s.release()


def test_loading_refuses_a_point_of_another_library(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    generate("cartpole", {"xf": [0.4, 0.6]}, executor="serial", N=60, verify="none", out=a, progress=False)
    generate("cartpole", {"xf": [0.45, 0.65]}, executor="serial", N=60, verify="none", out=b, progress=False)
    _ends_at_its_xf(Library.load(a))
    (a / "point_00001.npz").write_bytes((b / "point_00001.npz").read_bytes())  # what a mixed folder held
    with pytest.raises(LibraryError, match=r"point_00001.npz: point 1 .*belongs to another library"):
        Library.load(a)


def test_sizes_are_refused_before_any_work(capsys, monkeypatch):
    cases = [(["generate", "cartpole", "--grid", "xf=0.3:0.5:10000000"], r"--grid.*use --grid axes with \d+ points"),
             (["generate", "cartpole", "--grid", "xf=0.3:0.5:4000", "--grid", "x0=0:0.1:4000"], r"4000 x 4000"),
             (["generate", "cartpole", "--grid", "xf=0.3:0.5:3", "--N", "100000000"], r"generate --N 100000000.*"
                                                                                        r"use --N \d+ or less"),
             (["analyze", "cartpole", "--samples", "1000000000"], r"--samples 1000000000.*use --samples \d+ or less"),
             (["invert", "cartpole", "--N", "10000000"], r"invert --N 10000000 .*would take about")]
    for argv, pattern in cases:
        t = time.perf_counter()
        rc = main([*argv, "--json"])
        wall = time.perf_counter() - t
        d = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        assert rc == 2 and d["error"] == "ResourceLimitError" and re.search(pattern, d["message"]), d
        assert wall < 10.0, (argv, wall)  # refused at once (measured 0.1-0.4 s; generous for a loaded machine)
    # the time budget alone: 50000 samples take ~3 s (estimate), more than a budget of one second
    monkeypatch.setenv("INVCTL_MAX_TIME", "1")
    rc = main(["analyze", "cartpole", "--samples", "50000", "--json"])
    d = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    fit = d["diagnostics"]["count_that_fits"]
    assert rc == 2 and d["diagnostics"]["seconds_budget"] == 1.0 and f"use --samples {fit} or less" in d["message"]
    assert fit * d["diagnostics"]["seconds_estimated"] / 50000 <= 1.0 < (fit + 1) * d["diagnostics"]["seconds_estimated"] / 50000
    with pytest.raises(ResourceLimitError, match="--grid"):  # the Python call checks too
        generate("cartpole", ["xf=0.3:0.5:100000"], executor="serial", progress=False)
    monkeypatch.setenv("INVCTL_MAX_TIME", "soon")
    rc = main(["analyze", "cartpole", "--samples", "5000", "--json"])
    d = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert rc == 2 and d["error"] == "ParameterError" and "INVCTL_MAX_TIME" in d["message"]


def test_ordinary_sizes_pass_the_checks(monkeypatch):
    from invctl.scenes import bind_scene, load_scene
    from invctl.studies.library import check_library_size
    from invctl.studies.workflow import check_inversion, workflow

    sc = load_scene("cartpole")
    workflow(sc)._check_samples(bind_scene(sc, "analyze"), 100000)  # ~6 s
    check_inversion(bind_scene(sc, "invert"), {"N": 20000})  # measured 12 s
    check_library_size(sc, {}, [100, 100], 200, None, 1)  # 10^4 points: 100 s, 350 MB at the least


def test_ctrl_c_during_generate_lists_the_saved_points(tmp_path):
    args = ["generate", "cartpole", "--grid", "xf=0.3:0.7:40", "--N", "60", "--workers", "1", "--verify", "none",
            "--out", "lib", "--json"]
    p = _cli(args, tmp_path)
    lines = []
    for line in p.stderr:  # progress lines per 10 %: interrupt after the first ones
        lines.append(line)
        if re.search(r"\] ([4-9]|[1-3]\d)/40", line):
            p.send_signal(signal.SIGINT)
            break
    out, rest = p.communicate(timeout=300)
    assert p.returncode == 130, "".join(lines) + rest
    d = json.loads(out.strip().splitlines()[-1])
    kept = d["diagnostics"]["kept"]
    assert d["error"] == "RunInterrupted" and 4 <= len(kept) < 40 and "run the same command again" in d["message"]
    assert d["partial"] == [k["file"] for k in kept] and all((tmp_path / f).is_file() for f in d["partial"])
    from invctl.io import read_meta

    for k in kept:
        inv = Inverse.load(tmp_path / k["file"])
        assert read_meta(tmp_path / k["file"])["info"]["library"]["index"] == k["index"]
        assert inv.q(inv.Tf)[0] == pytest.approx(k["values"]["xf"], abs=1e-6)
    q = _cli([a for a in args if a != "--json"] + ["--quiet", "--json"], tmp_path)
    out, err = q.communicate(timeout=600)
    again = json.loads(out.strip().splitlines()[-1])
    assert q.returncode == 0 and again["info"]["resumed"] == len(kept) and again["counts"]["solved"] == 40, err


def test_interruption_in_python_carries_what_was_kept(tmp_path):
    def stop(rec):
        if rec["index"] != 1:
            raise KeyboardInterrupt

    with pytest.raises(RunInterrupted) as ei:
        generate("cartpole", {"xf": [0.4, 0.5, 0.6]}, executor="serial", N=60, verify="none", out=tmp_path / "l.npz",
                 progress=False, callback=stop)
    kept = ei.value.diagnostics["kept"]
    assert len(kept) >= 1 and ei.value.saved == [k["file"] for k in kept]
    assert all(Path(f).is_file() and ".parts" in f for f in ei.value.saved)


def test_an_output_whose_lock_cannot_be_created_is_refused_before_work(tmp_path):
    out = tmp_path / ("b" * 250 + ".npz")  # a valid name; its lock ".<name>.lock" is too long for the file system
    with pytest.raises(OutputPathError, match=r"cannot create .*\.lock .*choose another --out"):
        generate("cartpole", {"xf": [0.4, 0.5]}, executor="serial", N=60, out=out, progress=False)
