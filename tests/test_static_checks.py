"""The linter and the type checker configured in pyproject.toml pass on the package (and the shipped scenes)."""
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _run(*args):
    return subprocess.run([sys.executable, "-m", *args], cwd=ROOT, capture_output=True, text=True, timeout=600)


def test_the_linter_passes():
    pytest.importorskip("ruff")
    r = _run("ruff", "check", "invctl", "invctl_scenes", "tests", "benchmarks", "tools")
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-2000:]


def test_the_type_checker_passes():
    pytest.importorskip("mypy")
    r = _run("mypy", "--no-incremental")
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-2000:]
    assert "Success" in r.stdout


def test_the_package_says_it_is_typed():
    assert (ROOT / "invctl" / "py.typed").is_file()
