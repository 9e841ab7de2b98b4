"""tools/mutate.py on a tiny package in a temporary git repository (not on invctl)."""
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "tools" / "mutate.py"

MODULE = '''"""Tiny module: a < b in this docstring is never mutated."""


def clip(x, lo):
    """Return x, or lo if x < lo."""
    if x < lo:
        return lo
    return x


def untested(a, b):
    return a + b


def double(x):
    return 2 * x


def message(x):
    if x:
        raise ValueError(f"x > 0: {x < 1}")  # raise lines are skipped
    return x


def label(x):
    return "x=" + str(x)  # string building is skipped
'''

TEST = '''import time

from pkg.tiny import clip, double


def test_clip():
    if clip(5, 0) != 5:  # the `< -> >` mutant hangs
        time.sleep(60)
    assert clip(-1, 0) == 0
    assert clip(2, 0) == 2
    assert double(3) == 6
'''


def _git(root, *args):
    subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", *args], cwd=root,
                   check=True, capture_output=True)


@pytest.fixture
def repo(tmp_path):
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "__init__.py").write_text("")
    (tmp_path / "pkg" / "tiny.py").write_text(MODULE)
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "test_tiny.py").write_text(TEST)
    _git(tmp_path, "init", "-q")
    _git(tmp_path, "add", ".")
    _git(tmp_path, "commit", "-q", "-m", "tiny")
    return tmp_path


# the tiny tests need no plugins; skipping their autoload keeps each pytest run well under a second
ENV = dict(os.environ, PYTEST_DISABLE_PLUGIN_AUTOLOAD="1")


def _cmd(root, *args):
    return [sys.executable, str(SCRIPT), "--root", str(root), "--modules", "pkg/tiny.py", *args]


def _run(root, *args):
    return subprocess.run(_cmd(root, *args), capture_output=True, text=True, timeout=60, env=ENV)


def test_list_runs_nothing_and_skips_docstrings_and_raise(repo):
    r = _run(repo, "--list", "--out", str(repo / "report.txt"))
    assert r.returncode == 0, r.stderr
    keys = [line.split()[0] for line in r.stdout.splitlines() if line.startswith("pkg/")]
    assert "pkg/tiny.py:6:<" in keys            # `if x < lo:`
    assert "pkg/tiny.py:12:+" in keys           # `return a + b`
    assert not any(k.startswith(("pkg/tiny.py:1:", "pkg/tiny.py:5:", "pkg/tiny.py:21:",
                                   "pkg/tiny.py:26:"))
                   for k in keys)               # docstrings and the raise line
    assert not (repo / "report.txt").exists()   # nothing was run, no report


def test_killed_survived_timeout_and_restored(repo):
    source = (repo / "pkg" / "tiny.py").read_bytes()
    equivalent = repo / "equivalent.txt"
    equivalent.write_text("# comment\npkg/tiny.py:6:< -> <=  # x == lo returns lo either way\n")
    out = repo / "report.txt"
    # 10 s: the looping mutant's cost; the others end in about 1 s unloaded (python + pytest start)
    r = _run(repo, "--out", str(out), "--equivalent", str(equivalent), "--timeout", "10")
    assert r.returncode == 0, r.stderr
    assert (repo / "pkg" / "tiny.py").read_bytes() == source
    status = {line.split(None, 3)[3]: line.split()[1]
              for line in r.stdout.splitlines() if line.startswith("[")}
    assert status == {"pkg/tiny.py:6:< -> <=": "survived",   # equivalent
                      "pkg/tiny.py:6:< -> >": "timeout",
                      "pkg/tiny.py:12:+ -> -": "survived",
                      "pkg/tiny.py:16:2 -> 1": "killed",
                      "pkg/tiny.py:16:* -> /": "killed"}
    report = out.read_text()
    survivors, equivalents = report.split("survivors (")[1].split("equivalent mutants")
    assert survivors.split("\n")[1:-1] == ["  pkg/tiny.py:12:+ -> -"]
    assert "pkg/tiny.py:6:< -> <=  # x == lo returns lo either way" in equivalents
    assert "pkg/tiny.py    " in report and "75.0%" in report   # 3 of 4 non-equivalent caught


def test_ctrl_c_restores_the_file(repo):
    path = repo / "pkg" / "tiny.py"
    source = path.read_bytes()
    proc = subprocess.Popen(_cmd(repo, "--timeout", "60"), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=ENV)
    deadline = time.monotonic() + 30
    while b"x > lo" not in path.read_bytes():   # wait for the hanging `< -> >` mutant
        assert time.monotonic() < deadline and proc.poll() is None
        time.sleep(0.05)
    time.sleep(0.3)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=10)
    assert proc.returncode == 130
    assert "interrupted" in err
    assert path.read_bytes() == source


def test_refuses_uncommitted_changes(repo):
    path = repo / "pkg" / "tiny.py"
    path.write_text(path.read_text() + "\n# local edit\n")
    r = _run(repo)
    assert r.returncode == 2
    assert "git status" in r.stderr
    assert path.read_text().endswith("# local edit\n")


def test_per_folder_sampling_draws_from_every_folder(repo):
    (repo / "other").mkdir()
    (repo / "other" / "few.py").write_text("def f(a, b):\n    return a - b\n")
    _git(repo, "add", ".")
    _git(repo, "commit", "-q", "-m", "other")

    def listed(*args):
        r = _run(repo, "other", "--max-mutants", "2", "--list", *args)
        assert r.returncode == 0, r.stderr
        return [line.split(":")[0] for line in r.stdout.splitlines() if ":" in line]

    per_folder = listed("--per-folder")
    assert per_folder.count("pkg/tiny.py") == 2 and per_folder.count("other/few.py") == 1
    assert len(listed()) == 2                    # without it: 2 in all
    assert listed("--per-folder") == per_folder  # the seed fixes the sample


