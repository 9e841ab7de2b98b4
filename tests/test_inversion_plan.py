"""Automatic setup of the stable inversion (invctl.inversion.plan): selection, horizon, specific errors."""
import json
import math

import casadi as ca
import numpy as np
import pytest

import invctl_scenes.cartpole as cp
import invctl_scenes.manipulator as scene
import invctl_scenes.two_link_arm as arm
from invctl.errors import (BoundaryConditionError, HorizonTooLongError, ModelError, NoDichotomyError,
                           PositionOutputError, ReferenceSignalError, ReferenceSmoothnessError, RelativeDegreeError,
                           SingularDecouplingError)
from invctl.inversion import dichotomy, invert, resolve_selection, servo_model
from invctl.inversion.plan import check_reference, choose_rows, graded_mesh, plan_inversion
from invctl.inversion.guess import default_mesh
from invctl.model import Model, ParamSet
from invctl.reference import Reference, poly9_timing_law
from invctl.testing import assert_inverts

TOL = 1e-8  # the plan's default truncation tolerance (relative tails)


def cartpole_variant(output="sin", c=1.0, **overrides):
    """The cart-pole of invctl_scenes/cartpole.py with another output: ``x + c l sin(theta)``,
    a constant, or the cart velocity."""
    P = ParamSet(list(cp.PARAMS))
    mc, mp, l, I, g, D = (P[k] for k in cp.PARAMS)
    q, v = ca.SX.sym("q", 2), ca.SX.sym("v", 2)
    x, th = q[0], q[1]
    com_v = ca.vertcat(v[0] + l * ca.cos(th) * v[1], -l * ca.sin(th) * v[1])
    T = 0.5 * mc * v[0] ** 2 + 0.5 * mp * ca.sumsqr(com_v) + 0.5 * I * v[1] ** 2
    h = {"sin": x + c * l * ca.sin(th), "const": ca.SX(0.3), "velocity": v[0]}[output]
    return Model.from_lagrangian(f"cartpole_{output}_{c:g}", q, v, P, cp.PARAMS, T=T, V=mp * g * l * ca.cos(th),
                                 Q=ca.vertcat(0, -D * v[1]), B=ca.DM([[1], [0]]), h=h, derived=cp.DERIVED,
                                 region=cp.REGION, overrides=overrides, q_names=["x", "theta"], u_names=["F"],
                                 y_names=["y"])


@pytest.fixture(scope="module")
def manip():
    md = scene.build()
    return md, scene.reference(md), scene.initial_configuration(md)


# ----------------------------------------------------------------------------- rates and horizon
@pytest.mark.parametrize("damping", [0.0, 0.05])
def test_plan_rates_match_cartpole_closed_form(damping):
    md = cp.build(D=damping)
    plan = plan_inversion(md, cp.reference(md))
    lo, hi = cp.zero_dynamics_eigenvalues(md)  # closed form of the inverted pendulum (cart held)
    for ev in (plan.eigenvalues_start, plan.eigenvalues_end):
        ev = np.sort(np.real_if_close(np.array(ev)))
        assert np.max(np.abs(ev - [lo, hi])) < 1e-8
    assert abs(plan.rate_pre - hi) < 1e-8 and abs(plan.rate_post + lo) < 1e-8
    # one real mode per side: the tail is exactly exp(-rate span) (factor 1), so the span is
    # ln(1/tol)/rate up to the bisection's relative 1e-6
    assert plan.kappa_pre == pytest.approx(1.0, abs=1e-9) and plan.kappa_post == pytest.approx(1.0, abs=1e-9)
    assert plan.pre_actuation == pytest.approx(math.log(1 / TOL) / hi, rel=2e-6)
    assert plan.post_actuation == pytest.approx(math.log(1 / TOL) / -lo, rel=2e-6)
    assert plan.drift_rate == pytest.approx(10.0, rel=1e-3)  # Baumgarte omega (triple pole, perturbed 1e-4)


