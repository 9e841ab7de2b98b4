import os

import matplotlib
import pytest

matplotlib.use("Agg")
os.environ.setdefault("MPLBACKEND", "Agg")
# no detached compile workers from the suite (tests/test_inversion_solver.py runs one on purpose)
os.environ.setdefault("INVCTL_BACKGROUND_COMPILE", "0")


@pytest.fixture(scope="session")
def manipulator():
    import problems.manipulator as scene

    return scene.build()
