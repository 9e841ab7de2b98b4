"""Fuzzing the command line: random invocations of every shipped scene and command.

Each case is an ``invctl`` command line run in this process through :func:`invctl.cli.main`
(with ``--json``): a random scene and command, random ``--set`` values (plausible, extreme, invalid,
NaN/inf, huge/tiny, malformed assignments), random option values (valid and not), random output
paths, corrupted result files (``--inverse``, ``invctl animate``) and randomly corrupted scene files.

The property: exit code 0 with one JSON object as the last line of output (strict JSON: no NaN,
no ``"nan"`` value), or exit code 2 with a JSON error object naming a specific error class of
:mod:`invctl.errors` (or the usage error of the argument parser) -- never a traceback, never an
internal error (exit 3), never a hang (per-case time limit, :data:`CASE_LIMIT_S`).

Profiles (environment ``INVCTL_FUZZ``):

* default (CI): :data:`CI_EXAMPLES` cases; ``pipeline`` and ``study`` only with option and value
  checks that end before any run (their runs take 10-60 s each; they share the checks of
  ``simulate``/``invert`` and run end to end in tests/test_pipelines.py and tests/test_tradeoffs.py);
  plausible values within a factor 2 of the defaults plus the extremes ``x 1e+-6``, ``x 1e+-12``,
  ``1e+-300`` (rejected, or tiny runs) -- factors like ``x 1e-3`` on a time step are legitimate
  runs of a minute and belong to the long profile.
* ``INVCTL_FUZZ_RANDOM=1``: the CI profile with fresh random cases (CI runs a fixed, derandomized set).
* ``INVCTL_FUZZ=long`` (by hand): ``INVCTL_FUZZ_EXAMPLES`` cases (default 2000) with every command
  run, the factors ``1e+-1 ... 1e+-4`` as well and a longer per-case limit.

The number of cases and their outcomes (by exit code and error class) are printed at the end.
"""
from __future__ import annotations

import contextlib
import io
import json
import math
import os
import signal
import string
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

import invctl.errors as errors  # noqa: E402
from invctl.cli import main  # noqa: E402
from invctl.scenes import available_scenes, load_scene  # noqa: E402
from invctl.studies.commands import options_of  # noqa: E402

LONG = os.environ.get("INVCTL_FUZZ") == "long"
CI_EXAMPLES = 400
EXAMPLES = int(os.environ.get("INVCTL_FUZZ_EXAMPLES", 2000 if LONG else CI_EXAMPLES))
#: per-case wall-time limit: the slowest legitimate CI case (a tracking simulate with a new design,
#: ~5 s alone, several times that on a 2-core machine shared with other jobs) times 12
CASE_LIMIT_S = 300.0 if LONG else 60.0
SCENES = available_scenes()
HEAVY = ("pipeline", "study")
#: every error class a user may see: the invctl hierarchy and the parser's usage error
SPECIFIC = {name for name in errors.__all__ if isinstance(getattr(errors, name), type)
            and issubclass(getattr(errors, name), errors.InvctlError)} | {"UsageError"}

OUTCOMES: Counter = Counter()
CASES = {"n": 0, "wall": 0.0, "slowest": []}


class CaseTimeout(BaseException):
    """A case ran past :data:`CASE_LIMIT_S` (BaseException: no ``except Exception`` swallows it)."""


def _alarm(signum, frame):
    raise CaseTimeout()


def _scene_info():
    out = {}
    for name in SCENES:
        s = load_scene(name)
        out[name] = (s.commands, {**s.params, **s.settings})
    return out


INFO = _scene_info()

# ------------------------------------------------------------------ values
INVALID_TEXT = ["", "abc", "1..2", "1e", "0x10", "1,5", "__import__('os').system('true')", "True", "None",
                "[1, 2]", "1/3", "1e400", "-1e400", "nan", "NaN", "inf", "-inf", "+inf", " ", "٣", "0b11",
                "1_000", "--1"]
EXTREME_FACTORS = [1e-300, 1e-12, 1e-6, 1e6, 1e12, 1e300]
LONG_FACTORS = [1e-4, 1e-3, 1e-2, 0.1, 10.0, 100.0, 1e3, 1e4]


def _fmt_number(x: float, style: int) -> str:
    return [repr(x), f"{x:.3e}", f"{x:g}", f"{x:.17g}"][style % 4]


@st.composite
def set_value(draw, default: float) -> str:
    kind = draw(st.sampled_from(["plausible"] * 5 + ["extreme", "sign", "zero", "invalid", "big_int"]))
    style = draw(st.integers(0, 3))
    base = default if default != 0 else 1.0
    if kind == "plausible":
        factor = 2.0 ** draw(st.floats(-1.0, 1.0, allow_nan=False))
        if LONG and draw(st.booleans()):
            factor = draw(st.sampled_from(LONG_FACTORS))
        if default in (0.0, 1.0, -1.0, 2.0) and float(default).is_integer():
            return _fmt_number(default, style) if draw(st.booleans()) else str(int(default))
        return _fmt_number(default * factor if default != 0 else factor - 1.0, style)
    if kind == "extreme":
        return _fmt_number(base * draw(st.sampled_from(EXTREME_FACTORS)), style)
    if kind == "sign":
        return _fmt_number(-base, style)
    if kind == "zero":
        return draw(st.sampled_from(["0", "0.0", "-0", "-0.0", "5e-324"]))
    if kind == "big_int":
        return str(draw(st.sampled_from([2, 3, 10**6, 10**400, -(10**400)])))
    return draw(st.sampled_from(INVALID_TEXT))