def test_minimum_phase_arm_has_no_pre_actuation():
    md = arm.build()
    ref = arm.reference(md)
    plan = plan_inversion(md, ref)
    assert plan.T0 == ref.t0 and plan.rate_pre is None and plan.end == {}
    assert sum(len(v) for v in plan.start.values()) == servo_model(md).layout.nx
    # internal eigenvalues = the damped pendulum of link 2 with q1 held (closed form), at both ends
    for ev, t in ((plan.eigenvalues_start, ref.t0), (plan.eigenvalues_end, ref.tf)):
        closed = arm.zero_dynamics_eigenvalues(md, ref(t).ravel()[0])
        assert np.max(np.abs(np.sort_complex(np.array(ev)) - np.sort_complex(closed))) < 1e-8
    # complex pair: the non-normal 2x2 block has a factor > 1, so the span exceeds ln(1/tol)/rate
    rate = -np.real(plan.eigenvalues_end[0])
    assert plan.rate_post == pytest.approx(rate, rel=1e-10)
    assert plan.kappa_post > 1 and plan.tail_post <= TOL * (1 + 1e-6)
    assert plan.post_actuation > math.log(1 / TOL) / rate  # the factor lengthens it


def test_horizon_cap_names_the_slow_rate():
    md = cp.build(g=1e-3)  # pendulum almost without gravity: zero dynamics rate 0.0384/s, spans 476 s
    rate = cp.zero_dynamics_eigenvalues(md)[1]
    with pytest.raises(HorizonTooLongError, match=r"max_horizon") as exc:
        plan_inversion(md, cp.reference(md))
    assert f"{rate:.4g}/s" in str(exc.value) and "tol" in str(exc.value)
    assert isinstance(exc.value, BoundaryConditionError)
    plan = plan_inversion(md, cp.reference(md), max_horizon=2000.0)  # the cap is overridable
    assert plan.pre_actuation == pytest.approx(math.log(1 / TOL) / rate, rel=2e-6)


# ----------------------------------------------------------------------------- inversions without setup
@pytest.mark.parametrize("build,reference,tol", [
    # forward checks measured at HS N = 200: cart-pole 1.0e-7, arm 2.4e-7 (tolerance 10x / 4x above)
    (cp.build, cp.reference, 1e-6),
    (arm.build, arm.reference, 1e-6),
])
def test_invert_without_selection_or_horizon(build, reference, tol):
    md = build()
    ref = reference(md)
    inv = invert(md, ref, backend="newton")
    assert_inverts(md, inv, ref, tol=tol)
    d = inv.diagnostics
    plan = d["plan"]
    assert set(plan["derived"]) == {"start", "end", "T0", "Tf"}
    assert plan["T0"] == inv.T0 and plan["Tf"] == inv.Tf and d["mesh"] == "graded"
    assert d["dichotomy"]["well_posed"] is True  # the independent check of invert agrees with the choice
    json.dumps(plan)
    assert "selection chosen at T0" in plan["describe"]
    assert ref.t0 in inv.t_mesh and ref.tf in inv.t_mesh


def test_manipulator_auto_setup_matches_hand_selection(manip):
    md, ref, q0 = manip
    # fine Legendre-4 meshes (forward-check error ~1e-11) so that the difference is the truncation:
    # the automatic horizon leaves tails <= tol = 1e-8 (relative), the hand one [-1, 2] smaller ones;
    # tolerance 10 tol max|u| (measured 1.0e-9 max|u|)
    auto = invert(md, ref, q_guess=q0, scheme="legendre4", N=300, backend="newton")
    hand = invert(md, ref, q_guess=q0, backend="newton", **{**scene.INVERSION, "scheme": "legendre4", "N": 300})
    t = np.linspace(ref.t0, ref.tf, 2001)
    umax = np.max(np.abs(hand.u(t)))
    assert np.max(np.abs(auto.u(t) - hand.u(t))) < 10 * TOL * umax
    assert hand.diagnostics["plan"] is None and hand.diagnostics["mesh"] == "piecewise uniform"
    plan = auto.diagnostics["plan"]
    assert -1.0 < plan["T0"] < 0.0 and 1.0 < plan["Tf"] < 2.0
    # the hand selection, evaluated by the same criterion, is worse conditioned than the chosen one
    given = plan_inversion(md, ref, q_guess=q0, **{k: scene.INVERSION[k] for k in ("start", "end", "T0", "Tf")})
    assert given.derived == () and given.start == plan_inversion(md, ref, q_guess=q0, **{
        k: scene.INVERSION[k] for k in ("start", "end")}).start
    assert plan["conditioning_start"] > given.conditioning_start and plan["conditioning_end"] > given.conditioning_end


