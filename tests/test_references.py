"""References users have: rest-to-rest moves, waypoint paths, sampled data, stacks.

Checked against closed forms (the derivative of the rest-to-rest law, the k = 4 law of
003 Sect. 6, least-squares limits of the smoothing spline), independent implementations
(scipy's clamped cubic spline and GCV smoothing spline) and numerical one-sided limits.
"""
import math

import casadi as ca
import numpy as np
import pytest
from scipy.interpolate import CubicSpline, make_smoothing_spline

from invctl.errors import ReferenceSignalError
from invctl.reference import Reference, from_samples, poly9_timing_law, rest_to_rest, waypoints
from invctl.reference.piecewise import continuity_jumps


def one_sided(ref, b, j, delta):
    """Left and right limits of ``y^(j)`` at ``b`` without using the AD derivative of order j:
    second-order one-sided differences of ``y^(j-1)`` (``y`` itself for j = 0)."""
    if j == 0:  # linear extrapolation from each side, also second order
        return (2 * ref([b - delta])[:, 0] - ref([b - 2 * delta])[:, 0],
                2 * ref([b + delta])[:, 0] - ref([b + 2 * delta])[:, 0])
    f = lambda x: ref(np.atleast_1d(x), j - 1)[:, 0]  # noqa: E731
    left = (3 * f(b) - 4 * f(b - delta) + f(b - 2 * delta)) / (2 * delta)
    right = (-3 * f(b) + 4 * f(b + delta) - f(b + 2 * delta)) / (2 * delta)
    return left, right


def derivative_scales(ref, order, n=2001):
    tt = np.linspace(ref.t0, ref.tf, n)
    return [float(np.max(np.abs(ref(tt, j)))) for j in range(order + 3)]


def assert_continuous(ref, breaks, order, rtol=1e-6):
    """One-sided limits of y^(0..order) at every break agree with the AD value there.

    delta = 1e-5 of the span: truncation of the differences is ~delta^2 |y^(j+2)| and rounding
    ~eps |y^(j-1)| / delta, both below 1e-8 of the derivative's scale on these signals;
    rtol = 1e-6 leaves a margin of 100 and is far below any real jump."""
    delta = 1e-5 * (ref.tf - ref.t0)
    scale = derivative_scales(ref, order)
    for b in breaks:
        for j in range(order + 1):
            ad = ref([b], j)[:, 0]
            left, right = one_sided(ref, b, j, delta)
            tol = rtol * max(scale[j], 1e-12)
            assert np.max(np.abs(left - ad)) <= tol, (b, j, left, ad)
            assert np.max(np.abs(right - ad)) <= tol, (b, j, right, ad)


# --------------------------------------------------------------------------- rest to rest
@pytest.mark.parametrize("k", [0, 1, 2, 3, 4, 6, 8])
def test_rest_to_rest_closed_form(k):
    y0, yf, t0, tf = np.array([0.5, -1.0]), np.array([2.0, 3.0]), 0.3, 1.8
    T, dy = tf - t0, yf - y0
    ref = rest_to_rest(y0, yf, t0, tf, smoothness=k)
    assert ref.smoothness == k and ref.m == 2
    tt = np.linspace(t0 - 0.5, tf + 0.5, 1201)
    s = np.clip((tt - t0) / T, 0, 1)
    # S_k'(s) = (2k+1)!/(k!)^2 s^k (1-s)^k: the defining closed form (exact in exact arithmetic);
    # rounding of the degree-(2k+1) evaluation is ~1e-13 relative
    c = math.factorial(2 * k + 1) / math.factorial(k) ** 2
    expected = c * (s * (1 - s)) ** k / T * dy[:, None]
    expected[:, (tt <= t0) | (tt >= tf)] = 0.0  # k = 0: the kink belongs to the constant part
    assert np.allclose(ref(tt, 1), expected, rtol=1e-11, atol=1e-11 * np.max(np.abs(expected)))
    # ends, symmetry y(t0 + tf - t) + y(t) = y0 + yf, midpoint
    assert np.allclose(ref([t0 - 1, t0, tf, tf + 1]), np.c_[y0, y0, yf, yf], atol=1e-14)
    assert np.allclose(ref(tt) + ref(t0 + tf - tt), (y0 + yf)[:, None], atol=1e-13)
    assert np.allclose(ref([0.5 * (t0 + tf)])[:, 0], 0.5 * (y0 + yf), atol=1e-14)
    # order k + 1 is the first derivative that does not vanish at the ends (from inside):
    # S^(k+1)(0) = (k+1)! C(2k+1, k), S^(k+1)(1) = (-1)^k S^(k+1)(0); y^(j) for j <= k starts
    # like its Taylor term first eps^(k+1-j)/(k+1-j)! (next term relatively O(k^2 eps / T) < 1e-2)
    first = math.factorial(k + 1) * math.comb(2 * k + 1, k) * dy / T ** (k + 1)
    t_in = [np.nextafter(t0, np.inf), np.nextafter(tf, -np.inf)]
    assert np.allclose(ref(t_in, k + 1), np.c_[first, (-1) ** k * first], rtol=1e-9)
    eps = 1e-4 * T
    for j in range(1, k + 1):
        taylor = first * eps ** (k + 1 - j) / math.factorial(k + 1 - j)
        assert np.allclose(ref([t0 + eps], j)[:, 0], taylor, rtol=1e-2), j
    # and derivatives 0..k are continuous across the ends (one-sided limits: zero from outside)
    assert_continuous(ref, [t0, tf], k)


