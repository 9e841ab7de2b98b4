"""The setup shared by every inversion: boundary selection and horizon (given, planned, or
shortened by bounds), mesh, equilibria at both ends, the quasi-static initial guess, and the
dichotomy check of the selection."""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import BoundaryConditionError, NoDichotomyError, OptionError, ReferenceSignalError
from .boundary import (BLOCKS, Selection, _resolve, dichotomy, explain_dichotomy, explain_no_dichotomy,
                       resolve_selection)
from .cache import compiled_key, equilibrium_solver, servo_model
from .schemes import Scheme, get_scheme
from .guess import default_mesh, quasi_static_guess
from .servo import NUMERIC_SOLVES_NX


@dataclass
class Setup:
    """Everything an inversion needs before its solve (see module doc)."""

    model: Any
    reference: Any
    servo: Any
    scheme: Scheme
    selection: Selection
    T0: float
    Tf: float
    t_mesh: np.ndarray
    mesh_kind: str
    E0: np.ndarray
    Ef: np.ndarray
    guess: np.ndarray | None
    guess_times: np.ndarray
    plan: Any = None
    dichotomy: dict | None = None
    underdetermined: bool = False
    rest: tuple = (False, False)
    timings: dict = field(default_factory=dict)

    def initial_guess(self, times) -> np.ndarray:
        """The quasi-static path interpolated at ``times`` (columns of ``X``)."""
        if self.guess is None:
            raise ValueError("this setup has no quasi-static path (prepared with ends=...)")
        return np.vstack([np.interp(times, self.guess_times, row) for row in self.guess])


def resolve_plan(model, reference, discretization, horizon):
    """``(T0, Tf, start, end, plan)``: the given parts of ``horizon`` and the rest from a plan
    (computed here, or ``horizon.plan``)."""
    plan = horizon.plan
    T0, Tf, start, end = horizon.T0, horizon.Tf, horizon.start, horizon.end
    use_cached_pieces(model, discretization)  # the plan's and the dichotomy check's linearizations
    if plan is None and (horizon.plan_options is not None or not horizon.complete):
        from .plan import plan_inversion

        plan = plan_inversion(model, reference, start=start, end=end, T0=T0, Tf=Tf,
                              formulation=discretization.formulation, omega=discretization.omega,
                              q_guess=horizon.q_guess, **dict(horizon.plan_options or {}))
    if plan is not None:
        if (plan.formulation, plan.omega) != (discretization.formulation, float(discretization.omega)):
            raise OptionError(f"the plan was made for formulation={plan.formulation!r}, omega={plan.omega}, not "
                              f"{discretization.formulation!r}, {discretization.omega}")
        T0 = plan.T0 if T0 is None else T0
        Tf = plan.Tf if Tf is None else Tf
        start = plan.start if start is None else start
        end = plan.end if end is None else end
    return T0, Tf, start, end, plan


def use_cached_pieces(model, discretization) -> None:
    """The plan's linearizations and the quasi-static path's checks through the compiled right-hand side
    Jacobian and residuals when the disk cache has them (those the transcription will load; unless
    ``compiled=False``): their SX functions are not built for the plan."""
    servo = servo_model(model, discretization.formulation, discretization.omega)
    if discretization.compiled is False or "_compiled_rhs_jac" in servo.__dict__ or (
            discretization.compiled == "auto" and servo.layout.nx > NUMERIC_SOLVES_NX):
        return
    key = compiled_key(servo, get_scheme(discretization.scheme))
    servo.use_compiled(*(servo.disk_piece(name, key) for name in ("servo_rhs_jac", "servo_residuals", "servo_Az",
                                                                  "servo_constraint_jac")))