@st.composite
def assignment(draw, scene: str) -> str:
    names = sorted(INFO[scene][1])
    kind = draw(st.sampled_from(["known"] * 8 + ["unknown", "malformed"]))
    if kind == "malformed":
        return draw(st.sampled_from(["x", "=3", "==", "a==3", "a=3=4", "=", " = ", "m 1=2"]))
    if kind == "unknown" or not names:
        name = draw(st.sampled_from(["nope", "M1", "__class__", "t", "h_", "é"]))
        return f"{name}={draw(st.sampled_from(['1', '0.5', 'nan']))}"
    name = draw(st.sampled_from(names))
    return f"{name}={draw(set_value(float(INFO[scene][1][name])))}"


# ------------------------------------------------------------------ options
def _option_values(draw, name: str, scene: str, tmp: Path, case: int) -> list[str]:
    """argv pieces for one option (empty: option left out)."""
    flag = "--" + name.replace("_", "-")
    valid = draw(st.integers(0, 9)) < 7
    if name in ("force", "quiet", "no_animation", "animate"):
        return [flag]
    if name == "N":
        v = draw(st.integers(4, 60)) if valid else draw(st.sampled_from(["3", "0", "-5", "abc", "2.5", "1e9",
                                                                          "10**9", "nan"]))
        return [flag, str(v)]
    if name == "scheme":
        ok = ["hermite-simpson", "radau3", "legendre2", "radau1"]
        v = draw(st.sampled_from(ok)) if valid else draw(st.sampled_from(["radau0", "foo", "legendre99", "", "HS"]))
        return [flag, v]
    if name == "tol":
        v = draw(st.sampled_from(["1e-4", "1e-6"])) if valid else draw(st.sampled_from(
            ["0", "-1", "nan", "inf", "abc", "1e400"] + (["1e-300", "1e-12"] if LONG else [])))
        return [flag, v]
    if name == "backend":
        return [flag, draw(st.sampled_from(["ipopt", "newton"])) if valid else draw(st.sampled_from(["foo", "IPOPT"]))]
    if name == "dt":
        return [flag, draw(st.sampled_from(["0.01", "0.005"])) if valid else draw(st.sampled_from(
            ["0", "-1", "nan", "abc", "1e-300"]))]
    if name in ("rtol", "atol"):
        return [flag, draw(st.sampled_from(["1e-6", "1e-9"])) if valid else draw(st.sampled_from(
            ["0", "-1", "nan", "inf", "abc"]))]
    if name == "max_steps":
        return [flag, draw(st.sampled_from(["20000", "500"])) if valid else draw(st.sampled_from(
            ["0", "-1", "abc", "2.5"]))]
    if name == "controller":
        return [flag, draw(st.sampled_from(["C1", "C2", "C3", "C1-42", "c2", "pd", "pdplus", "preload", "switching",
                                            "juggling", "none", "foo", ""]))]
    if name == "plant_set":
        return ["--plant-set", draw(assignment(scene))]
    if name == "t_end":
        v = draw(st.sampled_from(["0.05", "0.2", "0.5"])) if valid else draw(st.sampled_from(
            ["0", "-1", "nan", "inf", "abc", "1e6", "1e300", "1e-300", "5e-324"]))
        return [flag, v]
    if name in ("out", "plot", "inverse", "out_dir"):
        return [flag, _path(draw, name, tmp, case, valid)]
    if name == "samples":
        bad = ["0", "-3", "abc", "1e9", "2.5"]
        return [flag, str(draw(st.integers(1, 24))) if valid else draw(st.sampled_from(bad))]
    if name == "job":
        return [flag, draw(st.sampled_from(["simulate", "impacts", "invert", "analyze", "foo"]))]
    if name == "preset":
        return [flag, draw(st.sampled_from(["paper", "foo", ""]))]
    if name == "record_every":
        return [flag, draw(st.sampled_from(["1", "10", "1000"])) if valid else draw(st.sampled_from(
            ["0", "-1", "abc", "2.5", "1e12"]))]
    if name == "record":
        return [flag, draw(st.sampled_from(["steps", "events"])) if valid else draw(st.sampled_from(["all", ""]))]
    if name == "max_wall_time":
        return [flag, draw(st.sampled_from(["30", "60"])) if valid else draw(st.sampled_from(["0", "-1", "nan", "abc"]))]
    if name == "bound":
        return [flag, draw(st.sampled_from(["u=1000", "pre=50", "u_rate=1e6"])) if valid else draw(st.sampled_from(
            ["u=abc", "u", "x=1", "q=1", "u=1:-1", "u=nan", "u=", "pre=-1", "q.nope=1", "u=1e400"]))]
    if name == "weight":
        return [flag, draw(st.sampled_from(["output=1", "slack=1e-2", "energy=0"])) if valid else draw(st.sampled_from(
            ["output=-1", "slack=nan", "foo=1", "output", "energy=abc", "output.nope=1"]))]
    if name in ("minimum_time", "no_compile", "no_continuation"):
        return [flag] if draw(st.integers(0, 3)) == 0 else []
    if name == "grid":
        numeric = sorted(k for k, v in INFO[scene][1].items() if float(v) > 0)
        if valid and numeric:
            key = draw(st.sampled_from(numeric))
            v = float(INFO[scene][1][key])
            return [flag, f"{key}={0.98 * v:.12g},{v:.12g}"]
        return [flag, draw(st.sampled_from(["m3", "=1", "nope=1,2", "x=1:2", "x=1:2:1", "x=__import__('os')",
                                            "x=nan,1", "rf[9]=1,2", ""]))]
    if name == "workers":  # one process: a pool per case would dominate the run time
        return [flag, "1" if valid else draw(st.sampled_from(["0", "-1", "abc", "2.5"]))]
    if name == "dask":  # would contact a scheduler: covered by tests/test_library.py
        return []
    if name == "verify":
        return [flag, draw(st.sampled_from(["all", "corners", "none"])) if valid else draw(st.sampled_from(
            ["some", "", "ALL"]))]
    if name == "energy":
        return [flag, draw(st.sampled_from(["0.1", "1"])) if valid else draw(st.sampled_from(["-1", "nan", "abc"]))]
    if name == "duration":
        return [flag, draw(st.sampled_from(["0.5:5", "1:3"])) if valid else draw(st.sampled_from(
            ["3:1", "0:1", "abc", "1", "-1:2", "1:inf"]))]
    raise AssertionError(f"the fuzzer does not know option {name!r}: add it")