def test_same_mesh_hand_and_auto_selection_agree(manip):
    # identical meshes and horizon: only the boundary rows differ, each a well-posed selection,
    # so the solutions differ by the truncation sensitivities times tails <= 1e-8 (measured 1.6e-9 max|u|)
    md, ref, q0 = manip
    auto = invert(md, ref, q_guess=q0, backend="newton", N=160)
    hand = invert(md, ref, q_guess=q0, backend="newton", mesh=auto.t_mesh, T0=auto.T0, Tf=auto.Tf,
                  start=scene.BOUNDARY["start"], end=scene.BOUNDARY["end"])
    t = np.linspace(ref.t0, ref.tf, 1001)
    assert np.max(np.abs(auto.u(t) - hand.u(t))) < 10 * TOL * np.max(np.abs(hand.u(t)))
    assert_inverts(md, auto, ref, tol=1e-6)  # graded mesh: measured 3.0e-8 at N = 160 (hand setup: 1.1e-7)


@pytest.mark.parametrize("which", ["manipulator", "cartpole"])
def test_longer_horizon_changes_little(manip, which):
    if which == "manipulator":
        md, ref, q0 = manip
    else:
        md, q0 = cp.build(), None
        ref = cp.reference(md)
    a = invert(md, ref, q_guess=q0, backend="newton")
    pre, post = a.t0 - a.T0, a.Tf - a.tf
    T0, Tf = a.t0 - 3 * pre, a.tf + 3 * post
    # the same mesh on the automatic horizon plus 20 intervals on each extension: the difference
    # is the truncation alone (measured on [t0, tf]: 9e-11 / 1e-15 max|u|; whole horizon 5e-9 / 8e-10)
    mesh = np.concatenate([np.linspace(T0, a.T0, 21)[:-1], a.t_mesh, np.linspace(a.Tf, Tf, 21)[1:]])
    b = invert(md, ref, q_guess=q0, backend="newton", T0=T0, Tf=Tf, mesh=mesh)
    assert b.diagnostics["plan"]["start"] == a.diagnostics["plan"]["start"]
    assert b.diagnostics["plan"]["tail_pre"] < 1e-20
    t = np.linspace(a.T0, a.Tf, 3001)
    umax = np.max(np.abs(a.u(t)))
    assert np.max(np.abs(a.u(t) - b.u(t))) < 10 * TOL * umax


def test_partial_overrides(manip):
    md, ref, q0 = manip
    plan = plan_inversion(md, ref, q_guess=q0, start=scene.BOUNDARY["start"], end=scene.BOUNDARY["end"])
    assert plan.derived == ("T0", "Tf") and plan.end == {"q": ["gamma"]}
    assert "selection given at T0" in plan.describe()
    plan = plan_inversion(md, ref, q_guess=q0, T0=-1.0)
    assert plan.T0 == -1.0 and plan.tail_pre == pytest.approx(math.exp(-plan.rate_pre), rel=1e-9)
    with pytest.raises(BoundaryConditionError, match="1 modes to fix at Tf"):
        plan_inversion(md, ref, q_guess=q0, end={"q": ["gamma"], "u": "all"})
    with pytest.raises(ValueError, match="either plan"):
        invert(md, ref, plan=plan, plan_options={"tol": 1e-6})
    # everything given: a plan made only for the report changes nothing (same mesh and solution)
    a = invert(md, ref, q_guess=q0, backend="newton", **{**scene.INVERSION, "N": 40})
    b = invert(md, ref, q_guess=q0, backend="newton", plan_options={}, **{**scene.INVERSION, "N": 40})
    assert b.diagnostics["plan"]["derived"] == [] and b.diagnostics["mesh"] == "piecewise uniform"
    np.testing.assert_allclose(a.X_mesh, b.X_mesh, rtol=0, atol=1e-9)  # Newton tolerance 1e-10


def test_zero_length_post_actuation_solves():
    md = cp.build()
    ref = cp.reference(md)
    inv = invert(md, ref, Tf=ref.tf, backend="newton", N=120)
    assert inv.Tf == ref.tf and inv.t_mesh[-1] == ref.tf and inv.diagnostics["success"]
    assert inv.diagnostics["plan"]["tail_post"] == pytest.approx(1.0)  # nothing of the tail kept
    assert inv.diagnostics["residuals"]["position"] < 1e-5


