"""Event times of the exact switched simulation (002 (1)-(3)) against closed forms.

With a constant reference the filters stay at rest, so each mode of the loop is a damped
oscillator with constant forcing whose solution is written out here; crossings of the wall
``x = 0`` are roots of those closed forms (``brentq`` to 1e-15 s).
"""
import math

import pytest
from scipy.optimize import brentq

from invctl.control.switched import ClosedLoop, RigidWallPlant, SwitchedForceController
from invctl.reference.gluing import GluedReference, piecewise_polynomial
from invctl.simulate.switched import simulate_switched


KH = 1e3   # ke_hat: in the free phase F_d = ke_hat x_d


def _loop(x_ref, ctrl, plant):
    """Constant position reference ``x_ref`` (free phase until t = 0.9 s), F profile 0."""
    ref = GluedReference(piecewise_polynomial([0.0], [[x_ref]]), piecewise_polynomial([0.0], [[0.0]]),
                         [(0.9, 0.95)], 1000.0, 300.0, KH, 10.0, contact_start="time")
    return ClosedLoop(plant, ctrl, ref)


def _oscillator(c, k, f, x0, v0):
    """x(t) of x'' + c x' + k x = f (underdamped) from x(0) = x0, x'(0) = v0."""
    s, w = c / 2, math.sqrt(k - c * c / 4)
    xs = f / k
    a, b = x0 - xs, (v0 + s * (x0 - xs)) / w
    return lambda t: xs + math.exp(-s * t) * (a * math.cos(w * t) + b * math.sin(w * t))


@pytest.mark.parametrize("unit", [1.0, 1e3])
def test_graze_between_samples_in_free_motion(unit):
    """Free motion (kp = (2 pi)^2, kd = 0.2, M = 1) around x_d = -1 m swings up to only ~1e-7 m past
    the wall, between two samples (32 per period): the crossing is found by the graze screen at
    the closed-form time.  The same motion in millimetres (every position x 1e3: the loop is
    linear and the wall is at 0) gives the same times: the screen's tolerance is relative."""
    kp, kd = (2 * math.pi) ** 2, 0.2
    xd = -1.0
    free = _oscillator(kd, kp, kp * xd, 0.0, 0.0)       # shape of the swing; scaled below
    # start at x0 (v0 = 0) so that the first maximum is 1e-7 above the wall
    t_pk = brentq(lambda t: (free(t + 1e-7) - free(t - 1e-7)), 0.3, 0.7)
    peak0 = free(t_pk)                                   # from x0 = 0: max of the first swing
    x0 = xd + (1e-7 - xd) * (0.0 - xd) / (peak0 - xd)    # linear in x0 - x_d
    x = _oscillator(kd, kp, kp * xd, x0, 0.0)
    t_in = brentq(x, 0.3, t_pk, xtol=1e-15)
    ctrl = SwitchedForceController(1.0, kp, kd, 1.0, 5.0)
    plant = RigidWallPlant(1.0, 0.0, 1e6, 10.0)
    sim = simulate_switched(_loop(unit * xd, ctrl, plant), 0.52, h_max=1.0, state0=[unit * x0, 0.0])
    assert x(t_pk) == pytest.approx(1e-7, rel=1e-6)
    assert sim.event_t.size >= 1
    assert sim.event_t[0] == pytest.approx(t_in, abs=1e-9)
    # the sample before lies well outside the ~0.14 ms excursion: only the screen can find it
    assert sim.event_t[0] - sim.t[sim.t < sim.event_t[0]][-1] > 1e-3


def test_start_inside_the_wall_is_in_contact():
    """From x0 = 1 mm inside the wall (v0 = 0) the contact law acts at once: with Fd = ke_hat x_d
    (x_d = -1 mm at rest, free phase), ``M x'' = (1 + kf) (Fd - ke x - be x') - bf x' - b x'``;
    the mass leaves the wall at the closed-form first root of x(t)."""
    M, b, ke, be = 1.0, 2.0, 1e4, 5.0
    kf, bf, kh = 0.5, 3.0, KH
    xd = -1e-3
    ctrl = SwitchedForceController(1.0, 400.0, 40.0, kf, bf)
    plant = RigidWallPlant(M, b, ke, be)
    c = ((1 + kf) * be + bf + b) / M
    k = (1 + kf) * ke / M
    f = (1 + kf) * kh * xd / M
    x = _oscillator(c, k, f, 1e-3, 0.0)
    t_out = brentq(x, 1e-6, 0.5 * math.pi / math.sqrt(k) * 2, xtol=1e-15)
    sim = simulate_switched(_loop(xd, ctrl, plant), 0.05, state0=[1e-3, 0.0])
    assert sim.event_t[0] == pytest.approx(t_out, abs=1e-9)
    inside = sim.t < t_out - 1e-6
    for tk, xk in zip(sim.t[inside][::25], sim.x[inside][::25]):
        assert xk == pytest.approx(x(tk), abs=1e-12)