def test_rest_to_rest_k4_is_the_law_of_003():
    t = ca.SX.sym("t")
    t0, tf = 0.2, 1.7
    law = Reference(t, 3.0 + 2.0 * poly9_timing_law(t, t0, tf), t0, tf, smoothness=4)
    ref = rest_to_rest(3.0, 5.0, t0, tf, smoothness=4)
    tt = np.linspace(0.0, 2.0, 2001)
    for j in range(5):
        scale = np.max(np.abs(law(tt, j)))
        # monomial vs positive-term form of the same polynomial: both round at ~1e-13 of the
        # scale (sum of |coefficients| 1471 x eps), 1e-11 leaves a margin of 100
        assert np.max(np.abs(ref(tt, j) - law(tt, j))) <= 1e-11 * scale, j


def test_rest_to_rest_scalar_broadcast_and_errors():
    ref = rest_to_rest(0.0, [1.0, 2.0, -1.0], 0.0, 1.0, 2)
    assert ref.m == 3 and np.allclose(ref([1.0])[:, 0], [1, 2, -1])
    with pytest.raises(ReferenceSignalError, match="t0 < tf"):
        rest_to_rest(0, 1, 1.0, 1.0)
    with pytest.raises(ReferenceSignalError, match="smoothness"):
        rest_to_rest(0, 1, 0, 1, smoothness=1.5)
    with pytest.raises(ReferenceSignalError, match="smoothness"):
        rest_to_rest(0, 1, 0, 1, smoothness=-1)
    with pytest.raises(ReferenceSignalError, match="components"):
        rest_to_rest([0, 1], [1, 2, 3], 0, 1)
    with pytest.raises(ReferenceSignalError, match="finite"):
        rest_to_rest([0, np.nan], [1, 2], 0, 1)


# --------------------------------------------------------------------------- waypoints
TIMES = np.array([0.0, 0.4, 1.1, 1.5, 2.6, 3.0])
VALUES = np.array([[0.0, 1.0], [0.5, 1.2], [0.2, 0.4], [0.9, 0.8], [1.4, -0.3], [1.0, 0.0]])


@pytest.mark.parametrize("k", [1, 2, 3, 4])
@pytest.mark.parametrize("stop", [False, True])
def test_waypoints_interpolate_rest_and_continuity(k, stop):
    ref = waypoints(TIMES, VALUES, smoothness=k, stop=stop)
    assert ref.smoothness == k and ref.m == 2 and (ref.t0, ref.tf) == (TIMES[0], TIMES[-1])
    assert np.max(np.abs(ref(TIMES) - VALUES.T)) <= 1e-12
    ends = ref([TIMES[0], TIMES[-1]], 0)
    assert np.allclose(ref([TIMES[0] - 1, TIMES[-1] + 1]), ends, atol=0)   # held constant outside
    rests = TIMES if stop else TIMES[[0, -1]]
    for j in range(1, k + 1):
        scale = derivative_scales(ref, k)[j]
        assert np.max(np.abs(ref(rests, j))) <= 1e-10 * scale, j
    assert_continuous(ref, TIMES, k)
    # the library's own check (one ulp either side, through the same SX expression)
    jumps = continuity_jumps(ref, TIMES, k)
    assert np.all(jumps.max(axis=1) <= 1e-9 * np.array(derivative_scales(ref, k)[:k + 1]))


