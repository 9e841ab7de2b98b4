import os
import signal
from pathlib import Path

import matplotlib
import pytest

matplotlib.use("Agg")
os.environ.setdefault("MPLBACKEND", "Agg")
# no detached compile workers from the suite (tests/test_inversion_solver.py runs one on purpose)
os.environ.setdefault("INVCTL_BACKGROUND_COMPILE", "0")


def pytest_configure(config):
    """Tests of Ctrl-C send SIGINT to this process and to command-line children. A suite started as a background job
    (``pytest ... &`` in a script) inherits SIGINT ignored, and so would every child: a Python started with
    SIGINT ignored keeps ignoring it, and the child ran to the end (exit 0). Give the suite a terminal's default,
    which the children then inherit."""
    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


#: node ids of the tests measured slow (tests/slow_tests.txt): `pytest -m "not slow"` is the quick tier
_SLOW = {line.strip() for line in (Path(__file__).parent / "slow_tests.txt").read_text().splitlines()
         if line.strip() and not line.startswith("#")}


def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.nodeid in _SLOW:
            item.add_marker(pytest.mark.slow)


@pytest.fixture(scope="session")
def manipulator():
    import invctl_scenes.manipulator as scene

    return scene.build()


@pytest.fixture(scope="session")
def model():
    """The manipulator on its ``guess`` parameter set (the held-solver tests' model; m3 = 0.5, c = 5), one per test
    process, so the modules share what the inversion builds and keeps on it (a module's own ``model`` fixture takes
    precedence)."""
    import invctl_scenes.manipulator as scene

    return scene.build(**scene.PRESETS["guess"])


@pytest.fixture(scope="session")
def ref(model):
    """The manipulator scene's reference for ``model``."""
    import invctl_scenes.manipulator as scene

    return scene.reference(model)
