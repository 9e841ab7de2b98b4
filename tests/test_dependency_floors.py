"""The declared lower bounds of the dependencies are the versions pinned in constraints-lowest.txt, the set on
which the whole suite is run before a bound changes (README, Development)."""
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _floors() -> dict:
    text = (ROOT / "pyproject.toml").read_text()
    deps = text[text.index("dependencies = ["):]
    deps = deps[:deps.index("]")]
    return {m[0].lower(): m[1] for m in re.findall(r'"([A-Za-z0-9_.-]+)>=([0-9.]+)"', deps)}


def _pins() -> dict:
    out = {}
    for line in (ROOT / "constraints-lowest.txt").read_text().splitlines():
        line = line.split("#")[0].strip()
        if line:
            name, version = line.split("==")
            out[name.strip().lower()] = version.strip()
    return out


def _release(v: str) -> tuple:
    parts = [int(x) for x in v.split(".")]
    return tuple(parts + [0] * (3 - len(parts)))


def test_every_dependency_has_a_floor_pinned_in_the_constraints_file():
    floors, pins = _floors(), _pins()
    assert set(floors) == {"casadi", "numpy", "scipy", "control", "matplotlib"}
    assert set(pins) == set(floors)
    for name, floor in floors.items():
        assert _release(pins[name]) == _release(floor), (name, floor, pins[name])