def test_waypoint_spline_inner_smoothness_and_the_check_can_fail():
    """Inside, the degree-(2k+1) spline is C^{2k}; its derivative 2k+1 jumps at the waypoints,
    and the one-sided-limit check sees that (so it is not a test that cannot fail)."""
    k = 1
    ref = waypoints(TIMES, VALUES, smoothness=k)
    assert_continuous(ref, TIMES[1:-1], 2 * k)
    with pytest.raises(AssertionError):
        assert_continuous(ref, TIMES[1:-1], 2 * k + 1)


def test_waypoints_match_independent_splines():
    # k = 1: the cubic spline with zero end slopes (scipy's clamped CubicSpline, another code path)
    ref = waypoints(TIMES, VALUES, smoothness=1)
    cs = CubicSpline(TIMES, VALUES, bc_type="clamped")
    tt = np.linspace(TIMES[0], TIMES[-1], 777)[:-1]  # y'' jumps at the end (C^1), tf belongs to the rest
    for j in range(3):
        # both are exact cubics; rounding ~1e-13 of the values (times 1/h^j for derivatives)
        assert np.max(np.abs(ref(tt, j) - cs(tt, j).T)) <= 1e-10 * max(1, np.max(np.abs(cs(tt, j)))), j
    # k = 0: linear interpolation
    lin = waypoints(TIMES, VALUES[:, 0], smoothness=0)
    assert np.max(np.abs(lin(tt)[0] - np.interp(tt, TIMES, VALUES[:, 0]))) <= 1e-14
    # two waypoints: the unique polynomial of degree 2k+1 is the rest-to-rest move
    for k in (2, 4):
        two = waypoints([0.5, 2.0], [[1.0, 0.0], [3.0, -2.0]], smoothness=k)
        r2r = rest_to_rest([1.0, 0.0], [3.0, -2.0], 0.5, 2.0, smoothness=k)
        tt = np.linspace(0, 2.5, 501)
        for j in range(k + 1):
            assert np.max(np.abs(two(tt, j) - r2r(tt, j))) <= 1e-9 * max(1, np.max(np.abs(r2r(tt, j)))), (k, j)


def test_waypoints_stop_segments_are_rest_to_rest_moves():
    ref = waypoints(TIMES, VALUES, smoothness=3, stop=True)
    for i in range(TIMES.size - 1):
        seg = rest_to_rest(VALUES[i], VALUES[i + 1], TIMES[i], TIMES[i + 1], smoothness=3)
        tt = np.linspace(TIMES[i], TIMES[i + 1], 51)[:-1]
        assert np.max(np.abs(ref(tt) - seg(tt))) <= 1e-13
        assert np.max(np.abs(ref(tt, 2) - seg(tt, 2))) <= 1e-9 * np.max(np.abs(seg(tt, 2)) + 1)


def test_waypoints_errors():
    with pytest.raises(ReferenceSignalError, match="increasing"):
        waypoints([0, 1, 1], [0, 1, 2])
    with pytest.raises(ReferenceSignalError, match="pass values.T"):
        waypoints(TIMES, VALUES.T)
    with pytest.raises(ReferenceSignalError, match="finite"):
        waypoints([0, 1], [0, np.inf])
    with pytest.raises(ReferenceSignalError, match="at least 2"):
        waypoints([0.0], [1.0])


# --------------------------------------------------------------------------- sampled data
T_END = 2.0


def signal(t, j=0):
    """A smooth signal at rest (to order 4) at 0 and T_END: S_4(s) + 0.3 sin^5(pi s)."""
    t_ = ca.SX.sym("t")
    s = t_ / T_END
    e = 70 * s**9 - 315 * s**8 + 540 * s**7 - 420 * s**6 + 126 * s**5 + 0.3 * ca.sin(np.pi * s) ** 5
    for _ in range(j):
        e = ca.jacobian(e, t_)
    t = np.atleast_1d(t)
    return np.array(ca.Function("f", [t_], [e]).map(t.size)(t[None, :])).ravel()


