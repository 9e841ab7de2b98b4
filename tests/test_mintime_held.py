"""The held minimum-time solver (:class:`~invctl.inversion.mintime.MinimumTimeSolver`) and the warm-started
extrema round of :func:`~invctl.inversion.mintime.minimum_time`."""
from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import invctl.inversion.mintime as mt
import invctl.inversion.square as square
import invctl_scenes.cartpole as cp
from invctl.errors import OptionError
from invctl.inversion import Bounds
from invctl.inversion.bounded import _limits, solve_scaled
from invctl.inversion.options import SolverOptions

N = 40  # small: the cart-pole minimum time, |F| <= 1 N


@pytest.fixture(scope="module")
def cart():
    md = cp.build()
    ref = cp.reference(md)
    return md, ref, mt.minimum_time(md, ref, bounds=Bounds(u=1.0), N=N)


def test_held_resolve_equals_a_fresh_solve_and_builds_nothing(cart, monkeypatch):
    # the re-solve starts at the last optimum with its multipliers and interior points: the same NLP as the fresh
    # solve's last round, so the same optimum to IPOPT's tolerance (tol 1e-10; measured 3e-15 in tau, 6e-15 in X),
    # in a few iterations (4 measured; from the primal point alone IPOPT needs 14 at N = 100), and nothing is built
    md, ref, fresh = cart
    held = mt.MinimumTimeSolver(md, ref, bounds=Bounds(u=1.0), N=N)
    first = held.solve()
    assert not first.diagnostics["held"]
    built = []
    monkeypatch.setattr(ca, "nlpsol", lambda *a, **k: built.append("nlpsol"))
    for name in ("prepare", "resolve_plan"):
        monkeypatch.setattr(mt, name, lambda *a, _n=name, **k: built.append(_n))
    monkeypatch.setattr(square, "solve_square", lambda *a, **k: built.append("solve_square"))
    servo = held._held["last"]["setup"].servo
    kept = list(servo.ocp_transcriptions.values())
    again = held.solve()
    assert built == [] and list(servo.ocp_transcriptions.values()) == kept
    d = again.diagnostics
    assert d["held"] and d["bound_rounds"] == 0 and d["iterations"] <= 6
    assert d["free_time"]["duration"] == pytest.approx(fresh.diagnostics["free_time"]["duration"], rel=1e-9)
    assert np.max(np.abs(again.X_mesh - fresh.X_mesh)) < 1e-8


def test_held_resolve_honours_a_new_bound(cart):
    # |F| <= 1.5 N after 1 N: the same optimum as a fresh solve (rel. 1e-9 in tau; measured 6e-13), and the
    # returned interpolant touches the new bound (its peak 1.5 to 1e-8), which the old optimum exceeds nowhere
    md, ref, _fresh = cart
    held = mt.MinimumTimeSolver(md, ref, bounds=Bounds(u=1.0), N=N)
    held.solve()
    inv = held.solve(bounds=Bounds(u=1.5))
    fresh = mt.minimum_time(md, ref, bounds=Bounds(u=1.5), N=N)
    tau = inv.diagnostics["free_time"]["duration"]
    assert tau == pytest.approx(fresh.diagnostics["free_time"]["duration"], rel=1e-9)
    assert np.max(np.abs(inv.X_mesh - fresh.X_mesh)) < 1e-8
    assert tau < 0.9 * _fresh.diagnostics["free_time"]["duration"]  # a looser bound: a shorter move
    t = np.linspace(inv.T0, inv.Tf, 40001)
    k = int(np.argmax(np.abs(inv.u(t)[0])))
    peak = np.max(np.abs(inv.u(np.linspace(t[max(k - 2, 0)], t[min(k + 2, t.size - 1)], 10001))))
    assert peak == pytest.approx(1.5, abs=1e-8)


def test_held_solver_names_what_cannot_change(cart):
    md, ref, _fresh = cart
    held = mt.MinimumTimeSolver(md, ref, bounds=Bounds(u=1.0), N=N)
    with pytest.raises(OptionError, match="N cannot change between solves"):
        held.solve(N=20)
    with pytest.raises(OptionError, match="tol"):
        mt.MinimumTimeSolver(md, ref, bounds=Bounds(u=1.0), N=N, tol=1e-3).solve()


def test_warm_round_falls_back_to_a_cold_solve(cart):
    # multipliers of the wrong sign and size make the warm start fail; solve_scaled solves again from the primal
    # point alone and reaches the same optimum (tau to 1e-9), counting the iterations of both solves
    md, ref, fresh = cart
    held = mt.MinimumTimeSolver(md, ref, bounds=Bounds(u=1.0), N=N)
    held.solve()
    last = held._held["last"]
    tr, setup = last["tr"], last["setup"]
    rb = Bounds(u=1.0).resolve(tr.servo)
    tau_ref = ref.tf - ref.t0
    lim = _limits(tr, rb, (0.02 * tau_ref, 50 * tau_ref))
    t_mesh = setup.t_mesh
    mask = ((t_mesh[:-1] >= ref.t0 - 1e-12) & (t_mesh[1:] <= ref.tf + 1e-12)).astype(float)
    Y = tr.servo.reference_samples(ref, tr.sample_times(t_mesh))

    def params(scale):
        return tr.parameters(t_mesh, Y, md.theta_values, setup.E0, setup.Ef, time_weight=1.0, c=1.0, mask=mask,
                             tau_ref=tau_ref, scale=scale, points=last["points"])

    slv = SolverOptions(max_iter=3)  # the warm start cannot recover from these multipliers in 3 iterations ...
    bad = (-1e6 * np.sign(np.array(last["lam_x"])) - 1e3, 1e6 * np.ones(tr.ng))
    _sol, st, _s = solve_scaled(tr, slv, last["x"], params, lim, hessian="exact", scale=1.0, warm=bad)
    assert not st["success"] and st["iterations"] == 6  # ... nor the cold one: both counted
    sol, st, _s = solve_scaled(tr, SolverOptions(), last["x"], params, lim, hessian="exact", scale=1.0, warm=bad)
    assert st["success"]
    assert float(np.array(sol["x"]).ravel()[tr.i_tau]) == pytest.approx(
        fresh.diagnostics["free_time"]["duration"], rel=1e-9)