def test_no_internal_dynamics_gives_the_transition_as_horizon():
    # fully actuated arm, tip output (m = n = 2): no internal dynamics, both spans zero, all at T0
    md = arm.build_tip()
    t = ca.SX.sym("t")
    q1, q2 = 0.3, 0.7  # away from the singular stretched arm
    p0 = [0.5 * math.sin(q1) + 0.4 * math.sin(q1 + q2), -0.5 * math.cos(q1) - 0.4 * math.cos(q1 + q2)]
    ref = Reference(t, ca.vertcat(p0[0] - 0.1 * poly9_timing_law(t, 0, 1), p0[1]), 0, 1, smoothness=4, name="tip")
    inv = invert(md, ref, q_guess=np.array([q1, q2]), backend="newton", N=60)
    plan = inv.diagnostics["plan"]
    assert (inv.T0, inv.Tf) == (0.0, 1.0) and plan["eigenvalues_start"] == [] and plan["end"] == {}
    assert_inverts(md, inv, ref, tol=1e-6)  # measured 2.3e-8


# ----------------------------------------------------------------------------- meshes
def test_graded_mesh_is_uniform_in_the_stretched_coordinate():
    b0, bf = 24.4 / 5, 19.6 / 5
    t = graded_mesh(-0.75, 1.94, 0.0, 1.0, 200, (b0, bf))
    assert t.size == 201 and t[0] == -0.75 and t[-1] == 1.94 and 0.0 in t and 1.0 in t
    assert np.all(np.diff(t) > 0)
    pre, mid, post = t[t <= 0], t[(t >= 0) & (t <= 1)], t[t >= 1]
    for part, b, ref in ((pre, b0, 0.0), (post, bf, 1.0)):
        s = -np.expm1(-b * np.abs(part - ref)) / b
        assert np.ptp(np.diff(np.sort(s))) < 1e-12
    assert np.ptp(np.diff(mid)) < 1e-12
    # steps: equal to the middle's at the transition (within one interval's rounding), growing outwards
    h_mid = np.diff(mid)[0]
    assert 0.5 * h_mid < np.diff(pre)[-1] < 2 * h_mid and np.diff(pre)[0] > 20 * h_mid
    # zero-length spans: [T0, Tf] = [t0, tf] and one-sided
    for T0, Tf in ((0.0, 1.0), (0.0, 3.0), (-2.0, 1.0)):
        for mesh in (graded_mesh(T0, Tf, 0.0, 1.0, 50, (1.0, 1.0)), default_mesh(T0, Tf, 0.0, 1.0, 50)):
            assert mesh.size == 51 and mesh[0] == T0 and mesh[-1] == Tf and 0.0 in mesh and 1.0 in mesh
            assert np.all(np.diff(mesh) > 0)


# ----------------------------------------------------------------------------- the selection criterion
def test_choose_rows_is_optimal_and_prefers_blind_rows(monkeypatch):
    import itertools

    rng = np.random.default_rng(1)
    for nx, k in ((6, 2), (7, 5), (8, 4)):
        Z = np.linalg.qr(rng.standard_normal((nx, k)))[0]
        W = np.linalg.qr(rng.standard_normal((nx, 1)))[0]
        rows, sig, sens = choose_rows(Z, W)
        best = max(np.linalg.svd(Z[list(S)], compute_uv=False)[-1] for S in itertools.combinations(range(nx), k))
        assert sig >= 0.5 * best - 1e-12  # within the stated factor of the optimum
        assert sig == pytest.approx(np.linalg.svd(Z[list(rows)], compute_uv=False)[-1], rel=1e-10)
        assert sens == pytest.approx(np.linalg.norm(np.linalg.solve(Z[list(rows)], W[list(rows)]), 2), rel=1e-10)
    # many candidates: column-pivoted QR instead of enumeration (seeded case, brute force as reference;
    # pivoted QR has no tight worst-case bound; here it finds the optimum)
    import invctl.inversion.plan as plan_mod

    Z = np.linalg.qr(rng.standard_normal((10, 5)))[0]
    best = max(np.linalg.svd(Z[list(S)], compute_uv=False)[-1] for S in itertools.combinations(range(10), 5))
    monkeypatch.setattr(plan_mod, "MAX_ENUMERATION", 10)
    rows, sig, _ = choose_rows(Z, np.zeros((10, 0)))
    assert len(set(rows)) == 5 and sig == pytest.approx(np.linalg.svd(Z[list(rows)], compute_uv=False)[-1])
    assert sig > 0.5 * best
    monkeypatch.undo()
    # rows 0 and 1 fix Z equally well; row 1 also sees the wrong-end mode W, row 0 is blind to it
    Z = np.array([[1.0], [1.0], [0.0]]) / math.sqrt(2)
    W = np.array([[0.0], [1.0], [0.0]])
    assert choose_rows(Z, W)[0] == (0,) and choose_rows(Z, W)[2] == 0.0