def noisy_samples(seed):
    rng = np.random.default_rng(seed)
    N, sigma = 400, 0.01
    t = np.r_[0.0, np.sort(rng.uniform(0, T_END, N - 2)), T_END]
    return t, signal(t) + sigma * rng.standard_normal(N), sigma


@pytest.fixture(scope="module")
def noisy():
    return noisy_samples(7)


@pytest.mark.parametrize("seed", [7, 8, 9])
def test_from_samples_recovers_a_smooth_signal(seed):
    t, y, sigma = noisy_samples(seed)
    ref = from_samples(t, y, smoothness=4)
    d = ref.diagnostics
    out = d["outputs"][0]
    assert ref.smoothness == 4 and d["degree"] == 5 and d["rule"] == "gcv"
    tt = np.linspace(0, T_END, 2001)
    err = np.max(np.abs(ref(tt)[0] - signal(tt)))
    # a linear smoother with trace edf has pointwise noise std ~ sigma sqrt(edf / N); the max over
    # the interval of the (noise + smaller bias) error stays within 4 of those
    bound = 4 * sigma * math.sqrt(out["edf"] / t.size)
    assert err <= bound, (err, bound)
    # velocity within 5 % of its peak (differentiation amplifies noise by ~ 1/bandwidth)
    vel = signal(tt, 1)
    assert np.max(np.abs(ref(tt, 1)[0] - vel)) <= 0.05 * np.max(np.abs(vel))
    # noise estimate: RSS/(N - edf) is chi-square with ~390 dof, relative std 3.6 %; 3 sd
    assert abs(out["sigma_hat"] / sigma - 1) <= 0.11
    # the reported residuals are those of the reference itself
    res = y - ref(t)[0]
    assert np.allclose(d["residuals"][0], res, atol=1e-14)
    assert out["rms_residual"] == pytest.approx(np.sqrt(np.mean(res**2)), rel=1e-12)
    # at rest at the ends and C^4 across every knot (including the ends, where it is glued)
    for j in range(1, 5):
        assert np.max(np.abs(ref([0.0, T_END], j))) <= 1e-8 * derivative_scales(ref, 4)[j]
    assert_continuous(ref, d["breaks"], 4)


def test_gcv_is_close_to_the_best_smoothing_in_hindsight(noisy):
    """The GCV choice (no knowledge of the signal or the noise) is within 1.5x of the true error of
    the best lambda on a grid chosen knowing the signal; the noise rule (known sigma) as well."""
    t, y, sigma = noisy
    tt = np.linspace(0, T_END, 801)
    truth = signal(tt)

    def rms(ref):
        return float(np.sqrt(np.mean((ref(tt)[0] - truth) ** 2)))

    gcv = from_samples(t, y, 4)
    lam = gcv.diagnostics["outputs"][0]["lam"]
    oracle = min(rms(from_samples(t, y, 4, smoothing=lam * f)) for f in 10.0 ** np.arange(-3, 3.1, 0.5))
    assert rms(gcv) <= 1.5 * oracle
    assert rms(from_samples(t, y, 4, smoothing="noise", noise=sigma)) <= 1.5 * oracle


def test_cubic_smoothing_spline_matches_scipy(monkeypatch):
    """k = 2, free ends, a knot at every sample: the classical cubic smoothing spline.
    Ours minimizes (1/N) RSS + lam int_0^1 f_ss^2 ds (s = (t - t1)/L): scipy's lam is N lam L^3."""
    rng = np.random.default_rng(3)
    N = 60
    t = np.sort(rng.uniform(0, 2, N))
    y = np.sin(3 * t) + 0.05 * rng.standard_normal(N)
    L = t[-1] - t[0]
    tt = np.linspace(t[0], t[-1], 500)
    for lam in (1e-8, 1e-6, 1e-4):
        ours = from_samples(t, y, 2, smoothing=lam, ends="free", max_pieces=N)
        sp = make_smoothing_spline(t, y, lam=N * lam * L**3)
        # same minimizer by two factorizations; conditioning ~1e3, rounding ~1e-13
        assert np.max(np.abs(ours(tt)[0] - sp(tt))) <= 1e-9
        assert np.max(np.abs(ours(tt, 2)[0] - sp(tt, 2))) <= 1e-7 * np.max(np.abs(sp(tt, 2)))
    # plain GCV (no 1.4 factor) chosen independently by both: same curve to well below the noise (0.05)
    monkeypatch.setattr("invctl.reference.samples.GCV_GAMMA", 1.0)
    ours = from_samples(t, y, 2, ends="free", max_pieces=N)
    assert np.max(np.abs(ours(tt)[0] - make_smoothing_spline(t, y)(tt))) <= 0.005


