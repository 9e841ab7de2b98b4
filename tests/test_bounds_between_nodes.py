"""Bounds hold on the trajectory the user gets (the interpolants of :class:`Inverse`, the saved
``.npz`` samples), not only at the mesh and collocation points; the reported largest violation
between the nodes is the one measured on a fine grid."""
from __future__ import annotations

import contextlib
import io
import json

import numpy as np
import pytest

import invctl_scenes.cartpole as cp
from invctl.cli import main
from invctl.errors import InversionFailed
from invctl.inversion import Bounds, invert
from invctl.inversion.bounded import ACTIVE_TOL, between_nodes
from invctl.inversion.cache import servo_model
from invctl.inversion.mintime import minimum_time
from invctl.inversion.result import Inverse

TOL = 1e-9  # IPOPT meets the constraints to 1e-10


@pytest.fixture(scope="module")
def cartpole():
    md = cp.build()
    return md, cp.reference(md)


def _cli(*argv):
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        rc = main(list(argv) + ["--json", "--quiet"])
    return rc, json.loads(out.getvalue().strip().splitlines()[-1])


def _cubic_peak(inv, row):
    """Largest |X[row]| of the Hermite-Simpson interpolant, exactly: the ends of every interval and
    the real roots in it of the derivative of its cubic (independent of the library's sampling)."""
    best = np.max(np.abs(inv.X_mesh[row]))
    for k in range(inv.N):
        a, h = inv.t_mesh[k], inv.t_mesh[k + 1] - inv.t_mesh[k]
        y0, y1 = inv.X_mesh[row, k], inv.X_mesh[row, k + 1]
        d0, d1 = h * inv.dX_mesh[row, k], h * inv.dX_mesh[row, k + 1]
        # p(s) = c3 s^3 + c2 s^2 + c1 s + c0 in s = (t - a) / h
        c3, c2, c1 = 2 * y0 + d0 - 2 * y1 + d1, -3 * y0 - 2 * d0 + 3 * y1 - d1, d0
        for s in np.roots([3 * c3, 2 * c2, c1]):
            if abs(s.imag) < 1e-12 and 0 < s.real < 1:
                best = max(best, abs(float(inv.X([a + s.real * h])[row, 0])))
    return best


def test_cartpole_input_bound_holds_on_the_saved_and_sampled_feedforward(cartpole, tmp_path):
    # the audit case: the node-only bound let the saved feedforward reach |u| = 0.1047 (2.1x the
    # bound) at 439 of 1001 samples; now the .npz samples, the reloaded interpolant and the Python
    # result on 5000 points all stay within 0.05
    path = tmp_path / "cp.npz"
    rc, data = _cli("invert", "cartpole", "--bound", "u=0.05", "--out", str(path))
    assert rc == 0 and data["success"]
    z = np.load(path)
    assert z["u"].shape[1] == 1001 and np.max(np.abs(z["u"])) <= 0.05 + TOL
    inv = Inverse.load(path)
    t = np.linspace(inv.T0, inv.Tf, 5000)
    assert np.max(np.abs(inv.u(t))) <= 0.05 + TOL
    assert np.max(np.abs(inv.sample(t)["u"])) <= 0.05 + TOL
    # the bound is active (not trivially met) and the reported violation is the measured one
    assert np.max(np.abs(inv.u(t))) > 0.05 - 1e-6
    row = inv._slice("u").start
    exact = max(0.0, _cubic_peak(inv, row) - 0.05)
    b = data["bounds"]
    assert b["max_violation_between_nodes"] == pytest.approx(exact, abs=1e-12) and exact <= TOL
    assert b["samples_per_interval"] >= 10

    md, ref = cartpole
    py = invert(md, ref, bounds=Bounds(u=0.05))
    assert np.max(np.abs(py.u(t))) <= 0.05 + TOL
    assert py.diagnostics["bounds"]["max_violation_between_nodes"] <= TOL