def test_auto_selection_is_well_posed_by_the_dichotomy_check(manip):
    md, ref, q0 = manip
    plan = plan_inversion(md, ref, q_guess=q0)
    sv = servo_model(md)
    sel = resolve_selection(sv, plan.start, plan.end)
    Y = sv.reference_samples(ref, np.array([ref.t0, ref.tf]))
    d = dichotomy(sv, sel, np.array(plan.E0), Y[:, :1], np.array(plan.Ef), Y[:, 1:], md.theta_values)
    assert d["well_posed"] is True and (d["decaying"], d["growing"]) == (13, 1)


# ----------------------------------------------------------------------------- bad setups
def test_flat_output_singular_decoupling():
    # homogeneous pole (I = m l^2/3): x + (4/3) l sin(theta) is the flat output (centre of
    # percussion); h' M^-1 B = 0 at theta = 0, relative degree 4
    md = cartpole_variant("sin", 4.0 / 3.0)
    ref = cp.reference(md)
    for kw in ({}, {"T0": -3.0, "Tf": 5.0, "start": {"q": "all", "v": "all"}, "end": {"u": "all"}}):
        with pytest.raises(SingularDecouplingError, match="relative degree") as exc:
            invert(md, ref, backend="newton", **kw)
        assert isinstance(exc.value, RelativeDegreeError) and "flat output" in str(exc.value)
        assert exc.value.diagnostics["rcond"] < 1e-10


def test_neutral_zero_dynamics_no_dichotomy():
    # c = 2 l: (J - c m l) theta'' = m g l theta with J - 2 m l^2 < 0: eigenvalues +-i sqrt(1.5 g / l)
    md = cartpole_variant("sin", 2.0)
    ref = cp.reference(md)
    w = math.sqrt(1.5 * 9.81 / 0.5)
    with pytest.raises(NoDichotomyError, match="imaginary axis") as exc:
        plan_inversion(md, ref)
    assert "neutral: 2" in str(exc.value) and f"{w:.4g}i" in str(exc.value)
    ev = np.array(exc.value.diagnostics["eigenvalues_internal_start"])
    assert np.max(np.abs(np.abs(ev) - w)) < 1e-8
    # a hand selection with conditions at Tf does not get the generic "refine the mesh" either
    with pytest.raises(NoDichotomyError, match="no exponential dichotomy"):
        invert(md, ref, backend="newton", T0=-3.0, Tf=5.0, start={"q": "all", "v": ["x"], "u": "all"},
               end={"v": ["theta"]})
    # the initial value problem the message offers (everything at T0 = t0) needs no dichotomy: the
    # pendulum keeps oscillating after tf, the output is tracked (forward check measured 8e-7)
    assert "initial value problem" in str(exc.value)
    inv = invert(md, ref, T0=0.0, Tf=3.0, start={"q": "all", "v": "all", "u": "all"}, end={}, backend="newton")
    assert inv.diagnostics["dichotomy"]["neutral_internal"] == 2
    assert_inverts(md, inv, ref, tol=1e-5)


@pytest.mark.parametrize("output,words", [("const", "does not depend on q"), ("velocity", "depends on the velocities")])
def test_output_not_a_function_of_q(output, words):
    md = cartpole_variant(output)
    with pytest.raises(PositionOutputError, match=words) as exc:
        servo_model(md)  # before any equilibrium or solve
    assert isinstance(exc.value, ModelError) and "'y'" in str(exc.value)
    with pytest.raises(PositionOutputError):
        invert(md, cp.reference(cartpole_variant()), backend="newton")


def _ref(expr_of_s, smoothness=4, name="y_ref"):
    t = ca.SX.sym("t")
    s = t / 2.0
    expr = 0.5 * ca.if_else(s <= 0, 0, ca.if_else(s >= 1, 1, expr_of_s(s)))
    return Reference(t, expr, 0.0, 2.0, smoothness=smoothness, name=name)