def test_heavy_smoothing_limits_are_least_squares_polynomials():
    """lam -> inf leaves the unpenalized part: with rest ends a constant (the weighted mean), with
    free ends (m = 2) the least-squares line."""
    rng = np.random.default_rng(5)
    t = np.linspace(0, 1, 80)
    y = 1 + 2 * t + 0.1 * rng.standard_normal(t.size)
    w = rng.uniform(0.5, 2.0, t.size)
    rest = from_samples(t, y, 2, smoothing=1e12, weights=w)
    # penalty 1e12 against data O(1): the fit is within ~1e-9 of the limit
    assert np.allclose(rest(t)[0], np.sum(w * y) / np.sum(w), atol=1e-7)
    free = from_samples(t, y, 2, smoothing=1e12, ends="free")
    assert np.allclose(free(t)[0], np.polyval(np.polyfit(t, y, 1), t), atol=1e-7)
    assert free.smoothness == 0 and free.diagnostics["interior_smoothness"] == 2
    with pytest.raises(ReferenceSignalError, match="C\\^0"):
        free.require(3, "servo-constraint inversion")


def test_from_samples_vector_many_samples_and_per_output_smoothing():
    rng = np.random.default_rng(11)
    N = 3000
    t = np.linspace(0, T_END, N)
    sig = np.array([0.002, 0.05])
    Y = np.c_[signal(t), -2 * signal(t)] + sig * rng.standard_normal((N, 2))
    ref = from_samples(t, Y, 3, max_pieces=40)
    d = ref.diagnostics
    assert ref.m == 2 and d["pieces"] == 40 and ref.smoothness == 3
    lams = [o["lam"] for o in d["outputs"]]
    assert lams[1] > lams[0]  # more noise, more smoothing
    tt = np.linspace(0, T_END, 1001)
    truth = np.vstack([signal(tt), -2 * signal(tt)])
    for r in range(2):
        # same rule as above: 4 sd of the smoother's pointwise noise, plus the bias of 40 pieces
        # of degree 5 (below 1e-4 for this signal)
        bound = 4 * sig[r] * math.sqrt(d["outputs"][r]["edf"] / N) + 1e-4
        assert np.max(np.abs(ref(tt)[r] - truth[r])) <= bound
    assert_continuous(ref, d["breaks"], 3)


def test_from_samples_unsorted_samples_and_weights():
    """Order of the samples does not matter; residuals come back in the order given; a sample
    with a much smaller weight pulls the fit much less (weights are inverse variances)."""
    rng = np.random.default_rng(2)
    t = np.linspace(0, T_END, 120)
    y = signal(t) + 0.01 * rng.standard_normal(t.size)
    perm = rng.permutation(t.size)
    a = from_samples(t, y, 4, smoothing=1e-8)
    b = from_samples(t[perm], y[perm], 4, smoothing=1e-8)
    tt = np.linspace(0, T_END, 301)
    assert np.max(np.abs(a(tt) - b(tt))) <= 1e-12
    assert np.allclose(b.diagnostics["residuals"][0], y[perm] - b(t[perm])[0], atol=1e-14)
    y_out = y.copy()
    y_out[60] += 1.0  # an outlier
    w = np.ones(t.size)
    w[60] = 1e-6
    pulled = from_samples(t, y_out, 4, smoothing=1e-8)
    weighted = from_samples(t, y_out, 4, smoothing=1e-8, weights=w)
    assert abs(weighted([t[60]])[0, 0] - a([t[60]])[0, 0]) <= 1e-3 < abs(pulled([t[60]])[0, 0] - a([t[60]])[0, 0])