def test_reported_violation_equals_an_independent_fine_grid_measurement(cartpole):
    # an interpolant that leaves the bound between its nodes (slopes of a node-only solution):
    # between_nodes reports the exact cubic peak to within its sampling, and flags the bound
    md, ref = cartpole
    inv = invert(md, ref, bounds=Bounds(u=0.05), N=60)
    row = inv._slice("u").start
    inv.dX_mesh[row] += np.where(np.arange(inv.N + 1) % 2, 3.0, -3.0)  # wiggles through the bound
    rb = Bounds(u=0.05).resolve(servo_model(md))
    chk = between_nodes(inv, rb)
    exact = _cubic_peak(inv, row) - 0.05
    assert exact > 1e-2
    assert chk["max_violation_bound"] == "u[F]"
    assert 0.99 * exact <= chk["max_violation_between_nodes"] <= exact + 1e-15
    t = np.linspace(inv.T0, inv.Tf, 200001)
    assert chk["max_violation_between_nodes"] <= np.max(np.abs(inv.u(t))) - 0.05 + 1e-4 * exact


@pytest.mark.parametrize("bounds, check", [
    (Bounds(u=(-0.03, 0.08)), lambda inv, t: (inv.u(t)[0], -0.03, 0.08)),
    (Bounds(q={"theta": 0.05}), lambda inv, t: (inv.q(t)[1], -0.05, 0.05)),
    (Bounds(v={"x": 0.3}), lambda inv, t: (inv.v(t)[0], -0.3, 0.3)),
    (Bounds(u_rate=0.5), lambda inv, t: (inv.dX(t)[inv._slice("u")][0], -0.5, 0.5)),
], ids=["u", "q", "v", "u_rate"])
def test_every_kind_of_bound_holds_between_the_nodes(cartpole, bounds, check):
    md, ref = cartpole
    inv = invert(md, ref, bounds=bounds, N=60)
    t = np.linspace(inv.T0, inv.Tf, 20001)
    x, lo, hi = check(inv, t)
    assert lo - TOL <= np.min(x) and np.max(x) <= hi + TOL
    assert min(hi - np.max(x), np.min(x) - lo) < 1e-6  # active
    assert inv.diagnostics["bounds"]["max_violation_between_nodes"] <= TOL


def test_pre_actuation_bound_holds_on_the_returned_trajectory(cartpole):
    md, ref = cartpole
    inv = invert(md, ref, bounds=Bounds(max_pre_actuation=1.0), N=60)
    assert ref.t0 - inv.T0 <= 1.0 + 1e-12
    t = np.linspace(inv.T0 - 2.0, ref.t0 - 1.0, 200)  # at rest (the start equilibrium) before T0
    assert np.ptp(inv.X(t), axis=1).max() == 0.0
    assert inv.diagnostics["bounds"]["max_violation_between_nodes"] == 0.0


@pytest.mark.parametrize("scheme", ["legendre3", "radau3"])
def test_collocation_schemes_bound_their_polynomials(cartpole, scheme):
    # their node-only solution leaves the bound between the collocation points: solved again with
    # the Bernstein coefficients of the polynomials bounded
    md, ref = cartpole
    inv = invert(md, ref, bounds=Bounds(u=0.05), N=60, scheme=scheme)
    t = np.linspace(inv.T0, inv.Tf, 20001)
    assert np.max(np.abs(inv.u(t))) <= 0.05 + TOL


def test_a_violation_between_the_nodes_is_never_a_success(cartpole):
    # rate bounds of a Legendre scheme hold at the collocation points only: the check refuses it
    md, ref = cartpole
    with pytest.raises(InversionFailed, match="u_rate.*hermite-simpson") as exc:
        invert(md, ref, bounds=Bounds(u_rate=0.5), N=60, scheme="legendre3")
    part = exc.value.partial
    assert part is not None and not part.success
    b = part.diagnostics["bounds"]
    assert b["max_violation_between_nodes"] > ACTIVE_TOL and b["max_violation_bound"] == "u_rate[F]"


@pytest.mark.parametrize("scheme, bounds, row, value", [
    ("hermite-simpson", Bounds(u=1.0), 4, 1.0), ("legendre3", Bounds(u=1.0), 4, 1.0),
    ("legendre3", Bounds(q={"theta": 0.03}), 1, 0.03),
])
def test_minimum_time_bounds_hold_on_the_returned_trajectory(cartpole, scheme, bounds, row, value):
    # exact tracking: the interior points moved to the extrema bound the interpolant exactly (its
    # peak touches the bound, checked at the roots of its derivative)
    md, ref = cartpole
    inv = minimum_time(md, ref, bounds=bounds, N=60, scheme=scheme)
    t = np.concatenate([np.linspace(inv.T0, inv.Tf, 20001), inv.extrema(row)])
    peak = np.max(np.abs(inv.X(t)[row]))
    assert value - 1e-6 < peak <= value + TOL
    assert inv.diagnostics["free_time"]["bound_violation"] <= TOL
    assert inv.diagnostics["bounds"]["max_violation_between_nodes"] <= TOL


