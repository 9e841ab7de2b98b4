"""Region sampling (analyze --samples): the vectorized box test and per-point constraints draw exactly the
points a point-by-point rejection with OperatingRegion.contains draws from the same random stream."""
import numpy as np
import pytest

import problems.cartpole as cartpole
import problems.manipulator as manipulator
import problems.two_link_arm as two_link_arm


def _rejection(region, count, seed):
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(region.q_lower, float), np.asarray(region.q_upper, float)
    if region.sample_bounds is not None:
        lo, hi = np.maximum(lo, region.sample_bounds[0]), np.minimum(hi, region.sample_bounds[1])
    qs = []
    while len(qs) < count:
        qs.extend(c for c in rng.uniform(lo, hi, size=(4 * count, lo.size)) if region.contains(c))
    q = np.array(qs[:count])
    return q, rng.uniform(-region.v_scale, region.v_scale, size=q.shape)


@pytest.mark.parametrize("region", [cartpole.REGION, manipulator.REGION, two_link_arm.REGION,
                                    two_link_arm.REGION_TIP], ids=["cartpole", "manipulator", "two_link", "tip"])
@pytest.mark.parametrize("count", [1, 37, 3000])
def test_samples_equal_point_by_point_rejection(region, count):
    q, v = region.sample(count, 5)
    q_ref, v_ref = _rejection(region, count, 5)
    assert np.array_equal(q, q_ref) and np.array_equal(v, v_ref)
    assert all(region.contains(x) for x in q)


def test_a_constraint_that_rejects_everything_is_reported():
    from dataclasses import replace

    from invctl.errors import ModelError

    region = replace(cartpole.REGION, constraints=(lambda q: -1.0,))
    with pytest.raises(ModelError, match="could not sample"):
        region.sample(10, 0, max_tries=3)


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
    assert region._inside(grid).tolist() == expected.tolist()


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
