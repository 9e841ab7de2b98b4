"""OperatingRegion against a region stated in closed form: membership, sampling box, retries, immutability."""
import numpy as np
import pytest


# a region stated in closed form: the open box (-1, 1) x (0, inf) with q1 + q2 > 0.5, sampled in q2 < 2
def _closed_form(q):
    return -1 < q[0] < 1 and q[1] > 0 and q[0] + q[1] > 0.5


def _box():
    from invctl.model import OperatingRegion

    return OperatingRegion([-1.0, 0.0], [1.0, np.inf], constraints=(lambda q: q[0] + q[1] - 0.5,),
                           sample_bounds=([-5.0, -5.0], [5.0, 2.0]), description="box")


def test_contains_is_the_open_box_and_the_strict_constraint():
    region = _box()
    grid = np.array([[a, b] for a in (-1.5, -1.0, -0.5, 0.0, 0.25, 1.0) for b in (-0.5, 0.0, 0.25, 0.5, 3.0)])
    expected = np.array([_closed_form(q) for q in grid])
    assert expected.any() and not expected.all()
    assert [region.contains(q) for q in grid] == expected.tolist()     # boundary points are outside
    assert region.inside(grid).tolist() == expected.tolist()


def test_samples_stay_in_the_sampling_box_and_fill_it():
    """Samples of q2 lie in (0, 2) (the region's (0, inf) cut by sample_bounds) and reach near both ends."""
    q, v = _box().sample(400, 1)
    assert all(_closed_form(x) for x in q) and q[:, 1].max() < 2.0 and q[:, 1].max() > 1.9
    assert q[:, 0].min() < -0.9 and q[:, 0].max() > 0.9 and np.all(np.abs(v) <= 1.0)


def test_sampling_retries_until_enough_points():
    """A constraint that accepts about 5 % of the box: one batch of 4 x count candidates is not enough."""
    from dataclasses import replace

    region = replace(_box(), constraints=(lambda q: q[0] - 0.9,))
    q, _ = region.sample(50, 0)
    assert q.shape == (50, 2) and np.all(q[:, 0] > 0.9)


def test_regions_are_immutable():
    from dataclasses import FrozenInstanceError

    region = _box()
    with pytest.raises(FrozenInstanceError):
        region.v_scale = 2.0