def _path(draw, name: str, tmp: Path, case: int, valid: bool) -> str:
    if name == "inverse":
        return str(draw(st.sampled_from(_result_files(tmp))))
    if name == "out_dir":
        if valid:
            return str(tmp / f"dir{case}")
        return draw(st.sampled_from([str(tmp / "afile.txt"), "/proc/invctl-no", str(tmp / ("x" * 300)), ""]))
    suffix = {"out": [".npz", ".csv", "", ".npz"], "plot": [".png", ".pdf", ".svg"]}[name]
    if valid:
        return str(tmp / f"{name}{case}{draw(st.sampled_from(suffix))}")
    return draw(st.sampled_from([str(tmp / "no" / "such" / "dir" / "x.npz"), str(tmp), str(tmp / "afile.txt"),
                                 str(tmp / ("y" * 300 + ".npz")), str(tmp / "existing.npz"),
                                 str(tmp / "fig.txt")]))


_FILES: dict = {}


def _result_files(tmp: Path) -> list[Path]:
    """Corrupted, foreign and valid result files (made once per session)."""
    key = str(tmp)
    if key in _FILES:
        return _FILES[key]
    files = []
    good = tmp / "good_inverse.npz"
    assert main(["invert", "two_link_arm", "--quiet", "--out", str(good)]) == 0
    raw = good.read_bytes()
    for name, data in {"truncated.npz": raw[: len(raw) // 2], "empty.npz": b"", "text.npz": b"hello\n",
                       "header_only.npz": raw[:30]}.items():
        (tmp / name).write_bytes(data)
        files.append(tmp / name)
    np.savez(tmp / "foreign.npz", a=np.arange(3))
    files.append(tmp / "foreign.npz")
    with np.load(good) as z:
        d = dict(z)
    meta = json.loads(str(d["__invctl__"]))
    variants = {"n7": ("sizes", "n", 7), "version": ("version", None, 99), "nan": ("nan", None, None),
                "kind": ("kind", None, "SwitchedSimulation")}
    for label, (what, sub, val) in variants.items():
        dd, mm = dict(d), json.loads(json.dumps(meta))
        if what == "sizes":
            mm["info"]["sizes"][sub] = val
        elif what in ("version", "kind"):
            mm[what] = val
        else:
            dd["X_mesh"] = dd["X_mesh"].copy()
            dd["X_mesh"][0, 1] = np.nan
        dd["__invctl__"] = np.asarray(json.dumps(mm))
        np.savez(tmp / f"bad_{label}.npz", **dd)
        files.append(tmp / f"bad_{label}.npz")
    files += [good, tmp / "missing.npz", tmp]
    (tmp / "afile.txt").write_text("a file, not a folder\n")
    (tmp / "existing.npz").write_bytes(raw)
    _FILES[key] = files
    return files


# ------------------------------------------------------------ scene files
BASES = ["knife_edge", "bouncing_ball", "gear_backlash"]


@st.composite
def corrupted_scene(draw, tmp: Path, case: int) -> tuple[str, str]:
    base = draw(st.sampled_from(BASES))
    text = (Path(__file__).resolve().parents[1] / "invctl_scenes" / f"{base}.py").read_text()
    lines = text.splitlines(keepends=True)
    how = draw(st.sampled_from(["truncate", "delete_line", "insert_garbage", "replace", "bytes", "empty"]))
    if how == "truncate":
        text = text[: draw(st.integers(0, len(text)))]
    elif how == "delete_line":
        i = draw(st.integers(0, len(lines) - 1))
        text = "".join(lines[:i] + lines[i + 1:])
    elif how == "insert_garbage":
        i = draw(st.integers(0, len(lines)))
        junk = draw(st.sampled_from(["raise RuntimeError('boom')\n", "import no_such_module_xyz\n", "SCENE = 3\n",
                                     "SCENE = None\n", "def build(**k):\n    return 42\n", "x = 1 +\n",
                                     "PARAMS = {'m': float('nan')}\n", "\tbad indent\n",
                                     draw(st.text(string.printable, max_size=40)) + "\n"]))
        text = "".join(lines[:i] + [junk] + lines[i:])
    elif how == "replace":
        a, b = draw(st.sampled_from([("SCENE = Scene(", "SCEN = Scene("), ("return Model(", "return None and Model("),
                                     ("positive=(", "positive=('nope', "), ("build,", "42,"),
                                     ("params=", "params=[1] or "), ("1.0", "float('inf')"), ("def build", "def _b"),
                                     ("Contact(", "Contact(controllers=3, "), ("Tracking(", "Tracking(split='x', ")]))
        text = text.replace(a, b, 1)
    elif how == "bytes":
        i = draw(st.integers(0, len(text)))
        path = tmp / f"scene{case}.py"
        path.write_bytes(text[:i].encode() + draw(st.sampled_from([b"\x00", b"\xff\xfe", b"\x80"])) +
                         text[i:].encode())
        return str(path), base
    else:
        text = ""
    path = tmp / f"scene{case}.py"
    path.write_text(text)
    return str(path), base


# ------------------------------------------------------------------ cases
@st.composite
def command_line(draw, tmp: Path):
    case = CASES["n"]
    kind = draw(st.sampled_from(["scene"] * 8 + ["scene_file", "animate"]))
    if kind == "animate":
        argv = ["animate", str(draw(st.sampled_from([p for p in _result_files(tmp) if "good" not in p.name])))]
        if draw(st.booleans()):
            argv += ["--fps", draw(st.sampled_from(["25", "0", "-1", "nan", "abc", "1e300"]))]
        return argv + ["--json"], None
    if kind == "scene_file":
        path, base = draw(corrupted_scene(tmp, case))
        cmd = draw(st.sampled_from(list(INFO[base][0]) + ["invert"]))
        cmd = "analyze" if cmd in HEAVY else cmd
        return [cmd, path, "--json", "--quiet"] if cmd in ("simulate", "invert") else [cmd, path, "--json"], None
    scene = draw(st.sampled_from(SCENES))
    offered = list(INFO[scene][0])
    cmd = draw(st.sampled_from(offered + ["invert", "design", "analyze", "generate"]))
    argv = [cmd] + (["tradeoff"] if cmd == "study" else []) + [scene, "--json"]
    heavy = cmd in HEAVY and cmd in offered
    if cmd == "generate":  # a base inversion and a grid: run one case in three in CI
        heavy = "invert" in offered and draw(st.integers(0, 2)) > 0
        argv += ["--workers", "1", "--verify", "none"]
    for _ in range(draw(st.integers(0, 3))):
        argv += ["--set", draw(assignment(scene))]
    for name in options_of(cmd):
        if draw(st.integers(0, 9)) < 3:
            argv += _option_values(draw, name, scene, tmp, case)
    if "simulate" == cmd and "--t-end" not in argv and draw(st.booleans()):
        argv += ["--t-end", draw(st.sampled_from(["0.05", "0.3"]))]
    if heavy and not LONG:
        # CI: end every heavy case before its run, with an option error drawn at random
        argv += draw(st.sampled_from([["--set", "nope=1"], ["--out-dir", str(tmp / "afile.txt")],
                                      ["--set", "t_end=nan"], ["--plant-set", "nope=2"], ["--job", "no_such_job"],
                                      ["--quiet", "--t-end", "-1"]]))
    if cmd in ("invert", "simulate", "pipeline", "study", "generate") and "--quiet" not in argv:
        argv.append("--quiet")
    return argv, scene


def _strict_json(text: str):
    def bad_constant(c):
        raise ValueError(f"non-standard JSON constant {c}")

    return json.loads(text, parse_constant=bad_constant)


def _nan_strings(obj, path=""):
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _nan_strings(v, f"{path}.{k}")
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _nan_strings(v, f"{path}[{i}]")
    elif isinstance(obj, str) and obj.strip().lower() in ("nan", "-nan", "+nan"):
        yield path


def run_case(argv: list[str], cwd: Path) -> tuple[int, str, str]:
    """``main(argv)`` in ``cwd`` (relative and default output paths land there), with the time limit."""
    out, err = io.StringIO(), io.StringIO()
    old = signal.signal(signal.SIGALRM, _alarm)
    here = os.getcwd()
    os.chdir(cwd)
    signal.setitimer(signal.ITIMER_REAL, CASE_LIMIT_S)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            rc = main(argv)
    except CaseTimeout:
        pytest.fail(f"hang: {argv} ran longer than {CASE_LIMIT_S} s")
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
        os.chdir(here)
    return rc, out.getvalue(), err.getvalue()


def check_property(argv, rc, out, err) -> str:
    """The property of the module docstring; returns the outcome label."""
    assert "Traceback" not in out + err, f"{argv}: traceback\n{err[-3000:]}"
    assert rc in (0, 2), f"{argv}: exit {rc}\nstderr: {err[-3000:]}\nstdout: {out[-1000:]}"
    lines = out.strip().splitlines()
    assert lines, f"{argv}: no output (exit {rc}); stderr: {err[-2000:]}"
    try:
        data = _strict_json(lines[-1])
    except ValueError as exc:
        raise AssertionError(f"{argv}: last line is not strict JSON ({exc}): {lines[-1][:500]}") from None
    assert isinstance(data, dict), f"{argv}: last line is not a JSON object"
    if rc == 0:
        assert "error" not in data, f"{argv}: exit 0 with an error object {data}"
        nans = list(_nan_strings(data))
        assert not nans, f"{argv}: NaN in a success answer at {nans[:5]}"
        return "ok"
    assert set(data) >= {"error", "message"}, f"{argv}: error object without error/message: {data}"
    assert data["error"] in SPECIFIC, f"{argv}: unspecific error class {data['error']}: {data['message'][:500]}"
    assert data["message"].strip(), f"{argv}: empty error message"
    return data["error"]


@pytest.fixture(scope="module")
def fuzz_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("fuzz")
    (d / "cwd").mkdir()
    return d


@pytest.fixture(scope="module", autouse=True)
def _report(request):
    yield
    if CASES["n"]:
        summary = ", ".join(f"{k}: {v}" for k, v in OUTCOMES.most_common())
        line = (f"fuzz ({'long' if LONG else 'CI'} profile): {CASES['n']} cases in {CASES['wall']:.1f} s -- {summary}"
                f"\n  slowest: {CASES['slowest']}")
        capman = request.config.pluginmanager.getplugin("capturemanager")
        with capman.global_and_fixture_disabled() if capman is not None else contextlib.nullcontext():
            print("\n" + line, flush=True)


@settings(max_examples=EXAMPLES, deadline=None, database=None,
          derandomize=not (LONG or os.environ.get("INVCTL_FUZZ_RANDOM")),
          suppress_health_check=list(HealthCheck))
@given(data=st.data())
def test_fuzz_cli(fuzz_dir, data):
    old_smoke = os.environ.get("INVCTL_SMOKE")
    os.environ["INVCTL_SMOKE"] = "1"
    try:
        argv, _ = data.draw(command_line(fuzz_dir))
        CASES["n"] += 1
        t = time.perf_counter()
        rc, out, err = run_case(argv, fuzz_dir / "cwd")
        dt = time.perf_counter() - t
        CASES["wall"] += dt
        CASES["slowest"] = sorted(CASES["slowest"] + [(round(dt, 2), " ".join(argv))], reverse=True)[:3]
        OUTCOMES[check_property(argv, rc, out, err)] += 1
    finally:
        if old_smoke is None:
            os.environ.pop("INVCTL_SMOKE", None)
        else:
            os.environ["INVCTL_SMOKE"] = old_smoke


def test_property_checker_rejects_bad_outcomes():
    """The checker itself fails on what it must catch (so the fuzz test can fail)."""
    ok = '{"a": 1}'
    assert check_property(["x"], 0, ok + "\n", "") == "ok"
    for rc, out, err in [(3, '{"error": "InternalError", "message": "x"}', ""),
                         (0, '{"a": NaN}', ""), (0, '{"a": "nan"}', ""),
                         (2, '{"error": "ValueError", "message": "x"}', ""),
                         (0, ok, "Traceback (most recent call last):"), (0, "", ""), (2, "not json", ""),
                         (130, '{"error": "RunInterrupted", "message": "x"}', "")]:
        with pytest.raises((AssertionError, pytest.fail.Exception)):
            check_property(["x"], rc, out, err)
    assert check_property(["x"], 2, '{"error": "ParameterError", "message": "bad"}', "") == "ParameterError"
    assert math.isfinite(CASE_LIMIT_S)


# ------------------------------------------------------------ trajectory libraries: sizes and one owner
from invctl.studies.library_data import reference_arguments  # noqa: E402

_TRACKING = [s for s in SCENES if load_scene(s).kind == "tracking" and "invert" in load_scene(s).commands]


@st.composite
def huge_size(draw):
    """A size far beyond the budgets (the default INVCTL_MAX_TIME and any machine's memory): the grid of
    ``generate`` (10^8 .. 10^15 points over 1-3 axes), ``analyze --samples`` (>= 10^9: >= 16 h),
    ``invert``/``generate --N`` (>= 10^8 intervals: terabytes); returns (argv, option)."""
    scene = draw(st.sampled_from(_TRACKING))
    what = draw(st.sampled_from(["grid", "samples", "invert-N", "generate-N"]))
    if what == "samples":
        return ["analyze", scene, "--samples", str(draw(st.integers(10**9, 10**12)))], "--samples"
    if what == "invert-N":
        return ["invert", scene, "--N", str(draw(st.integers(10**8, 10**12)))], "--N"
    refargs = sorted(k for k, v in reference_arguments(load_scene(scene)).items() if isinstance(v, float))
    names = refargs or sorted(load_scene(scene).params)
    k = draw(st.integers(1, min(3, len(names))))
    axes = draw(st.permutations(names))[:k]
    total = draw(st.integers(8, 15))
    split = sorted(draw(st.lists(st.integers(0, total), min_size=k - 1, max_size=k - 1)))
    exps = [b - a for a, b in zip([0] + split, split + [total])]
    argv = ["generate", scene, "--workers", str(draw(st.integers(1, 8)))]
    for name, e in zip(axes, exps):
        argv += ["--grid", f"{name}=1:2:{max(2, 10 ** e)}"]
    if what == "generate-N":
        argv += ["--N", str(draw(st.integers(10**8, 10**12)))]
        return argv, "--N"
    return argv, "--grid"


@settings(max_examples=30 if not LONG else 200, deadline=None, database=None,
          derandomize=not (LONG or os.environ.get("INVCTL_FUZZ_RANDOM")), suppress_health_check=list(HealthCheck))
@given(case=huge_size())
def test_fuzz_sizes_beyond_the_budget_are_refused_at_once(fuzz_dir, case):
    argv, option = case
    old = os.environ.pop("INVCTL_MAX_TIME", None)
    try:
        t = time.perf_counter()
        rc, out, err = run_case([*argv, "--json"], fuzz_dir / "cwd")
        wall = time.perf_counter() - t
    finally:
        if old is not None:
            os.environ["INVCTL_MAX_TIME"] = old
    assert check_property(argv, rc, out, err) == "ResourceLimitError", (argv, out[-500:])
    msg = json.loads(out.strip().splitlines()[-1])["message"]
    assert option in msg and ("or less" in msg or "or fewer" in msg), (argv, msg)
    assert wall < 10.0, (argv, wall)  # before any work: ~0.03 s after the scene is loaded


@st.composite
def two_libraries(draw):
    """Two grids of the cart-pole's end point (maybe equal) and one output (folder or .npz)."""
    def grid():
        lo = draw(st.sampled_from([0.3, 0.35, 0.4, 0.45]))
        return f"xf={lo}:{lo + 0.2:.2f}:{draw(st.integers(2, 4))}"
    a = grid()
    b = a if draw(st.booleans()) and draw(st.booleans()) else grid()
    return a, b, draw(st.sampled_from(["lib", "lib.npz"]))


@settings(max_examples=3 if not LONG else 20, deadline=None, database=None,
          derandomize=not (LONG or os.environ.get("INVCTL_FUZZ_RANDOM")), suppress_health_check=list(HealthCheck))
@given(case=two_libraries())
def test_fuzz_concurrent_generate_into_one_output(tmp_path_factory, case):
    """Two ``invctl generate`` started together into one output: each exits 0 or is refused
    (``LibraryError`` while the other writes, ``OutputPathError`` for other settings after it); the
    output then holds one run's grid, every point its own trajectory (the cart ends at its xf)."""
    import subprocess
    import sys

    from invctl.studies.library import Library

    a, b, out = case
    cwd = tmp_path_factory.mktemp("gen")
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    procs = [subprocess.Popen([sys.executable, "-m", "invctl.cli", "generate", "cartpole", "--grid", g, "--N", "40",
                               "--workers", "1", "--verify", "none", "--out", out, "--quiet", "--json"], cwd=cwd,
                              env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for g in (a, b)]
    res = [p.communicate(timeout=CASE_LIMIT_S * 5) + (p.returncode,) for p in procs]
    grids = []
    for (o, e, rc), g in zip(res, (a, b)):
        label = check_property(["generate", g], rc, o, e)
        assert label in ("ok", "LibraryError", "OutputPathError"), (g, label, o[-500:])
        if label == "ok":
            grids.append(g)
    assert grids and (a == b or len(grids) == 1), res
    lib = Library.load(cwd / out)
    lo, hi, n = (float(x) for x in grids[0].partition("=")[2].split(":"))
    assert [p["xf"] for p in lib.points] == pytest.approx(np.linspace(lo, hi, int(n)).tolist())
    for i, pt in enumerate(lib.points):
        inv = lib.inverse(i)
        assert abs(inv.q(inv.Tf)[0] - pt["xf"]) < 1e-6, (i, pt)


#: bounds of random size on the cart-pole (its exact inverse peaks at |F| = 1.32 N, |theta| = 0.065,
#: |x'| = 0.62 m/s, |F'| = 10 N/s, with 4.8 s of pre-actuation): value range of each kind
BOUND_KINDS = {"u": (0.02, 2.0), "u.F": (0.02, 2.0), "q.theta": (0.01, 0.1), "v.x": (0.1, 1.0),
               "u_rate": (0.3, 20.0), "pre": (0.3, 6.0)}


@settings(max_examples=20 if LONG else 5, deadline=None, database=None,
          derandomize=not (LONG or os.environ.get("INVCTL_FUZZ_RANDOM")),
          suppress_health_check=list(HealthCheck))
@given(data=st.data())
def test_fuzz_bounds_hold_between_the_nodes(fuzz_dir, data):
    """``invctl invert cartpole --bound ...`` with random bounds, schemes, meshes and minimum time: a
    success's saved trajectory meets the bound on a fine grid of its interpolant and in its samples,
    and reports that largest violation; anything else is a specific error."""
    from invctl.inversion.result import Inverse

    kind = data.draw(st.sampled_from(sorted(BOUND_KINDS)))
    lo, hi = BOUND_KINDS[kind]
    value = float(f"{data.draw(st.floats(lo, hi)):.6g}")  # as written on the command line
    asym = kind in ("u.F", "q.theta") and data.draw(st.booleans())
    low = float(f"{-0.5 * value:.6g}") if asym else -value
    spec = f"{kind}={low:.6g}:{value:.6g}" if asym else f"{kind}={value:.6g}"
    case = CASES["n"] = CASES["n"] + 1
    out = fuzz_dir / f"bounds_{case}.npz"
    argv = ["invert", "cartpole", "--bound", spec, "--N", str(data.draw(st.sampled_from([20, 40, 60]))),
            "--scheme", data.draw(st.sampled_from(["hermite-simpson", "hermite-simpson", "legendre3"])),
            "--out", str(out), "--force", "--json", "--quiet"]
    if kind != "pre" and data.draw(st.booleans()):
        argv.append("--minimum-time")
    t_case = time.perf_counter()
    rc, text, err = run_case(argv, fuzz_dir / "cwd")
    CASES["wall"] += time.perf_counter() - t_case
    OUTCOMES["bounds:" + check_property(argv, rc, text, err)] += 1
    if rc != 0:
        return
    report = json.loads(text.strip().splitlines()[-1])["bounds"]
    inv = Inverse.load(out)
    z = np.load(out)
    t = np.linspace(inv.T0, inv.Tf, 20001)
    b_lo, b_hi = low, value
    if kind == "pre":
        excess = (inv.t0 - inv.T0) - value
        assert z["t"][0] == pytest.approx(inv.T0) and excess <= 1e-9, f"{argv}: pre-actuation {inv.t0 - inv.T0}"
        return
    pick = {"u": lambda X, dX: X[inv._slice("u")], "u.F": lambda X, dX: X[inv._slice("u")],
            "q.theta": lambda X, dX: X[inv._slice("q")][1:2], "v.x": lambda X, dX: X[inv._slice("v")][0:1],
            "u_rate": lambda X, dX: dX[inv._slice("u")]}[kind]
    fine = pick(inv.X(t), inv.dX(t))
    tol = 1e-6 * max(1.0, value)
    assert np.max(fine - b_hi) <= tol and np.max(b_lo - fine) <= tol, f"{argv}: the trajectory violates {spec}"
    # 200 points per mesh interval (those of the report among them) and the polynomials' extrema
    s = np.arange(200) / 200
    t = np.concatenate([(inv.t_mesh[:-1, None] + np.diff(inv.t_mesh)[:, None] * s).ravel(), [inv.Tf]])
    row = {"q.theta": inv._slice("q").start + 1, "v.x": inv._slice("v").start}.get(kind, inv._slice("u").start)
    t = np.concatenate([t, inv.extrema(row, derivative=kind == "u_rate")])
    fine = pick(inv.X(t), inv.dX(t))
    measured = float(max(np.max(fine - b_hi), np.max(b_lo - fine), 0.0))
    if kind != "u_rate":  # the saved samples (rates are not saved)
        saved = {"u": z["u"], "u.F": z["u"], "q.theta": z["q"][1:2], "v.x": z["v"][0:1]}[kind]
        assert np.max(saved - b_hi) <= tol and np.max(b_lo - saved) <= tol, f"{argv}: saved samples violate {spec}"
    assert 0.0 <= report["max_violation_between_nodes"] <= tol
    assert report["max_violation_between_nodes"] == pytest.approx(measured, rel=1e-9, abs=1e-15), argv


# ------------------------------------------------------------- Ctrl-C in every simulator
#: long runs of every simulator kind (each would take a minute or more): the command line and the
#: end time of its run; ``None``: the event-driven reference, which no command runs (a Python call)
_SIGINT_RUNS = {
    "moreau-jean simulate": (["simulate", "bouncing_ball", "--set", "h=1e-7", "--set", "t_end=30", "--quiet"], 30.0),
    "moreau-jean pipeline": (["pipeline", "prismatic_clearance", "--set", "h=1e-7", "--no-animation", "--quiet"], 2.0),
    "switched simulate": (["simulate", "stiff_wall", "--set", "h_max=1e-6", "--t-end", "3"], 3.0),
    "switched simulate (wrist)": (["simulate", "compliant_wrist", "--set", "h_max=1e-6", "--t-end", "3"], 3.0),
    "switched pipeline": (["pipeline", "stiff_wall", "--set", "h_max=1e-6", "--t-end", "3", "--no-animation"], 3.0),
    "event-driven": (None, 1e5),
}


def _interrupt_once_stepping(monkeypatch, delay: float):
    """Send SIGINT to this process ``delay`` s after a simulator has made its first steps (a Moreau-Jean
    chunk recorded, a switched window propagated, an event-driven phase integrated); returns the timers."""
    import threading

    from invctl.simulate import contact_record, event_driven, switched

    timers = []

    def wrap(owner, name):
        fn = getattr(owner, name)

        def stepping(*a, **k):
            if not timers:
                timers.append(threading.Timer(delay, os.kill, (os.getpid(), signal.SIGINT)))
                timers[0].start()
            return fn(*a, **k)

        monkeypatch.setattr(owner, name, stepping)

    wrap(contact_record.ChunkRecorder, "consume")
    wrap(switched, "powers_apply")
    wrap(event_driven, "solve_ivp")
    return timers


def _check_prefix(path: Path, t_end: float, complete_ok: bool) -> None:
    """``path`` loads and holds a run from its start: finite, time ordered, within the horizon."""
    from invctl.simulate.contact_record import ContactTrajectory
    from invctl.simulate.switched import SwitchedSimulation

    if path.suffix == ".txt":
        assert path.read_text().startswith("PARTIAL RESULTS"), path
        return
    if path.suffix == ".csv":
        t = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)[:, 0]
        status = "interrupted"
    else:
        try:
            run = ContactTrajectory.load(path)
        except errors.ResultFileError:
            run = SwitchedSimulation.load(path)
        t, status = run.t, run.status
        assert np.all(np.isfinite(run.x if hasattr(run, "x") else run.q)), path
    assert t.size >= 1 and np.all(np.isfinite(t)) and np.all(np.diff(t) >= 0) and t[0] == 0.0, path
    assert t[-1] <= t_end * (1 + 1e-12), path
    assert status == "interrupted" or (complete_ok and status == "ok"), (path, status)


@pytest.mark.parametrize("kind", list(_SIGINT_RUNS))
@settings(max_examples=3, deadline=None, database=None, derandomize=not os.environ.get("INVCTL_FUZZ_RANDOM"),
          suppress_health_check=list(HealthCheck))
@given(data=st.data())
def test_fuzz_sigint_in_every_simulator_keeps_a_loadable_prefix(kind, data, tmp_path_factory):
    """A Ctrl-C at a random moment of a long run of each simulator: exit 130 with a RunInterrupted JSON
    that lists the files kept; the prefix of the interrupted run is among them (``x.partial.npz``/``.csv``,
    ``run_<controller>.partial.npz``) and every file listed loads as a run from its start."""
    argv, t_end = _SIGINT_RUNS[kind]
    delay = data.draw(st.floats(0.0, 0.8), label="delay")
    cwd = tmp_path_factory.mktemp("sigint")
    with pytest.MonkeyPatch.context() as mp:
        timers = _interrupt_once_stepping(mp, delay)
        try:
            if argv is None:
                import invctl_scenes.bouncing_ball as bb
                from invctl.simulate.event_driven import simulate_event_driven

                model = bb.build(e=data.draw(st.sampled_from([0.8, 1.0]), label="e"))
                with pytest.raises(errors.RunInterrupted) as exc:
                    simulate_event_driven(model, [1.0], [0.0], t_end, potential=bb.potential(model),
                                          max_events=10**7, v_rest=1e-300)
                path = cwd / "x.partial.npz"
                exc.value.partial.to_npz(path)
                _check_prefix(path, t_end, complete_ok=False)
                return
            argv = list(argv)
            if argv[0] == "pipeline":
                argv += ["--out-dir", "out"]
            else:
                argv += ["--out", "x." + data.draw(st.sampled_from(["npz", "csv"] if "switched" in kind else ["npz"]),
                                                   label="suffix")]
            if kind.startswith("moreau"):
                k = data.draw(st.sampled_from([None, 1000, 30000]), label="record_every")
                argv += ["--record-every", str(k)] if k else []
            rc, out, err = run_case(argv + ["--json"], cwd)
        finally:
            for t in timers:
                t.cancel()
    assert rc == 130, f"{argv}: exit {rc}\n{err[-2000:]}"
    d = _strict_json(out.strip().splitlines()[-1])
    assert d["error"] == "RunInterrupted" and d["partial"], (argv, d)
    files = [cwd / f for f in d["partial"]]
    expected = ({"x.partial.npz", "x.partial.csv"} if argv[0] == "simulate" else
                {"run_switched.partial.npz", "run_pd.partial.npz", "run_preload.partial.npz"})
    assert any(f.name in expected for f in files), (argv, d["partial"])
    for f in files:
        assert f.is_file(), f
        _check_prefix(f, t_end, complete_ok=argv[0] == "pipeline")


# ------------------------------------------------------------ references with constant components
_SLIDER = Path(__file__).resolve().parent / "scenes" / "cart_pole_and_slider.py"


@st.composite
def constant_components(draw):
    """A cart-pole-and-slider scene file whose rest-to-rest reference holds a random subset of its two
    components constant (at a random value; possibly both), and a controller to simulate after ``design``."""
    moves = draw(st.sampled_from([(True, False), (False, True), (False, False)]))
    start = [draw(st.sampled_from([0.0, 0.1, -0.2])) for _ in range(2)]
    end = [s + (draw(st.sampled_from([0.3, -0.4])) if m else 0.0) for s, m in zip(start, moves)]
    return start, end, draw(st.sampled_from(["C1", "C2", "C3"]))


@settings(max_examples=4 if not LONG else 30, deadline=None, database=None,
          derandomize=not (LONG or os.environ.get("INVCTL_FUZZ_RANDOM")), suppress_health_check=list(HealthCheck))
@given(case=constant_components())
def test_fuzz_constant_reference_components_design_and_simulate(fuzz_dir, case):
    """Structurally zero derivatives of constant components never become an internal error (they did:
    ``Sparsities of v and vdef must match``): exit 0 or a documented error."""
    start, end, controller = case
    text = _SLIDER.read_text().replace("rest_to_rest([0.0, 0.0], [0.5, 0.0]",
                                       f"rest_to_rest({start!r}, {end!r}")
    assert text != _SLIDER.read_text()
    path = fuzz_dir / f"slider_{abs(hash((tuple(start), tuple(end)))):x}.py"
    path.write_text(text)
    for argv in (["design", str(path), "--json"],
                 ["simulate", str(path), "--controller", controller, "--t-end", "2.5", "--json"]):
        rc, out, err = run_case(argv, fuzz_dir / "cwd")
        label = check_property(argv, rc, out, err)
        if start != end:  # a reference that does not move at all asks for Tracking(expected_error=...)
            assert label == "ok", (argv, out[-800:])