def prepare(model, reference, discretization, horizon, *, T0=None, Tf=None, rest_start: bool = False,
            rest_end: bool = False, plan_result=None, any_count: bool = False, ends=None) -> Setup:
    """The :class:`Setup` of one inversion.

    ``T0``/``Tf`` override the horizon (pre-/post-actuation bounds); ``rest_start``/``rest_end``
    fix every entry of ``X`` at that end to the equilibrium (an inverse that starts/ends at rest
    there; over-determined for exact tracking).  ``plan_result`` is the output of
    :func:`resolve_plan` when the caller has it already.  ``any_count`` accepts selections with
    more or fewer conditions than unknowns (problems with a relaxed servo constraint).  ``ends``:
    guesses ``(E0, Ef)`` of both equilibria (a warm re-solve of a held solver): the quasi-static
    path is not computed (``Setup.guess`` is ``None``; the caller has its own initial guess).
    """
    from .plan import check_reference, graded_mesh

    t_build = time.perf_counter()
    T0p, Tfp, start, end, plan = plan_result or resolve_plan(model, reference, discretization, horizon)
    T0 = T0p if T0 is None else T0
    Tf = Tfp if Tf is None else Tf
    check_reference(reference, 3)
    if not (T0 <= reference.t0 and Tf >= reference.tf and Tf > T0):
        raise ReferenceSignalError(f"the horizon [T0, Tf] = [{T0}, {Tf}] must contain [t0, tf] = "
                                   f"[{reference.t0}, {reference.tf}] (pre- and post-actuation)")
    sch = get_scheme(discretization.scheme)
    servo = servo_model(model, discretization.formulation, discretization.omega)
    nx = servo.layout.nx
    if rest_start or rest_end or any_count:
        labels = tuple(f"{k}:{nm}" for k in BLOCKS for nm in servo.names[k])
        s0, sf = tuple(_resolve("start", start, servo)), tuple(_resolve("end", end, servo))
        sel = Selection(tuple(range(nx)) if rest_start else s0, tuple(range(nx)) if rest_end else sf, labels)
    else:
        sel = resolve_selection(servo, start, end, allow_underdetermined=horizon.allow_underdetermined)
    N = discretization.intervals
    if discretization.mesh is not None:
        t_mesh = np.array(discretization.mesh, float)
        if abs(t_mesh[0] - T0) > 1e-12 or abs(t_mesh[-1] - Tf) > 1e-12:
            raise OptionError(f"the mesh must run from T0 = {T0} to Tf = {Tf}, it runs from {t_mesh[0]} to "
                              f"{t_mesh[-1]}")
        kind = "given"
    elif plan is not None and discretization.mesh_fraction is None and {"T0", "Tf"} & set(plan.derived):
        # a pre-/post-actuation shortened by a bound keeps the grading of the tails (the inverse
        # still grows like exp(rate (t - t0)) there; it only starts from rest)
        t_mesh = graded_mesh(T0, Tf, reference.t0, reference.tf, int(N), plan.mesh_decay(sch.order))
        kind = "graded"
    else:
        frac = 0.5 if discretization.mesh_fraction is None else discretization.mesh_fraction
        t_mesh = default_mesh(T0, Tf, reference.t0, reference.tf, int(N), frac)
        kind = "piecewise uniform"
    under = len(sel.start) + len(sel.end) < nx
    square = len(sel.start) + len(sel.end) == nx
    build_s = time.perf_counter() - t_build
    # equilibria and the quasi-static guess
    t_guess = time.perf_counter()
    q0 = np.zeros(model.n) if horizon.q_guess is None else np.array(horizon.q_guess, float)
    qs_times = np.unique(np.concatenate([np.linspace(T0, Tf, 21), np.linspace(reference.t0, reference.tf, 41)]))
    qs_times = qs_times[np.r_[True, np.diff(qs_times) > 1e-9 * (Tf - T0)]]
    n = model.n
    G = None
    if ends is None:
        last = servo.quasi_static.get("entry")
        if (last is not None and last[0] is model and last[1] is reference and last[2] == (T0, Tf)
                and np.array_equal(last[3], q0)):
            G = last[4]  # mesh refinement: same model, reference and horizon
        else:
            path = None
            if plan is not None and plan.path is not None and (plan.t0, plan.tf) == (reference.t0, reference.tf):
                # the plan's path on [t0, tf] (the reference rests outside): one batched Newton solve
                pt = np.linspace(plan.t0, plan.tf, plan.path.shape[1])
                path = np.vstack([np.interp(qs_times, pt, row) for row in plan.path])
            G = quasi_static_guess(model, reference, qs_times, q0, servo=servo, path=path)
            servo.quasi_static["entry"] = (model, reference, (T0, Tf), q0, G)
        ends = (G[:, 0], G[:, -1])
    eq = equilibrium_solver(model)
    E = []
    Yends = servo.reference_samples(reference, np.array([T0, Tf]))
    for X0, k, name in ((ends[0], 0, "T0"), (ends[1], 1, "Tf")):  # the ends of the path are static
        X, _ = eq.solve(Yends[:reference.m, k], guess_w=np.concatenate([X0[:n], X0[2 * n:]]),
                        theta=model.theta_values, where=f" at {name} = {(T0, Tf)[k]}")
        E.append(X)
    dich = None
    if square and not (rest_start or rest_end):
        dich = dichotomy(servo, sel, E[0], Yends[:, :1], E[1], Yends[:, 1:], model.theta_values)
        public = {k: v for k, v in dich.items() if not k.startswith("eigenvalues")}
        if dich["neutral_internal"] and sel.end:  # all at T0: an initial value problem, no dichotomy needed
            raise NoDichotomyError(explain_no_dichotomy(dich["eigenvalues_internal_start"],
                                                        dich["eigenvalues_internal_end"], f" for {model.name!r}"),
                                   diagnostics=public)
        if dich["well_posed"] is False:
            raise BoundaryConditionError(explain_dichotomy(dich, sel), diagnostics=public)
        dich = public
    return Setup(model, reference, servo, sch, sel, float(T0), float(Tf), t_mesh, kind, E[0], E[1], G, qs_times,
                 plan, dich, under, (bool(rest_start), bool(rest_end)),
                 {"build_s": build_s, "guess_s": time.perf_counter() - t_guess})
