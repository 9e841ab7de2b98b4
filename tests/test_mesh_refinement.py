"""Error-driven mesh refinement (``Discretization.tol``) on the minimum-phase two-link arm:
the local error estimate against an independent differentiation, and the refined mesh size
against the smallest uniform mesh that meets the same tolerance (brute force)."""
import numpy as np
import pytest

import invctl_scenes.two_link_arm as arm
from invctl.inversion import invert, servo_model
from invctl.inversion.refine import interval_errors
from invctl.inversion.verify import forward_check

KW = dict(T0=-0.5, Tf=2.0, start={"q": "all", "v": "all", "u": "all"}, end={}, backend="newton")


@pytest.fixture(scope="module")
def arm_problem():
    md = arm.build()
    return md, arm.reference(md)


def test_interval_errors_match_a_five_point_derivative(arm_problem):
    """``h_k max |X' - F(X, t)| / (1 + max |X|)`` at s = 0.17, 0.33, 0.67, 0.83 of each interval,
    with X' from a five-point stencil (exact for the cubic pieces up to round-off) instead of
    the library's central difference."""
    md, rf = arm_problem
    inv = invert(md, rf, N=20, **KW)
    servo = servo_model(md)
    tm = inv.t_mesh
    h = np.diff(tm)
    s = np.array([0.17, 0.33, 0.67, 0.83])
    want = np.zeros(h.size)
    scale = 1.0 + np.max(np.abs(inv.X_mesh), axis=1)
    for k in range(h.size):
        t = tm[k] + h[k] * s
        d = 1e-3 * h[k]
        dX = (-inv.X(t + 2 * d) + 8 * inv.X(t + d) - 8 * inv.X(t - d) + inv.X(t - 2 * d)) / (12 * d)
        Y = servo.reference_samples(rf, t)
        F = np.column_stack([np.array(servo.rhs(inv.X(t)[:, i], Y[:, i], md.theta_values)).ravel()
                             for i in range(t.size)])
        want[k] = h[k] * np.max(np.abs(dX - F) / scale[:, None])
    got = interval_errors(inv, servo, rf, md.theta_values)
    assert want.max() > 1e-3                      # a coarse mesh: the estimate is far from round-off
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-9 * want.max())


def test_refined_mesh_is_no_larger_than_twice_the_uniform_one(arm_problem):
    """tol = 1e-6 from N = 20: the refined N stays within max_N and below twice the smallest
    uniform N (of 60, 80, ..., 160) whose forward-check error meets tol."""
    md, rf = arm_problem
    tol = 1e-6
    inv = invert(md, rf, N=20, tol=tol, max_N=400, **KW)
    Ns = [m["N"] for m in inv.diagnostics["meshes"]]
    assert inv.diagnostics["max_output_error"] <= tol and all(n <= 400 for n in Ns)
    uniform = next(n for n in range(60, 161, 20) if forward_check(md, invert(md, rf, N=n, **KW), rf)["error"] <= tol)
    assert Ns[-1] <= 2 * uniform
