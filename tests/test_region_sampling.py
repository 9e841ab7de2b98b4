"""Region sampling (analyze --samples): the vectorized box test and per-point constraints draw exactly the
points a point-by-point rejection with OperatingRegion.contains draws from the same random stream."""
import numpy as np
import pytest

import invctl_scenes.cartpole as cartpole
import invctl_scenes.manipulator as manipulator
import invctl_scenes.two_link_arm as two_link_arm


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

