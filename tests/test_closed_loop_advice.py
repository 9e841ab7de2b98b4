"""The diagnosis of an integrator failure inside the funnel (``ClosedLoop._advice``) on given
input histories: the finite-time-escape verdict and the |u| values it quotes."""
from types import SimpleNamespace

import numpy as np
import pytest

from invctl.simulate.closed_loop import ClosedLoop

LOOP = SimpleNamespace(max_num_steps=500, dt=0.01, rtol=1e-8, atol=1e-10, controller=None)


def _result(u):
    u = np.asarray(u, float)
    n = u.shape[1]
    return SimpleNamespace(u=u, q=np.zeros((1, n)), v=np.zeros((1, n)), t=0.01 * np.arange(n))


def test_escape_is_recognised_from_the_fifth_output_sample():
    """|u| = 1, 1, 1, 2.5, 10 (k = 4): |u| at the last sample exceeds twice |u| three steps before
    and every earlier value, so the advice is the escape with the numbers 1 -> 10 in 0.03 s."""
    msg = ClosedLoop._advice(LOOP, _result([[1.0, 1.0, 1.0, 2.5, 6.0], [0.0, 0.0, 0.0, 0.0, 8.0]]))
    assert "escapes in finite time" in msg and "grew from 1 to 10 in the last 0.03 s" in msg
    assert "max_num_steps" in msg


@pytest.mark.parametrize("u", [[1.0, 1.0, 2.5, 10.0],                # four samples: too few to tell
                               [1.0, 6.0, 1.0, 2.5, 10.0],          # |u| was already larger than half
                               [1.0, 1.0, 1.0, 2.5, 1.9]])          # no growth over the last three steps
def test_no_escape_verdict_without_growth_over_three_steps(u):
    msg = ClosedLoop._advice(LOOP, _result([u]))
    assert msg.startswith("; the integrator reached its limits") and "escapes" not in msg
