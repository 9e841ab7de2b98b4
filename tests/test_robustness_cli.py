"""Issue 13: no traceback, no silent wrong answer, no lost work -- one test (at least) per row of the issue.

Rows, in the issue's order: scene files (syntax errors, wrong declarations, same file names,
shadowing), output paths checked before any work, loaders (truncated, foreign, inconsistent, NaN),
Ctrl-C during studies / refinements / IPOPT / closed loops / pipelines (a real SIGINT to a child
process, the partial result saved and checked), memory estimates, wall-time limits, repeated solves
with progress, clearances (sign, floor, penetration against the clearance), plant overrides,
scene-parameter checks, ``--out`` naming, ``--json`` on usage errors.
"""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from invctl.cli import main
from invctl.errors import (InversionFailed, ParameterError, ResultFileError,
                           RunInterrupted, WallTimeLimitError)
from invctl.scenes import available_scenes, load_scene
from invctl.studies import commands, contact, workflow

ROOT = Path(__file__).resolve().parents[1]


def run_cli(capsys, *argv):
    """``(exit code, last JSON line, stderr)`` of ``invctl argv --json`` run in this process."""
    rc = main([*argv, "--json"])
    cap = capsys.readouterr()
    lines = cap.out.strip().splitlines()
    return rc, json.loads(lines[-1]), cap.err


# ------------------------------------------------------------ scene files
def test_scene_file_syntax_error_names_file_and_line(tmp_path, capsys):
    f = tmp_path / "bad.py"
    f.write_text("import invctl\nSCENE = (\n")
    rc, d, err = run_cli(capsys, "analyze", str(f))
    assert rc == 2 and d["error"] == "SceneError"
    assert f"{f}:2" in d["message"] and "syntax error" in d["message"] and "Traceback" not in err


@pytest.mark.parametrize("body, expect", [
    ("SCENE = Scene('s', lambda **k: 42, params={'a': 1.0}, tracking=Tracking(reference=lambda m: None))",
     "build() returned int; a tracking scene must return an invctl.model.Model"),
    ("SCENE = Scene('s', lambda **k: 42, params={'a': 1.0}, tracking=Tracking(reference=3))",
     "tracking.reference must be a function"),
    ("SCENE = Scene('s', lambda **k: 42, params={'a': float('nan')})", "finite numbers"),
    ("SCENE = Scene('s', params={'a': 1.0})", "missing 1 required positional argument: 'build'"),
    ("x = 1", "a scene file must define SCENE"),
    ("SCENE = 3", "SCENE must be an invctl.Scene"),
    ("import no_such_module_xyz", "No module named 'no_such_module_xyz'"),
])
def test_scene_file_declarations_are_scene_errors(tmp_path, capsys, body, expect):
    f = tmp_path / "scene.py"
    f.write_text("from invctl.scenes import Scene, Tracking\n" + body + "\n")
    rc, d, err = run_cli(capsys, "analyze", str(f))
    assert rc == 2 and d["error"] == "SceneError", d
    assert expect in d["message"] and "Traceback" not in err
    if "Scene(" in body:  # errors raised while the file runs say where
        assert f"{f.resolve()}:2" in d["message"] or f"{f}:2" in d["message"]


def test_same_file_name_in_two_folders_are_two_scenes(tmp_path):
    for folder, mc in (("a", 2.0), ("b", 3.0)):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "scene.py").write_text(textwrap.dedent(f"""
            import dataclasses
            from invctl_scenes.cartpole import SCENE as S
            SCENE = dataclasses.replace(S, name="s{folder}", params={{**S.params, "mc": {mc}}})
            """))
    a, b = load_scene(tmp_path / "a" / "scene.py"), load_scene(tmp_path / "b" / "scene.py")
    assert (a.name, a.params["mc"], b.name, b.params["mc"]) == ("sa", 2.0, "sb", 3.0)
    assert load_scene(tmp_path / "a" / "scene.py").params["mc"] == 2.0  # loading b did not replace a