def test_reference_smoothness_declared_and_measured():
    md = cp.build()
    with pytest.raises(ReferenceSmoothnessError, match=r"W\^\{3,inf\}"):
        invert(md, _ref(lambda s: 3 * s**2 - 2 * s**3, smoothness=1), backend="newton")
    # declared C^4 but glued with lower-order polynomials: y'' jumps (cubic), y''' jumps (quintic)
    for poly, what, size in ((lambda s: 3 * s**2 - 2 * s**3, "y_ref''", 0.75),
                             (lambda s: 10 * s**3 - 15 * s**4 + 6 * s**5, "y_ref'''", 3.75)):
        with pytest.raises(ReferenceSmoothnessError, match=f"{what} jumps") as exc:
            invert(md, _ref(poly), backend="newton")
        jumps = exc.value.diagnostics["jumps"]
        # closed form: 0.5 * p''(0) / 2^2 = 0.75 for the cubic, 0.5 * p'''(0) / 2^3 = 3.75 for the quintic,
        # at both glue points
        assert {round(j["t"], 6) for j in jumps if j["order"] == len(what) - 5} == {0.0, 2.0}
        assert max(j["size"] for j in jumps) == pytest.approx(size, rel=1e-6)
        assert isinstance(exc.value, ReferenceSignalError)
    # a jump of y''' by 0.06 inside the transition (1 % of max |y'''|)
    t = ca.SX.sym("t")
    inside = Reference(t, 0.5 * poly9_timing_law(t, 0, 2) + ca.if_else(t > 1.3, 0.01 * (t - 1.3) ** 3, 0), 0, 2,
                       smoothness=4, name="bumped")
    with pytest.raises(ReferenceSmoothnessError, match=r"y_ref''' jumps by 0.06 at t = 1.3"):
        check_reference(inside)
    # smooth references pass (also a fast one)
    check_reference(cp.reference(md))
    check_reference(Reference(t, 0.5 * poly9_timing_law(t, 0, 2) * (1 + 0.1 * ca.sin(30 * t)), 0, 2, smoothness=4))


def test_describe_shows_imaginary_parts_above_round_off_only():
    """Internal eigenvalues with |imag| <= 1e-12 are real up to round-off and shown as real numbers."""
    from invctl.inversion.plan import InversionPlan

    plan = InversionPlan(
        start={}, end={}, T0=-1.0, Tf=2.0, t0=0.0, tf=1.0, eigenvalues_start=(1.5 + 1e-12j, -2.0 + 2e-12j),
        eigenvalues_end=(), rate_pre=None, rate_post=None, tail_pre=0.0, tail_post=0.0, kappa_pre=1.0,
        kappa_post=1.0, conditioning_start=1.0, conditioning_end=1.0, sensitivity_start=0.0, sensitivity_end=0.0,
        pins_start={}, pins_end={}, drift_rate=None, scale={}, tol=1e-8, max_horizon=10.0, formulation="sect3",
        omega=0.0, derived=())
    assert "internal eigenvalues: +1.5, -2+2e-12i at the start, none at the end" in plan.describe()


def test_graded_mesh_without_decay_is_uniform_on_each_span():
    """decay = (0, 0): the spans outside [t0, tf] are at rest and get one interval each, the transition the
    other 28 uniform ones: [-1, linspace(0, 1, 29), 2]."""
    t = graded_mesh(-1.0, 2.0, 0.0, 1.0, 30)
    np.testing.assert_allclose(t, np.r_[-1.0, np.linspace(0.0, 1.0, 29), 2.0], atol=1e-15)


def test_objective_output_weights_per_output():
    """One weight per output is used as given; a tuple of the wrong length names the outputs."""
    from types import SimpleNamespace

    from invctl.errors import OptionError
    from invctl.inversion.options import Objective

    model = SimpleNamespace(m=2, y_names=("y1", "y2"))
    np.testing.assert_array_equal(Objective(output=(1.0, 3.0)).output_weights(model), [1.0, 3.0])
    with pytest.raises(OptionError, match=r"1 output weights for 2 outputs \['y1', 'y2'\]"):
        Objective(output=(1.0,)).output_weights(model)