@pytest.mark.parametrize("scheme,free_time,interior", [
    ("hermite-simpson", True, "points"), ("hermite-simpson", False, "hull"), ("legendre3", True, "points"),
    ("radau3", False, "hull"),
])
def test_interior_rows_have_exact_derivatives(scheme, free_time, interior):
    # the assembled Jacobian and the structured exact Hessian of the transcription with interior
    # bound rows against CasADi's AD of the plain graph, at a random point and random positions
    import casadi as ca

    import invctl_scenes.manipulator as mn
    from invctl.inversion.boundary import resolve_selection
    from invctl.inversion.cache import ocp_transcription
    from invctl.inversion.schemes import get_scheme

    md = mn.build()
    sv = servo_model(md)
    sel = resolve_selection(sv, mn.BOUNDARY["start"], mn.BOUNDARY["end"])
    ub = sv.layout.blocks["u"]
    tr = ocp_transcription(sv, sel, get_scheme(scheme), 3, relaxed=True, free_time=free_time,
                           bounded=(3,) + tuple(range(ub.start, ub.stop)), rated=(0, 1), interior=interior)
    rng = np.random.default_rng(2)
    x = 0.3 * rng.random(tr.nX)
    if free_time:
        x[tr.i_tau] = 1.2
    pts = rng.random(tr.default_points().shape)
    p = tr.parameters(np.linspace(0, 1, 4), rng.random((8, tr.nY)), md.theta_values, rng.random(14), rng.random(14),
                      W=[1.0, 2.0], rho=0.3, energy=0.2, rate=0.1, time_weight=0.5, c=2.0, mask=np.array([0, 1, 1.0]),
                      tau_ref=1.0, scale=1.3, points=pts)
    lam_g = rng.standard_normal(tr.ng)
    f, g = tr._plain
    J_ad = ca.Function("j", [tr._x, tr._p], [ca.jacobian(g, tr._x)])(x, p).full()
    J = ca.Function("j2", [tr._x, tr._p], [ca.jacobian(tr.g, tr._x)])(x, p).full()
    assert np.max(np.abs(J - J_ad)) <= 1e-12 * np.max(np.abs(J_ad))
    L = 0.8 * f + ca.dot(ca.DM(lam_g), g)
    H_ad = ca.Function("h", [tr._x, tr._p], [ca.triu(ca.hessian(L, tr._x)[0])])(x, p).full()
    H = tr._build_exact_hessian()(x, p, 0.8, lam_g).full()
    assert np.max(np.abs(H - H_ad)) <= 1e-12 * np.max(np.abs(H_ad))
    assert len(tr.path_rows) == tr.ng - tr.n_defect - tr.n_bc


def test_extremum_points_find_the_interior_extrema():
    # the positions minimum time moves its interior rows to: the roots of the derivative of each
    # interval's cubic, checked against the sign changes of u' on a fine grid
    from invctl.inversion.boundary import resolve_selection
    from invctl.inversion.cache import ocp_transcription
    from invctl.inversion.schemes import get_scheme

    md = cp.build()
    sv = servo_model(md)
    inv = invert(md, cp.reference(md), N=40)
    sel = resolve_selection(sv, inv.diagnostics["plan"]["start"], inv.diagnostics["plan"]["end"])
    iu = inv._slice("u").start
    tr = ocp_transcription(sv, sel, get_scheme(inv.scheme), inv.N, relaxed=True, bounded=(iu,), interior="points")
    pts = tr.extremum_points(inv)
    assert pts.shape == (2, inv.N)
    found = 0
    for k in range(inv.N):
        s = np.linspace(0.0, 1.0, 2001)
        t = inv.t_mesh[k] + s * (inv.t_mesh[k + 1] - inv.t_mesh[k])
        du = inv.dX(t)[iu]
        for j in np.flatnonzero(np.sign(du[1:-1]) != np.sign(du[2:])):  # interior sign changes of u'
            assert np.min(np.abs(pts[:, k] - s[j + 1])) < 2e-3
            found += 1
    assert found > 0