def test_from_samples_errors():
    t = np.linspace(0, 1, 30)
    y = np.sin(t)
    with pytest.raises(ReferenceSignalError, match="pass y.T"):
        from_samples(t, np.vstack([y, y]))
    with pytest.raises(ReferenceSignalError, match="not finite .* t = 0.5"):
        from_samples(np.linspace(0, 1, 3), [0.0, np.nan, 1.0])
    with pytest.raises(ReferenceSignalError, match="noise=sigma"):
        from_samples(t, y, smoothing="noise")
    with pytest.raises(ReferenceSignalError, match="smoothing"):
        from_samples(t, y, smoothing=-1.0)
    with pytest.raises(ReferenceSignalError, match="ends"):
        from_samples(t, y, ends="periodic")
    with pytest.raises(ReferenceSignalError, match="too few"):
        from_samples(t[:3], y[:3], 4)
    with pytest.raises(ReferenceSignalError, match="weights"):
        from_samples(t, y, weights=-np.ones(30))


# --------------------------------------------------------------------------- stacks, require, cost
def test_stack_of_different_kinds(noisy):
    t, y, _ = noisy
    a = rest_to_rest(0.0, 1.0, 0.5, 1.5, 4, name="x_ref")
    b = waypoints(TIMES, VALUES, 2, name="path")
    c = from_samples(t, y, 3, name="measured")
    ref = Reference.stack([a, b, c])
    assert ref.m == 4 and ref.smoothness == 2
    assert (ref.t0, ref.tf) == (0.0, 3.0)
    tt = np.linspace(-0.5, 3.5, 301)
    for j in range(3):
        assert np.array_equal(ref(tt, j), np.vstack([a(tt, j), b(tt, j), c(tt, j)]))
    ref.require(2)
    with pytest.raises(ReferenceSignalError, match=r"needs y_ref with 3 .*only C\^2.*path \(C\^2\)"):
        ref.require(3, "servo-constraint inversion")
    with pytest.raises(ReferenceSignalError, match="not a Reference"):
        Reference.stack([a, np.zeros(2)])
    with pytest.raises(ReferenceSignalError, match="at least one"):
        Reference.stack([])


def test_require():
    ref = rest_to_rest(0, 1, 0, 1, smoothness=2, name="q1_ref")
    ref.require(2, "funnel controller")
    with pytest.raises(ReferenceSignalError, match="funnel controller needs q1_ref with 3 .* only C\\^2"):
        ref.require(3, "funnel controller")


def test_piecewise_expression_size_grows_linearly_and_derivatives_are_cheap():
    """The coefficient-selection construction: instructions ~ P (d + 3) for the value, and each
    AD derivative adds O(d) (not O(P d) as a chain of if_else would): structural, not timed."""
    rng = np.random.default_rng(1)
    counts = {}
    for P in (25, 50):
        ref = waypoints(np.arange(P + 1.0), rng.standard_normal(P + 1), 4)   # degree 9
        counts[P] = [ref.function(o).n_instructions() for o in (0, 4)]
    assert counts[50][0] <= 40 * 50 + 200
    assert counts[50][1] - counts[50][0] == counts[25][1] - counts[25][0] <= 600


def test_derivatives_of_a_constant_component_are_dense_zeros():
    """A component held constant has structurally zero derivatives; the Function gives them as dense
    zeros (callers substitute the values for dense symbols, e.g. the funnel controller's jets)."""
    ref = rest_to_rest([0.0, 0.3], [0.5, 0.3], t0=0.0, tf=2.0, smoothness=4)
    fn = ref.function(3)
    for k in range(4):
        assert fn.sparsity_out(k).is_dense(), k
    t, jets = ca.SX.sym("t"), [ca.SX.sym(f"y{k}", 2) for k in range(4)]
    e = ca.sumsqr(ca.vertcat(*jets))
    val = ca.Function("e", [t], [ca.substitute(e, ca.vertcat(*jets), ca.vertcat(*fn(t)))])(1.0)
    assert float(val) == pytest.approx(float(np.sum(np.concatenate([ref([1.0], k)[:, 0] for k in range(4)]) ** 2)))