def test_local_folder_named_like_a_shipped_scene_does_not_shadow_it(tmp_path):
    (tmp_path / "manipulator").mkdir()
    (tmp_path / "manipulator" / "__init__.py").write_text("raise RuntimeError('the local folder was imported')\n")
    (tmp_path / "manipulator.py").write_text("raise RuntimeError('the local file was imported')\n")
    (tmp_path / "invctl_scenes").mkdir()  # `python -m invctl.cli` puts the working directory first on sys.path
    (tmp_path / "invctl_scenes" / "__init__.py").write_text("")
    (tmp_path / "invctl_scenes" / "manipulator.py").write_text("raise RuntimeError('the local package was imported')\n")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    p = subprocess.run([sys.executable, "-m", "invctl.cli", "analyze", "manipulator", "--samples", "4", "--json"],
                       cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
    d = json.loads(p.stdout.strip().splitlines()[-1])
    assert d["scene"] == "manipulator" and d["params"]["L1"] == 0.5


def test_a_path_to_a_folder_is_not_a_scene(tmp_path, capsys):
    rc, d, _ = run_cli(capsys, "analyze", str(tmp_path))
    assert rc == 2 and d["error"] == "SceneError" and "is a folder" in d["message"]


# ----------------------------------------------------------- output paths
def test_output_path_is_checked_before_any_computation(tmp_path, capsys, monkeypatch):
    from invctl.studies import tracking_report

    def fail(*a, **k):
        raise AssertionError("the inversion ran although the output path is unusable")

    monkeypatch.setattr(tracking_report, "invert", fail)
    rc, d, _ = run_cli(capsys, "invert", "manipulator", "--out", str(tmp_path / "no" / "dir" / "x.npz"))
    assert rc == 2 and d["error"] == "OutputPathError" and "does not exist" in d["message"]
    (tmp_path / "x.npz").write_text("old")
    rc, d, _ = run_cli(capsys, "invert", "manipulator", "--out", str(tmp_path / "x.npz"))
    assert rc == 2 and d["error"] == "OutputPathError" and "--force" in d["message"]
    rc, d, _ = run_cli(capsys, "invert", "manipulator", "--out", str(tmp_path / ("n" * 300)))
    assert rc == 2 and d["error"] == "OutputPathError" and "longer than" in d["message"]
    rc, d, _ = run_cli(capsys, "pipeline", "cartpole", "--out-dir", str(tmp_path / "x.npz"))
    assert rc == 2 and d["error"] == "OutputPathError" and "is a file" in d["message"]


def test_out_without_suffix_reports_the_file_written_and_force_replaces(tmp_path, capsys):
    target = tmp_path / "traj"
    rc, d, _ = run_cli(capsys, "invert", "cartpole", "--quiet", "--N", "60", "--out", str(target))
    assert rc == 0 and d["out"] == str(target) + ".npz" and Path(d["out"]).is_file()
    before = Path(d["out"]).stat().st_mtime_ns
    rc, d, _ = run_cli(capsys, "invert", "cartpole", "--quiet", "--N", "60", "--out", str(target))
    assert rc == 2 and d["error"] == "OutputPathError" and Path(str(target) + ".npz").stat().st_mtime_ns == before
    time.sleep(0.01)
    rc, d, _ = run_cli(capsys, "invert", "cartpole", "--quiet", "--N", "60", "--out", str(target), "--force")
    assert rc == 0 and Path(d["out"]).stat().st_mtime_ns > before


def test_output_formats_are_what_the_name_says(tmp_path, capsys):
    rc, d, _ = run_cli(capsys, "simulate", "bouncing_ball", "--out", str(tmp_path / "b.csv"))
    assert rc == 2 and d["error"] == "OutputPathError" and ".npz only" in d["message"]
    rc, d, _ = run_cli(capsys, "simulate", "stiff_wall", "--out", str(tmp_path / "w.csv"))
    assert rc == 0 and d["out"] == str(tmp_path / "w.csv")
    table = np.loadtxt(tmp_path / "w.csv", delimiter=",", skiprows=1)
    assert table.shape[0] > 100 and np.all(np.diff(table[:, 0]) >= 0)  # one row per sample (events twice)
    assert not (tmp_path / "w.csv.npz").exists()


def test_unwritable_folders_are_found_before_any_work(capsys, tmp_path):
    for folder in ("/proc/invctl-test", "/proc"):
        rc, d, _ = run_cli(capsys, "pipeline", "bouncing_ball", "--out-dir", folder)
        assert rc == 2 and d["error"] == "OutputPathError", d
    rc, d, _ = run_cli(capsys, "invert", "cartpole", "--out", "/proc/x.npz")
    assert rc == 2 and d["error"] == "OutputPathError" and "not writable" in d["message"]
    rc, d, _ = run_cli(capsys, "pipeline", "cartpole", "--set", "nope=1", "--out-dir", str(tmp_path / "new"))
    assert rc == 2 and not (tmp_path / "new").exists()  # a rejected command leaves no folder behind


# ---------------------------------------------------------------- loaders
@pytest.fixture(scope="module")
def saved_inverse(tmp_path_factory):
    path = tmp_path_factory.mktemp("inv") / "inv.npz"
    assert main(["invert", "cartpole", "--N", "60", "--quiet", "--out", str(path)]) == 0
    return path


def _rewrite(src, dst, *, meta=None, arrays=None):
    with np.load(src) as z:
        d = dict(z)
    m = json.loads(str(d["__invctl__"]))
    if meta:
        meta(m)
    if arrays:
        arrays(d)
    d["__invctl__"] = np.asarray(json.dumps(m))
    np.savez(dst, **d)
    return dst


@pytest.mark.parametrize("name, corrupt, expect", [
    ("truncated", lambda p, q: q.write_bytes(p.read_bytes()[: p.stat().st_size // 2]), "not an .npz result file"),
    ("text", lambda p, q: q.write_text("root:x:0:0\n"), "not an .npz result file"),
    ("foreign", lambda p, q: np.savez(q, a=np.arange(3)), "not an invctl result file"),
    ("n7", lambda p, q: _rewrite(p, q, meta=lambda m: m["info"]["sizes"].update(n=7)), "do not match"),
    ("nan", lambda p, q: _rewrite(p, q, arrays=lambda d: d["X_mesh"].__setitem__((0, 1), np.nan)), "non-finite"),
    ("newer", lambda p, q: _rewrite(p, q, meta=lambda m: m.update(version=99)), "newer than"),
    ("older", lambda p, q: _rewrite(p, q, meta=lambda m: m.update(version=1)), "older than"),
    ("kind", lambda p, q: _rewrite(p, q, meta=lambda m: m.update(kind="SwitchedSimulation")), "holds a Switched"),
    ("version_text", lambda p, q: _rewrite(p, q, meta=lambda m: m.update(version="2")), "malformed"),
    ("sizes_type", lambda p, q: _rewrite(p, q, meta=lambda m: m["info"].update(sizes=5)), "malformed Inverse"),
    ("reversed", lambda p, q: _rewrite(p, q, arrays=lambda d: d.update(t_mesh=d["t_mesh"][::-1].copy())),
     "not increasing"),
])
def test_inverse_load_rejects_bad_files(saved_inverse, tmp_path, capsys, name, corrupt, expect):
    from invctl.inversion import Inverse

    bad = tmp_path / f"{name}.npz"
    corrupt(saved_inverse, bad)
    with pytest.raises(ResultFileError, match=re.escape(expect)):
        Inverse.load(bad)
    rc, d, err = run_cli(capsys, "simulate", "cartpole", "--inverse", str(bad))  # the CLI's loader path
    assert rc == 2 and d["error"] == "ResultFileError" and "Traceback" not in err


def test_saved_inverse_must_belong_to_the_scene_and_its_parameters(saved_inverse, tmp_path, capsys):
    rc, d, _ = run_cli(capsys, "simulate", "two_link_arm", "--inverse", str(saved_inverse))
    assert rc == 2 and d["error"] == "ResultFileError" and "computed for scene 'cartpole'" in d["message"]
    rc, d, _ = run_cli(capsys, "simulate", "cartpole", "--set", "mp=0.3", "--inverse", str(saved_inverse))
    assert rc == 2 and d["error"] == "ResultFileError" and "parameters" in d["message"]
    rc, d, _ = run_cli(capsys, "simulate", "cartpole", "--controller", "C3", "--t-end", "0.5", "--quiet",
                       "--inverse", str(saved_inverse))
    assert rc == 0 and d["controller"] == "C3"


def test_saved_inverse_round_trip_is_exact(saved_inverse):
    """The loader rebuilds the same interpolant: the stored samples are reproduced to round-off."""
    from invctl.inversion import Inverse

    inv = Inverse.load(saved_inverse)
    with np.load(saved_inverse) as z:
        t, q = z["t"], z["q"]
    assert np.max(np.abs(inv.q(t) - q)) < 1e-12  # same polynomial evaluated twice


def test_study_and_tradeoff_loaders_check_their_files(tmp_path):
    from invctl.studies.tracking import TrackingStudy
    from invctl.studies.tradeoff import TradeoffResult

    with pytest.raises(ResultFileError, match="no such file"):
        TrackingStudy.load(tmp_path)
    (tmp_path / "study.json").write_text('{"runs": ["C1"], "info"')
    with pytest.raises(ResultFileError, match="not a readable study summary"):
        TrackingStudy.load(tmp_path)
    (tmp_path / "study.json").write_text('{"runs": ["C1"], "info": {}}')
    with pytest.raises(ResultFileError, match="run_C1.npz: no such file"):
        TrackingStudy.load(tmp_path)
    for text, expect in [('{"knob": "h", "rows": [', "not a readable JSON"), ("[1, 2]", "not a trade-off table"),
                         ('{"knob": "h", "rows": [{"value": 1, "error": "x", "time_s": 1}], "reference": "r"}',
                          "'error' = 'x' is not a number")]:
        (tmp_path / "t.json").write_text(text)
        with pytest.raises(ResultFileError, match=re.escape(expect)):
            TradeoffResult.from_json(tmp_path / "t.json")
    ok = TradeoffResult("h", [{"value": 1e-3, "error": 0.1, "time_s": 0.2}], "ref", partial="interrupted")
    ok.to_json(tmp_path / "ok.json")
    back = TradeoffResult.from_json(tmp_path / "ok.json")
    assert back.rows == ok.rows and back.partial == "interrupted"


# --------------------------------------------------------- interruptions
def _child(args, *, code=None, cwd, env_extra=None):
    env = {**os.environ, "PYTHONPATH": str(ROOT), **(env_extra or {})}
    cmd = [sys.executable, "-c", code, *args] if code else [sys.executable, "-m", "invctl.cli", *args]
    return subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _interrupt_when(p, pattern, delay=0.0, timeout=300):
    """Send SIGINT to ``p`` once a stderr line matches ``pattern``; returns (rc, stdout, stderr)."""
    lines, t0 = [], time.monotonic()
    for line in p.stderr:
        lines.append(line)
        if re.search(pattern, line):
            time.sleep(delay)
            p.send_signal(signal.SIGINT)
            break
        assert time.monotonic() - t0 < timeout, "the child never reached the point to interrupt"
    else:
        raise AssertionError(f"the child ended before {pattern!r}: {''.join(lines)[-2000:]}")
    out, rest = p.communicate(timeout=timeout)
    return p.returncode, out, "".join(lines) + rest


def _last_json(out):
    return json.loads(out.strip().splitlines()[-1])


def test_sigint_during_study_keeps_the_rows_so_far(tmp_path):
    from invctl.studies.tradeoff import TradeoffResult

    p = _child(["study", "tradeoff", "bouncing_ball", "--out-dir", "st", "--json"], cwd=tmp_path,
               env_extra={"INVCTL_SMOKE": "1"})
    rc, out, err = _interrupt_when(p, r"\(1/3\)")
    assert rc == 130, err[-2000:]
    d = _last_json(out)
    assert d["error"] == "RunInterrupted" and "Traceback" not in err
    res = TradeoffResult.from_json(tmp_path / "st" / "tradeoff_bouncing_ball.partial.json")
    assert 1 <= len(res.rows) < 3 and "interrupted" in res.partial
    assert str(Path("st") / "tradeoff_bouncing_ball.partial.csv") in d["partial"]
    assert "PARTIAL" in (tmp_path / "st" / "INTERRUPTED.txt").read_text()
    # the saved row is the complete run of that setting: its error equals a fresh computation's
    from invctl.studies.tradeoff_specs import spec_for

    scene = load_scene("bouncing_ball")
    spec = spec_for(scene, {}, dict(scene.settings), smoke=True)
    row = res.rows[0]
    assert abs(spec.run(row["value"])["error"] - row["error"]) <= 1e-12 * max(1.0, row["error"])  # deterministic


def test_sigint_during_mesh_refinement_keeps_the_last_accepted_mesh(tmp_path):
    from invctl.inversion import Inverse, forward_check
    from invctl.studies.tracking import tracking_model

    p = _child(["invert", "cartpole", "--tol", "1e-13", "--out", "x.npz", "--json"], cwd=tmp_path)
    rc, out, err = _interrupt_when(p, r"refinement 0:")
    assert rc == 130, err[-2000:]
    d = _last_json(out)
    assert d["error"] == "RunInterrupted" and d["partial"] == ["x.partial.npz"], d
    assert not (tmp_path / "x.npz").exists()  # the requested file is never a partial result
    inv = Inverse.load(tmp_path / "x.partial.npz")
    meshes = d["diagnostics"]["meshes"]
    assert inv.N == meshes[-1]["N"] and "interrupted" in inv.diagnostics["partial"]
    # an independent check of what was saved: the forward check of the loaded inverse reproduces the
    # error recorded for that mesh (same CVODES settings; 1e-3 relative covers the resampled y_ref)
    model, ref = tracking_model(load_scene("cartpole"))
    err_now = forward_check(model, inv, ref)["error"]
    assert abs(err_now - meshes[-1]["error"]) <= 1e-3 * meshes[-1]["error"]


_SLOW_IPOPT = textwrap.dedent("""
    import sys, time
    from invctl.inversion import backends
    ev = backends._Progress.eval
    def slow_eval(self, arg):  # each IPOPT iteration lasts 0.2 s: the signal lands inside IPOPT
        time.sleep(0.2)
        return ev(self, arg)
    backends._Progress.eval = slow_eval
    from invctl.cli import main
    sys.exit(main(sys.argv[1:]))
    """)


def test_sigint_inside_ipopt_is_an_interruption_not_a_failed_inversion(tmp_path):
    p = _child(["invert", "manipulator", "--scheme", "radau3", "--N", "4", "--json"], code=_SLOW_IPOPT,
               cwd=tmp_path)
    rc, out, err = _interrupt_when(p, r"iter +2 ")
    assert rc == 130, err[-3000:]
    d = _last_json(out)
    # CasADi 3.8 returns from IPOPT with its stop status ("interrupted during the IPOPT solve ..."), 3.7.0 with
    # a SystemError from the call ("interrupted (the solver stopped with SystemError ...)"): an interruption both
    assert d["error"] == "RunInterrupted" and d["message"].startswith("interrupted") and "InversionFailed" not in err
    assert "IPOPT" in d["message"] or "the solver stopped with" in d["message"], d["message"]


_SLOW_LOOP = textwrap.dedent("""
    import sys, time
    from invctl.simulate import closed_loop
    init, run = closed_loop.ClosedLoop.__init__, closed_loop.ClosedLoop.run
    def slow_init(self, *a, **k):  # 40 chunks of at least 0.1 s each: the signal lands inside the loop
        k.update(rtol=1e-13, atol=1e-15, chunks=40)
        init(self, *a, **k)
        integrate = self.integrator
        def slow_chunk(*a, **k):
            time.sleep(0.1)
            return integrate(*a, **k)
        self.integrator = slow_chunk
    def marked_run(self, *a, **k):
        print("SIMULATION STARTED", file=sys.stderr, flush=True)
        return run(self, *a, **k)
    closed_loop.ClosedLoop.__init__, closed_loop.ClosedLoop.run = slow_init, marked_run
    from invctl.cli import main
    sys.exit(main(sys.argv[1:]))
    """)


def test_sigint_during_a_closed_loop_keeps_the_simulated_prefix(tmp_path, monkeypatch):
    from invctl.simulate import closed_loop
    from invctl.simulate.closed_loop import ClosedLoopResult

    args = ["simulate", "manipulator", "--controller", "C3", "--t-end", "6", "--out", "run.npz", "--quiet", "--json"]
    p = _child(args, code=_SLOW_LOOP, cwd=tmp_path)
    rc, out, err = _interrupt_when(p, "SIMULATION STARTED", delay=0.3)
    assert rc == 130, err[-2000:]
    d = _last_json(out)
    assert d["error"] == "RunInterrupted" and d["partial"] == ["run.partial.npz"], d
    part = ClosedLoopResult.load(tmp_path / "run.partial.npz")
    assert part.status == "interrupted" and 0 <= part.t[-1] < 6.0 and part.meta["partial"]
    # the prefix is the run itself: the same loop uninterrupted passes through the same states
    init = closed_loop.ClosedLoop.__init__

    def slow_init(self, *a, **k):
        k.update(rtol=1e-13, atol=1e-15, chunks=40)
        init(self, *a, **k)

    monkeypatch.setattr(closed_loop.ClosedLoop, "__init__", slow_init)
    full = commands.simulate("manipulator", controller="C3", t_end=6.0, quiet=True, out=str(tmp_path / "full.npz"))
    ref = ClosedLoopResult.load(full.data["out"])
    k = part.t.size
    np.testing.assert_allclose(part.t, ref.t[:k], rtol=0, atol=1e-12)
    # identical chunks and tolerances: equal up to round-off of the same CVODES steps (rtol 1e-13)
    np.testing.assert_allclose(part.q, ref.q[:, :k], rtol=0, atol=1e-9)


def test_sigint_during_a_pipeline_keeps_the_complete_runs(tmp_path):
    from invctl.simulate.closed_loop import ClosedLoopResult
    from invctl.studies.tracking import TrackingStudy

    # tight tolerances (as above): C2 runs long enough for the signal to land inside it
    p = _child(["pipeline", "cartpole", "--out-dir", "out", "--no-animation", "--json"], code=_SLOW_LOOP,
               cwd=tmp_path)
    rc, out, err = _interrupt_when(p, r"simulating C2")
    assert rc == 130, err[-2000:]
    d = _last_json(out)
    assert d["error"] == "RunInterrupted" and "complete runs: C1" in d["message"]
    study = TrackingStudy.load(tmp_path / "out")
    assert list(study.runs) == ["C1"] and "interrupted" in study.info["partial"]
    c1 = ClosedLoopResult.load(tmp_path / "out" / "run_C1.npz")
    assert c1.status == "ok" and np.all(np.isfinite(c1.q))
    assert "PARTIAL" in (tmp_path / "out" / "INTERRUPTED.txt").read_text()


_MARKED_CONTACT = textwrap.dedent("""
    import sys
    from invctl.simulate import timestepping
    run = timestepping.MoreauJean.run
    def marked_run(self, *a, **k):
        print("CONTACT RUN STARTED", file=sys.stderr, flush=True)
        return run(self, *a, **k)
    timestepping.MoreauJean.run = marked_run
    loop = timestepping.MoreauJean._loop
    def marked_loop(self, *a, **k):  # the compiled loop is built (or compiled): stepping starts next
        out = loop(self, *a, **k)
        print("CONTACT LOOP READY", file=sys.stderr, flush=True)
        return out
    timestepping.MoreauJean._loop = marked_loop
    from invctl.cli import main
    sys.exit(main(sys.argv[1:]))
    """)


def test_sigint_during_a_contact_run_is_an_interruption(tmp_path):
    # 3e8 Moreau-Jean steps (tens of seconds in compiled code, which turns Ctrl-C into its own
    # error); recorded every 1000th step to stay inside the memory budget; signalled once stepping starts
    p = _child(["simulate", "bouncing_ball", "--set", "h=1e-8", "--record-every", "1000", "--json"],
               code=_MARKED_CONTACT, cwd=tmp_path)
    rc, out, err = _interrupt_when(p, "CONTACT LOOP READY", delay=0.2)
    assert rc == 130, err[-2000:]
    assert _last_json(out)["error"] == "RunInterrupted" and "internal error" not in err


def test_sigint_during_a_contact_run_keeps_the_simulated_prefix(tmp_path):
    from invctl.simulate.contact_record import ContactTrajectory

    # 3e8 steps, recorded decimated by default: the signal lands inside the compiled loop
    p = _child(["simulate", "bouncing_ball", "--set", "h=1e-7", "--set", "t_end=30", "--out", "b.npz", "--quiet",
                "--json"], code=_MARKED_CONTACT, cwd=tmp_path)
    # after the loop is built: a loaded machine may spend longer than any fixed delay compiling it
    rc, out, err = _interrupt_when(p, "CONTACT LOOP READY", delay=1.0)
    assert rc == 130, err[-2000:]
    d = _last_json(out)
    assert d["error"] == "RunInterrupted" and d["partial"] == ["b.partial.npz"], d
    part = ContactTrajectory.load(tmp_path / "b.partial.npz")
    assert part.status == "interrupted" and 0 < part.t[-1] < 30 and np.all(np.diff(part.t) > 0)
    assert "interrupted" in part.meta["partial"] and np.all(np.isfinite(part.q))
    # the prefix is the run itself: its impacts are those of the closed form t1 (1 + 2 e + 2 e^2 + ...), up to
    # the accumulation point t1 (1 + 2 e / (1 - e)) = 4.06 s (after it the ball rests: the time stepping goes on
    # with grazing impacts the closed form does not list); 0.05 s before it the impacts are 4 ms apart
    t1, e = np.sqrt(2 / 9.81), 0.8
    exact = t1 + 2 * t1 * np.r_[0.0, np.cumsum(e ** np.arange(1, 40))]
    t_rest = t1 * (1 + 2 * e / (1 - e)) - 0.05
    ti = part.impact_times
    k = np.count_nonzero(exact < min(part.t[-1], t_rest) - 1e-5)
    assert ti.size == k if part.t[-1] < t_rest else ti.size >= k
    np.testing.assert_allclose(ti[:k], exact[:k], rtol=0, atol=1e-5)
    assert np.all(ti <= part.t[-1])


_MARKED_SWITCHED = textwrap.dedent("""
    import sys
    from invctl.simulate import switched
    run = switched._Engine.run
    def marked_run(self, *a, **k):
        print("SWITCHED RUN STARTED", file=sys.stderr, flush=True)
        return run(self, *a, **k)
    switched._Engine.run = marked_run
    from invctl.cli import main
    sys.exit(main(sys.argv[1:]))
    """)


def test_sigint_during_a_switched_run_keeps_the_simulated_prefix(tmp_path):
    from invctl.simulate.switched import SwitchedSimulation
    from invctl.studies.switched import simulate_scenario

    p = _child(["simulate", "stiff_wall", "--set", "h_max=1e-6", "--t-end", "3", "--out", "run.npz", "--json"],
               code=_MARKED_SWITCHED, cwd=tmp_path)
    rc, out, err = _interrupt_when(p, "SWITCHED RUN STARTED", delay=1.0)
    assert rc == 130, err[-2000:]
    d = _last_json(out)
    assert d["error"] == "RunInterrupted" and d["partial"] == ["run.partial.npz"], d
    assert not (tmp_path / "run.npz").exists()
    part = SwitchedSimulation.load(tmp_path / "run.partial.npz")
    assert part.status == "interrupted" and 0 < part.t[-1] < 3 and np.all(np.diff(part.t) >= 0)
    assert part.t.size > 1000 and "interrupted" in part.meta["partial"]
    # the prefix is the exact solution: a run at the default sampling passes through the same states
    p_ = load_scene("stiff_wall").model({}).params
    t_cut = min(part.t[-1], 0.5)
    ref = simulate_scenario(p_, t_end=t_cut)
    inside = (ref.t < t_cut) & ~np.isin(ref.t, ref.event_t)  # away from the duplicated event instants
    np.testing.assert_allclose(part.sample(ref.t[inside])["x"], ref.x[inside], rtol=0, atol=1e-9)
    assert part.event_t.size == ref.event_t[ref.event_t <= part.t[-1]].size


def test_sigint_during_a_contact_pipeline_keeps_the_runs_and_the_prefix(tmp_path):
    from invctl.simulate.contact_record import ContactTrajectory

    # h = 2e-7: 1e7 steps per controller; the signal lands inside the second run (preload), after its loop
    # is built (a loaded machine may spend longer than any fixed delay compiling it)
    p = _child(["pipeline", "prismatic_clearance", "--set", "h=2e-7", "--no-animation", "--out-dir", "out", "--json"],
               code=_MARKED_CONTACT, cwd=tmp_path)
    lines, seen = [], 0
    for line in p.stderr:
        lines.append(line)
        seen += "CONTACT LOOP READY" in line
        if seen == 2:
            time.sleep(0.5)
            p.send_signal(signal.SIGINT)
            break
    else:
        raise AssertionError("".join(lines)[-2000:])
    out, err = p.communicate(timeout=300)
    assert p.returncode == 130, err[-2000:]
    d = _last_json(out)
    assert d["error"] == "RunInterrupted" and "complete runs: pd" in d["message"]
    assert {str(Path("out") / "run_pd.npz"), str(Path("out") / "run_preload.partial.npz")} <= set(d["partial"])
    pd_run = ContactTrajectory.load(tmp_path / "out" / "run_pd.npz")
    assert pd_run.status == "ok" and pd_run.t[-1] == pytest.approx(2.0)
    part = ContactTrajectory.load(tmp_path / "out" / "run_preload.partial.npz")
    assert part.status == "interrupted" and 0 < part.t[-1] < 2.0 and part.meta["controller"] == "preload"
    assert "PARTIAL" in (tmp_path / "out" / "INTERRUPTED.txt").read_text()


def test_sigint_during_an_event_driven_run_keeps_the_simulated_prefix():
    """A real SIGINT to this process during the event-driven reference (a Python loop around DOP853)."""
    import threading

    import invctl_scenes.bouncing_ball as bb
    from invctl.simulate.contact_record import ContactTrajectory
    from invctl.simulate.event_driven import simulate_event_driven

    model = bb.build(e=1.0)  # elastic: it bounces for ever, one impact every 2 t1
    timer = threading.Timer(1.0, os.kill, (os.getpid(), signal.SIGINT))
    timer.start()
    try:
        with pytest.raises(RunInterrupted) as exc:
            simulate_event_driven(model, [1.0], [0.0], 1e5, potential=bb.potential(model), max_events=10**7)
    finally:
        timer.cancel()
    part = exc.value.partial
    assert isinstance(part, ContactTrajectory) and part.status == "interrupted" and 0 < part.t[-1] < 1e5
    t1 = np.sqrt(2 / 9.81)
    ti = part.stats["impact_t"]
    assert ti.size >= 2 and ti[-1] <= part.t[-1]
    np.testing.assert_allclose(ti, t1 * (1 + 2 * np.arange(ti.size)), rtol=1e-8)
    assert part.q.shape == (1, part.t.size) and np.all(np.isfinite(part.q))


def test_sigint_during_sweeps_and_tradeoffs_in_process():
    """A real SIGINT to this process while a sweep / trade-off runs (the library entry points)."""
    from invctl.studies.sweep import sweep
    from invctl.studies.tradeoff import TradeoffSpec, run_tradeoff

    def point(x):
        if x == 3:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1.0)  # the handler raises KeyboardInterrupt here
        return {"y": x * x}

    with pytest.raises(RunInterrupted) as exc:
        sweep(point, [{"x": k} for k in range(6)], executor="serial", progress=False)
    part = exc.value.partial
    assert [v["y"] for v in part.values[:3]] == [0, 1, 4] and part.values[3:] == [None] * 3
    assert part.errors[3:] == ["not run: interrupted"] * 3 and "3 of 6" in part.meta["partial"]
    spec = TradeoffSpec("k", [1, 2, 3, 4], lambda k: point(k) and {"error": 1.0 / k, "time_s": 1.0}, "exact")
    with pytest.raises(RunInterrupted) as exc:
        run_tradeoff(spec, progress=False)
    assert [r["value"] for r in exc.value.partial.rows] == [1, 2] and "2 of 4" in exc.value.partial.partial


def test_cli_exit_codes_for_interrupts_bugs_and_memory(capsys, monkeypatch):
    from invctl.studies import commands as cmds

    for exc, rc_expected, name in [(KeyboardInterrupt(), 130, "RunInterrupted"),
                                   (RuntimeError("boom"), 3, "InternalError"),
                                   (MemoryError(), 2, "ResourceLimitError")]:
        def raise_(*a, _e=exc, **k):
            raise _e

        monkeypatch.setattr(cmds, "run_command", raise_)
        rc, d, err = run_cli(capsys, "analyze", "cartpole")
        assert rc == rc_expected and d["error"] == name and "Traceback" not in err
    def bug(*a, **k):
        raise RuntimeError("boom")

    monkeypatch.setattr(cmds, "run_command", bug)
    monkeypatch.setenv("INVCTL_DEBUG", "1")
    with pytest.raises(RuntimeError, match="boom"):
        main(["analyze", "cartpole"])


def test_usage_errors_are_json_with_json(capsys):
    for argv in (["invert", "manipulator", "--bogus"], ["invert"], ["nocommand", "x"],
                 ["invert", "manipulator", "--N"]):
        rc, d, _ = run_cli(capsys, *argv)
        assert rc == 2 and d["error"] == "UsageError", argv
    rc, d, _ = run_cli(capsys, "invert", "manipulator", "--N", "abc")
    assert rc == 2 and d["error"] == "OptionError" and "--N 'abc'" in d["message"]


# ------------------------------------------------------ repeated solves
def test_repeated_solves_with_progress_behave_like_the_first(capsys):
    from invctl.inversion import invert
    from invctl.studies.tracking import tracking_model

    model, ref = tracking_model(load_scene("cartpole"))
    a = invert(model, ref, N=60, progress=True)
    b = invert(model, ref, N=60, progress=True)
    c = invert(model, ref, N=60, progress=False)
    err = capsys.readouterr().err
    assert err.count("iter   0") == 2  # each progress solve reports its own iterations
    for inv in (a, b, c):
        assert inv.diagnostics["status"] == "Solve_Succeeded"
    # the same equations from the same guess: the same solution (cached solver or not)
    assert np.max(np.abs(a.X_mesh - b.X_mesh)) < 1e-12 and np.max(np.abs(a.X_mesh - c.X_mesh)) < 1e-12


def test_radau3_n4_fallback_runs_the_same_with_progress_on_and_off(capsys):
    from invctl.studies.tracking import invert_tracking, tracking_model

    scene = load_scene("manipulator")
    model, ref = tracking_model(scene)
    outcomes = []
    for progress in (True, False, True):  # what `invctl invert manipulator --scheme radau3 --N 4 [--quiet]` runs
        with pytest.raises(InversionFailed) as exc:
            invert_tracking(scene, model, ref, N=4, scheme="radau3", progress=progress)
        d = exc.value.diagnostics
        steps = (d.get("continuation") or {}).get("steps") or []
        outcomes.append((d["status"], d["iterations"], str(exc.value),
                         [(s["status"], s["iterations"]) for s in steps]))
    capsys.readouterr()
    assert outcomes[0] == outcomes[1] == outcomes[2]
    assert outcomes[0][1] > 0 and "User_Requested_Stop" not in str(outcomes)


def test_wall_time_limit_is_reported_as_such():
    from invctl.inversion import invert
    from invctl.studies.tracking import tracking_model

    model, ref = tracking_model(load_scene("manipulator"))
    with pytest.raises(WallTimeLimitError, match=r"stopped at the wall-time limit of 1e-06 s after \d+ iterations"
                                                 r".*raise max_wall_time") as exc:
        invert(model, ref, N=300, T0=-1.0, Tf=2.0, max_wall_time=1e-6)
    assert "finer mesh" not in str(exc.value) and exc.value.diagnostics["continuation"] is None
    assert isinstance(exc.value, InversionFailed) and exc.value.partial is not None


# ------------------------------------------------------------- resources
@pytest.mark.parametrize("argv", [["simulate", "bouncing_ball", "--set", "t_end=1e6", "--record-every", "1"],
                                  ["simulate", "bouncing_ball", "--set", "h=1e-9", "--record-every", "1"]])
def test_large_contact_runs_are_refused_with_the_recording_that_fits(capsys, argv):
    """The Moreau-Jean run estimates its record before it starts (here every step, --record-every 1; the
    default is decimated) and names the decimation, the event record and the horizon that fit; the
    decimated run then goes through."""
    rc, d, _ = run_cli(capsys, *argv)
    assert rc == 2 and d["error"] == "ResourceLimitError"
    assert "--record-every" in d["message"] and "--record events" in d["message"] and "--t-end" in d["message"]
    diag = d["diagnostics"]
    assert diag["estimate_bytes"] > diag["budget_bytes"]
    k = diag["fits"]["record_every"]
    assert k > 1 and diag["estimate_bytes"] / k <= diag["budget_bytes"]


@pytest.mark.parametrize("argv, fits", [
    (["simulate", "manipulator", "--t-end", "1e6"], r"use --t-end [0-9.e+]+ or less"),
    (["pipeline", "stiff_wall", "--t-end", "1e7"], r"--set h_max="),
    (["study", "tradeoff", "stiff_wall", "--set", "t_end=1e5"], r"--set t_end="),
])
def test_large_runs_are_refused_before_they_start(capsys, tmp_path, argv, fits):
    argv = [*argv, "--out-dir", str(tmp_path / "o")] if argv[0] in ("pipeline", "study") else argv
    rc, d, _ = run_cli(capsys, *argv)
    assert rc == 2 and d["error"] == "ResourceLimitError" and re.search(fits, d["message"]), d
    diag = d["diagnostics"]
    assert diag["bytes_needed"] > diag["bytes_usable"]
    # the horizon the message offers fits: the memory scales with the horizon
    t_end = float(re.search(r"t_end = ([0-9.e+]+) s", d["message"]).group(1))
    assert diag["bytes_needed"] * diag["t_end_that_fits"] / t_end <= diag["bytes_usable"] * (1 + 1e-9)


def _peak_rss_of(argv, cwd) -> float:
    """Peak resident memory (bytes) of ``invctl argv`` in a fresh process."""
    # VmHWM of this process image (ru_maxrss would carry the parent's size across fork and exec)
    code = ("import re, sys\nfrom invctl.cli import main\nrc = main(sys.argv[1:])\n"
            "hwm = re.search(r'VmHWM:\\s+(\\d+)', open('/proc/self/status').read()).group(1)\n"
            "print('RSS', hwm, rc)")
    p = subprocess.run([sys.executable, "-c", code, *argv], cwd=cwd, capture_output=True, text=True, timeout=600,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    rss, rc = p.stdout.strip().splitlines()[-1].split()[1:]
    assert rc == "0", p.stderr[-2000:]
    return float(rss) * 1024  # Linux: KiB


def test_memory_estimate_of_inversions_against_a_measurement(tmp_path, capsys, monkeypatch):
    """The inversion estimate bounds the measured growth of the peak RSS with the mesh (cartpole,
    Hermite-Simpson, N = 200 -> 6000) from above: measured 112 MB against 174 MB estimated; the
    factor 6 allows for the compiled transcription (used when it is in the disk cache), which
    needs less."""
    small = _peak_rss_of(["invert", "cartpole", "--N", "200", "--quiet"], tmp_path)
    large = _peak_rss_of(["invert", "cartpole", "--N", "6000", "--quiet"], tmp_path)
    model = load_scene("cartpole").model({})
    nx = 2 * model.n + model.ell + model.p + model.m
    a, b = workflow._INVERSION_BYTES
    estimate = 5800 * a * (2 * nx) ** b
    assert large - small <= estimate <= 6 * (large - small), (large - small, estimate)
    monkeypatch.setenv("INVCTL_MAX_MEMORY", str(estimate / 2))
    rc, d, _ = run_cli(capsys, "invert", "cartpole", "--N", "6000")
    assert rc == 2 and d["error"] == "ResourceLimitError" and re.search(r"use --N \d+ or less", d["message"])
    assert 2000 < d["diagnostics"]["N_that_fits"] < 6000


def test_memory_limit_can_be_lowered_by_environment(capsys, monkeypatch):
    monkeypatch.setenv("INVCTL_MAX_MEMORY", "1e6")
    rc, d, _ = run_cli(capsys, "simulate", "bouncing_ball", "--set", "h=1e-5")
    assert rc == 2 and d["error"] == "ResourceLimitError" and d["diagnostics"]["budget_bytes"] == 1e6
    monkeypatch.setenv("INVCTL_MAX_MEMORY", "lots")
    rc, d, _ = run_cli(capsys, "simulate", "bouncing_ball", "--set", "h=1e-5")
    assert rc == 2 and d["error"] == "ParameterError" and "INVCTL_MAX_MEMORY" in d["message"]
    monkeypatch.setenv("INVCTL_MAX_MEMORY", "1e6")
    rc, d, _ = run_cli(capsys, "simulate", "manipulator", "--controller", "C2", "--t-end", "1000")
    assert rc == 2 and d["error"] == "ResourceLimitError" and d["diagnostics"]["bytes_usable"] == 1e6


# ------------------------------------------------------------- clearances
def test_clearance_sign_and_floor(capsys):
    rc, d, _ = run_cli(capsys, "simulate", "slider_crank_clearance", "--set", "c=-1e-3")
    assert rc == 2 and d["error"] == "ParameterError" and "c must be positive" in d["message"]
    rc, d, _ = run_cli(capsys, "simulate", "slider_crank_clearance", "--set", "c=1e-12")
    assert rc == 2 and d["error"] == "ParameterError" and "double precision" in d["message"]
    rc, d, _ = run_cli(capsys, "simulate", "prismatic_clearance", "--set", "L=0.10000000001")
    assert rc == 2 and d["error"] == "ParameterError" and "double precision" in d["message"]


@pytest.mark.parametrize("scene, setting, scale", [
    ("slider_crank_clearance", "c=1e-9", 1e-9),            # declared: the bearing's clearance c
    ("prismatic_clearance", "L=0.100000001", 1e-9),        # declared: the room L - 2 l
])
def test_penetration_far_beyond_the_clearance_fails_with_the_numbers(capsys, tmp_path, scene, setting, scale):
    out = tmp_path / "run.npz"
    rc, d, _ = run_cli(capsys, "simulate", scene, "--set", setting, "--out", str(out))
    assert rc == 2 and d["error"] == "SimulationFailed" and "times the clearance scale" in d["message"]
    (run,) = d["diagnostics"]["runs"].values()
    # the scale is the clearance in closed form (the sum of the two gaps of a centred start), the
    # ratio the reported penetration over it
    assert abs(run["clearance_scale"] - scale) <= 1e-6 * scale
    assert abs(run["gap_violation_ratio"] - run["max_gap_violation"] / scale) <= 1e-6 * run["gap_violation_ratio"]
    assert run["gap_violation_ratio"] > 1e3 and str(out) in d["message"] and out.is_file()


def test_penetration_of_a_fraction_of_the_clearance_warns_with_the_numbers(capsys):
    rc, d, _ = run_cli(capsys, "simulate", "slider_crank_clearance", "--controller", "pdplus")
    assert rc == 0 and len(d["warnings"]) == 1
    ratio = d["max_gap_violation"] / d["clearance_scale"]
    assert contact.GAP_WARN < ratio <= 1 and f"{ratio:.3g} times" in d["warnings"][0]
    assert abs(d["clearance_scale"] - 1e-3) <= 1e-12  # the declared clearance, default c = 1e-3
    rc, d, _ = run_cli(capsys, "simulate", "slider_crank_clearance", "--controller", "pdplus",
                       "--set", "projection=1")
    assert rc == 0 and "warnings" not in d and d["max_gap_violation"] < 1e-12  # projected: no penetration


# ---------------------------------------------------- parameters of scenes
def test_plant_overrides_are_checked_before_any_work(capsys, monkeypatch):
    from invctl.studies import switched_report

    def fail(*a, **k):
        raise AssertionError("the pipeline ran although --plant-set cannot apply")

    monkeypatch.setattr(switched_report, "Session", fail)
    rc, d, _ = run_cli(capsys, "pipeline", "compliant_wrist", "--plant-set", "kt=2")
    assert rc == 2 and d["error"] == "OptionError" and "not applicable" in d["message"]
    rc, d, _ = run_cli(capsys, "simulate", "cartpole", "--plant-set", "nope=2")
    assert rc == 2 and d["error"] == "ParameterError" and "unknown plant parameter" in d["message"]


def test_plant_overrides_go_through_the_scene_checks(capsys):
    for scene, item, expect in [("manipulator", "I2=-0.01", "I2 must be positive"),
                                ("manipulator", "m3=-1", "m3 must be positive"),
                                ("manipulator", "d=1.6", "loop cannot close"),
                                ("prismatic_clearance", "m2=-1", "m2 must be positive"),
                                ("prismatic_clearance", "e=2", "restitution")]:
        rc, d, _ = run_cli(capsys, "simulate", scene, "--plant-set", item)
        assert rc == 2 and d["error"] == "ParameterError" and expect in d["message"], (scene, item, d)


#: for every shipped scene: values its checks must reject (name=value, words of the message)
REJECTED = {
    "manipulator": [("L1=-0.5", "positive"), ("D=-1", "damper"), ("d=3", "loop cannot close"), ("L3=0.05", "reach")],
    "cartpole": [("l=0", "positive"), ("D=-0.1", "damping")],
    "two_link_arm": [("L2=-1", "positive"), ("c2=-1", "spring")],
    "knife_edge": [("m=0", "positive"), ("Dth=-1", "damping")],
    "bouncing_ball": [("e=1.5", "restitution"), ("h=0", "positive"), ("projection=0.5", "integer"),
                      ("theta=2", "theta")],
    "prismatic_clearance": [("actuators=1.5", "integer"), ("actuators=3", "1 or 2"), ("L=0.09", "clearance"),
                            ("beta=-1", "positive"), ("Kp=-1", "gain"), ("activation_tol=-1", "activation_tol")],
    "slider_crank_clearance": [("c=-1e-3", "positive"), ("Lr=0.05", "longer than the crank"), ("cs=-1", "friction"),
                               ("projection=2", "switch")],
    "gear_backlash": [("c4=0", "+1 or -1"), ("alpha1=-0.01", "positive"), ("alpha1=1e-12,alpha2=1e-12", "backlash"),
                      ("Kv=-1", "gain")],
    "stiff_wall": [("b=-1", ">= 0"), ("t_c=0.4", "t_c < t_b"), ("x_ret=0.01", "free space"), ("be_hat=-1", ">= 0"),
                   ("glue_at_crossing=0.5", "switch")],
    "compliant_wrist": [("kt=0", "positive"), ("switch_on_tip=2", "switch"), ("be=-1", ">= 0")],
    "crane": [("mL=0", "positive"), ("k=-1", "positive")],
    "sixbar": [("l1=0", "positive"), ("structure=1.5", "integer")],
    "sixbar_pd": [("l1=-1", "positive"), ("h=0", "positive")],
    "sixbar_tracking": [("l2=0", "positive"), ("h=-1", "positive")],
    "chain14": [("rho=0", "positive"), ("c=-1", "positive")],
    "backlash_pivot": [("Jm=0", "positive"), ("alpha=-1", "positive")],
    "fourbar_backlash": [("a=0", "positive"), ("h=0", "positive")],
    "slider_crank_prismatic_play": [("actuators=4", "1, 2 or 3"), ("corners=3", "corners must be"),
                                    ("c=0.015", "small against"), ("Lr=0.1", "longer than the crank")],
    "fourbar_clearance": [("actuators=3", "1 or 2"), ("b=0.35", "Grashof"), ("cl=0.02", "small against"),
                          ("e=2", "restitution")],
    "mass_chain": [("n=2.5", "integer"), ("k=-1", ">= 0"), ("k=0,c=0", "decouples")],
    "passive_arm": [("L1=0", "positive"), ("c2=-1", ">= 0")],
    "flexible_arm": [("n=0", "positive"), ("d=-1", ">= 0"), ("w=0", "colocated")],
    "acrobot": [("m_link1=0", "positive"), ("d_joint1=-1", ">= 0")],
    "ur5_elastic": [("m_forearm_link=-1", "positive"), ("k_elbow_joint=-1", ">= 0"), ("g=-9.81", ">= 0")],
}


def test_every_shipped_scene_has_its_rejections_listed():
    assert set(REJECTED) == set(available_scenes())


@pytest.mark.parametrize("scene, item, words", [(s, i, w) for s, items in REJECTED.items() for i, w in items])
def test_scene_parameter_checks(scene, item, words):
    sc = load_scene(scene)
    values = {k: float(v) for k, v in (a.split("=") for a in item.split(","))}
    with pytest.raises(ParameterError, match=re.escape(words)):
        sc.split(values)


def test_defaults_of_every_shipped_scene_pass_their_checks():
    for name in available_scenes():
        load_scene(name).split({})


def test_non_finite_and_malformed_values_are_rejected(capsys):
    for item in ("m3=nan", "m3=inf", "m3=-inf", "m3=1e400", "m3=abc", "m3", "=1", "m3=__import__('os')"):
        rc, d, _ = run_cli(capsys, "analyze", "manipulator", "--set", item)
        assert rc == 2 and d["error"] == "ParameterError", (item, d)


def test_a_swallowed_ctrl_c_is_raised_at_the_next_checkpoint():
    """CasADi's argument conversion swallows a KeyboardInterrupt (and reports a NotImplementedError);
    inside the command line's context the Ctrl-C is remembered and honoured."""
    import os
    import signal as sig

    from invctl.errors import INTERRUPT_LIKE, check_interrupt, is_interrupt, remember_sigint

    def swallowing_library():
        try:
            os.kill(os.getpid(), sig.SIGINT)
            time.sleep(0.5)  # the handler runs here
        except KeyboardInterrupt:
            pass
        return NotImplementedError("Wrong number or type of arguments")

    check_interrupt()  # nothing pending outside the context
    err = swallowing_library()
    assert not is_interrupt(err)  # without the context a NotImplementedError is what it says
    with remember_sigint():
        err = swallowing_library()
        assert isinstance(err, INTERRUPT_LIKE) and is_interrupt(err)
        with pytest.raises(KeyboardInterrupt):
            check_interrupt()
        check_interrupt()  # raised once
        assert not is_interrupt(err)
    try:  # Python's wrapping of a callback's KeyboardInterrupt
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as ki:
            raise SystemError("returned a result with an exception set") from ki
    except SystemError as se:
        assert is_interrupt(se)
    assert sig.getsignal(sig.SIGINT) is sig.default_int_handler


def test_after_a_ctrl_c_a_solver_failure_is_the_interruption_and_a_bug_stays_a_bug():
    """A compiled solver turns Ctrl-C into its own error (CasADi: RuntimeError): that is the interruption; an
    error no solver raises for a Ctrl-C (a KeyError: a bug) is not hidden behind it."""
    import signal as sig

    def run(error):
        try:
            sig.raise_signal(sig.SIGINT)
        except KeyboardInterrupt:
            raise error from None

    with pytest.raises(RunInterrupted, match="the solver stopped with RuntimeError"):
        commands._interruptible(lambda: run(RuntimeError("Error in Function::call")))
    with pytest.raises(KeyError, match="bug"):
        commands._interruptible(lambda: run(KeyError("bug")))