def test_only_and_rerun(repo):
    r = _run(repo, "--only", "pkg/tiny.py:12:+ -> -")
    assert r.returncode == 0, r.stderr
    assert [line.split()[1] for line in r.stdout.splitlines() if line.startswith("[")] == \
        ["survived"]
    earlier = repo / "earlier.txt"
    earlier.write_text("[1/5] killed      1.0s  pkg/tiny.py:16:2 -> 1\n"
                       "[2/5] survived    1.0s  pkg/tiny.py:12:+ -> -\n"
                       "[3/5] timeout     3.0s  pkg/tiny.py:6:< -> >\n")
    with open(repo / "tests" / "test_tiny.py", "a") as f:   # now kill the survivor
        f.write("\n\ndef test_untested():\n    from pkg.tiny import untested\n"
                "    assert untested(1, 2) == 3\n")
    out = repo / "rerun.txt"
    # nothing re-run here loops: a generous timeout keeps a loaded machine from turning a kill into a timeout
    r = _run(repo, "--rerun", str(earlier), "--timeout", "60", "--out", str(out))
    assert r.returncode == 0, r.stderr
    status = {line.split(None, 3)[3]: line.split()[1:3]
              for line in out.read_text().splitlines() if line.startswith("[")}
    assert status["pkg/tiny.py:16:2 -> 1"] == ["killed", "0.0s"]      # carried over
    assert status["pkg/tiny.py:12:+ -> -"][0] == "killed"              # re-run, now caught
    assert status["pkg/tiny.py:6:< -> >"] == ["timeout", "0.0s"]
    assert len(status) == 5 and "2 results carried over" in out.read_text()
    assert out.read_text().startswith("# python tools/mutate.py ")
    assert "survivors (1):\n  pkg/tiny.py:6:< -> <=\n" in out.read_text()   # the equivalent one
    merged = _run(repo, "--rerun", str(earlier), "--merge")   # survivors carried too: nothing re-run
    assert merged.returncode == 0, merged.stderr
    assert "3 results carried over" in merged.stdout
    assert "survived    0.0s  pkg/tiny.py:12:+ -> -" in merged.stdout
    only = _run(repo, "--rerun", str(earlier), "--merge", "--report-only")   # runs nothing at all
    assert only.returncode == 0, only.stderr
    assert "not run (2):\n  pkg/tiny.py:6:< -> <=\n  pkg/tiny.py:16:* -> /" in only.stdout
    bad = _run(repo, "--only", "pkg/tiny.py:99:+ -> -")
    assert bad.returncode == 2 and "no such mutant" in bad.stderr
    earlier.write_text("[1/1] survived    1.0s  pkg/tiny.py:99:+ -> -\n")
    bad = _run(repo, "--rerun", str(earlier))
    assert bad.returncode == 2 and "not in this sample" in bad.stderr


def test_arguments_from_a_file(repo):
    """``@FILE``: one argument a line, e.g. a fixed sample of keys for --only."""
    args = repo / "sample.txt"
    args.write_text("--only\npkg/tiny.py:16:2 -> 1\npkg/tiny.py:12:+ -> -\n")
    r = _run(repo, "--list", f"@{args}")
    assert r.returncode == 0, r.stderr
    assert [line.split("    ")[0] for line in r.stdout.splitlines() if line.startswith("pkg/")] == \
        ["pkg/tiny.py:16:2 -> 1", "pkg/tiny.py:12:+ -> -"]


def test_keys_of_removed_calls_survive_a_report_round_trip(repo):
    """``abs(x) -> (x)`` has an empty replacement; its key has no trailing blank, so --only, --rerun and the
    equivalent list find it again."""
    (repo / "pkg" / "tiny.py").write_text(MODULE + "\n\ndef size(x):\n    return abs(x)\n")
    _git(repo, "commit", "-qam", "abs")
    key = "pkg/tiny.py:30:abs ->"
    r = _run(repo, "--list")
    assert key in [line.split("    [")[0] for line in r.stdout.splitlines()]
    earlier = repo / "earlier.txt"
    earlier.write_text(f"[1/1] killed      1.0s  {key}\n")
    r = _run(repo, "--only", key + " ", "--rerun", str(earlier))
    assert r.returncode == 0, r.stderr
    assert f"killed      0.0s  {key}" in r.stdout


def test_every_core_module_is_mapped_to_existing_tests():
    """No core module falls back to the name heuristics or to unrelated fallback tests."""
    sys.path.insert(0, str(SCRIPT.parent))
    try:
        import mutate
    finally:
        sys.path.remove(str(SCRIPT.parent))
    root = SCRIPT.parents[1]
    modules = [m for m in mutate.expand(root, mutate.CORE) if not m.endswith("__init__.py")]
    assert modules and not [m for m in modules if m not in mutate.TEST_MAP]
    assert all((root / t).is_file() for tests in mutate.TEST_MAP.values() for t in tests)


def test_baseline_failure_skips_the_module_unless_told_not_to_check(repo):
    with open(repo / "tests" / "test_tiny.py", "a") as f:
        f.write("\n\ndef test_broken():\n    assert False\n")
    r = _run(repo, "--timeout", "3")
    assert r.returncode == 0 and "skipped pkg/tiny.py: its tests fail without any mutation" in r.stdout
    r = _run(repo, "--timeout", "3", "--no-baseline", "--only", "pkg/tiny.py:12:+ -> -")
    assert "killed" in r.stdout            # the unchecked broken test "kills" everything: hence the warning
