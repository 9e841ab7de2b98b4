"""The constraint residuals an inversion reports (``diagnostics["residuals"]``), recomputed from
the solution's interpolant and the model's equations written out here."""
import casadi as ca
import numpy as np
import pytest

from invctl.inversion import invert
from invctl.model import Model, ParamSet
from invctl.reference import Reference, poly9_timing_law


def test_holonomic_residual_of_a_pendulum_in_cartesian_coordinates():
    """A point mass on a rod (g = x^2 + z^2 - L^2, L = 1 m) pushed horizontally, y = x (no internal
    dynamics).  On a coarse mesh (N = 12) the reported ``holonomic_between`` is max |g| at a
    quarter, half and three quarters of each interval (its largest value there is negative)."""
    P = ParamSet(["m", "L", "c"])
    q, v = ca.SX.sym("q", 2), ca.SX.sym("v", 2)
    md = Model.from_lagrangian("cartesian_pendulum", q, v, P, {"m": 1.0, "L": 1.0, "c": 0.3},
                               T=0.5 * P["m"] * ca.dot(v, v), V=9.81 * P["m"] * q[1], Q=-P["c"] * v,
                               B=ca.DM([[1.0], [0.0]]), h=q[0], g=q[0] ** 2 + q[1] ** 2 - P["L"] ** 2)
    t = ca.SX.sym("t")
    yr = Reference(t, 0.6 * poly9_timing_law(t, 0.0, 1.0), 0.0, 1.0, 4)
    inv = invert(md, yr, N=12, backend="newton", q_guess=[0.0, -1.0])
    tm = inv.t_mesh
    tt = (tm[:-1, None] + np.diff(tm)[:, None] * np.array([0.25, 0.5, 0.75])).ravel()
    x, z = inv.q(tt)
    g = x**2 + z**2 - 1.0
    assert -g.min() > 1.05 * g.max() > 0
    assert inv.diagnostics["residuals"]["holonomic_between"] == pytest.approx(np.max(np.abs(g)), rel=1e-9)
