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
    r = _run(repo, "--out", str(out), "--equivalent", str(equivalent), "--timeout", "3")
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
