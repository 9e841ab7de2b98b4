"""A held stable inversion: :class:`InversionSolver` builds the problem once and re-solves it.

The model parameters ``theta``, the reference samples, the step sizes and both equilibria are
parameters of the compiled transcription (:class:`~invctl.inversion.collocation.Transcription`),
so ``solver.solve(m3=0.6)`` changes numbers, not the problem: it re-plans the horizon and the
boundary selection from the previous quasi-static path (one batched Newton solve), solves the
end equilibria from the previous ones and warm-starts the collocation from the last solution.
When the new parameters move the automatic horizon the same transcription runs on the new mesh
(``info["remapped"]``); a new boundary selection or ``N`` builds another one
(``info["rebuilt"]``), never an error.

:func:`invert` is a one-shot solver (its docstring lists the options).
"""
from __future__ import annotations

import time
from dataclasses import replace
from typing import Any

import numpy as np

from ..errors import InvctlError, ParameterError
from .collocation import start_deferred_compiles
from .options import from_keywords
from .problem import prepare, resolve_plan
from .result import Inverse


def structure_change(tr, servo, selection, N: int) -> str | None:
    """Why a held solve cannot reuse transcription ``tr`` (square or bounded) for ``(servo, selection, N)``:
    the text of ``info["rebuilt"]``, or ``None`` when those agree."""
    if tr.servo is not servo:
        return f"model structure ({tr.servo.model.name} -> {servo.model.name})"
    if (tr.selection.start, tr.selection.end) != (selection.start, selection.end):
        return f"boundary selection {tr.selection.describe()} -> {selection.describe()}"
    if tr.N != N:
        return f"N {tr.N} -> {N}"
    return None


class InversionSolver:
    """Stable inversion of ``model`` along ``reference`` (the options of
    :func:`~invctl.inversion.invert`), held for repeated solves.

    ``solve(**params)`` inverts the model with those parameter values (overrides of the model
    given here, e.g. ``solve(m3=0.6)``; ``solve()`` is the model as given), warm-started from the
    last solution unless ``warm=False``.  ``last`` is the last :class:`Inverse`; ``info`` says
    what the last solve reused, remapped or rebuilt; ``builds`` counts the transcriptions built
    or fetched (one per selection and mesh size).
    """

    def __init__(self, model, reference, *, discretization=None, solver=None, horizon=None, bounds=None,
                 objective=None, **keywords):
        self.opts = from_keywords("invert", discretization=discretization, solver=solver, horizon=horizon,
                                  bounds=bounds, objective=objective, **keywords)
        self.model, self.reference = model, reference
        self.last: Inverse | None = None
        self.info: dict = {}
        self.builds = 0
        self._setup = None
        self._tr = None
        self._x = None
        self._path = None
        self._square_last = None  # the last exact inverse (the bounded route's first step)
        self._bounded: dict = {}  # the last relaxed optimum of the bounded route (bounded.invert_bounded)
        self._mesh = None  # the last refined mesh and the (T0, t0, tf, Tf) it ran on (tol)

    @property
    def transcription(self):
        """The held transcription (``None`` before the first square solve)."""
        return self._tr

    def model_with(self, params: dict, model=None):
        """The solver's model (or ``model``) with ``params`` overriding its parameter values."""
        model = self.model if model is None else model
        if not params:
            return model
        bad = sorted(set(params) - set(model.params.names))
        if bad:
            raise ParameterError(f"InversionSolver.solve: {bad} are not parameters of model {model.name!r}; "
                                 f"its parameters are {sorted(model.params.names)}")
        return model.with_params(**{k: float(v) for k, v in params.items()})

    def solve(self, *, warm: bool = True, warm_start: Any = None, reference=None, model=None, mesh=None,
              bounds=None, objective=None, throw: bool = True, **params) -> Inverse:
        """The inverse with the parameter values ``params`` (and ``reference`` if given).

        ``model``: solve this model instead (one of the same structure reuses the transcription);
        ``mesh``: the mesh of this solve, ``T0`` and ``Tf`` follow it (as many intervals reuses the
        transcription); ``bounds``, ``objective``: this solve's (a solver built with bounds keeps its
        relaxed problem while only bound values and weights change); ``throw=False``: a failed solve returns its last iterate (``status`` FAILED,
        the error in ``diagnostics["error"]``) instead of raising, when there is one.

        Raises what :func:`~invctl.inversion.invert` raises; the solver keeps its last solution
        when a solve fails (``exc.partial`` is the failed iterate)."""
        t_all = time.perf_counter()
        opts = self.opts
        if bounds is not None or objective is not None:
            opts = from_keywords("InversionSolver.solve", discretization=opts.discretization, solver=opts.solver,
                                 horizon=opts.horizon, bounds=opts.bounds if bounds is None else bounds,
                                 objective=opts.objective if objective is None else objective)
        if mesh is not None:
            mesh = tuple(float(t) for t in np.ravel(mesh))
            opts = replace(opts, discretization=replace(opts.discretization, mesh=mesh),
                           horizon=replace(opts.horizon, T0=mesh[0], Tf=mesh[-1]))
        try:
            model = self.model_with(params, model)
            if model is not self.model and self._tr is not None:
                from .cache import share_servo

                share_servo(model, self._tr.servo)  # a rebuilt model of the same structure: the held pieces
            ref = self.reference if reference is None else reference
            ws = warm_start if warm_start is not None else (self.last if warm else None)
            if opts.bounds is not None:
                inv = self._solve_bounded(opts, model, ref, ws, reference is not None)
            elif opts.discretization.tol is not None:
                inv = self._refine(opts, model, ref, ws, reference is not None)
                self.info = dict(inv.diagnostics["solver"], route="refine", meshes=len(inv.diagnostics["meshes"]))
            else:
                inv = self._solve_square(opts, model, ref, ws, reference is not None)
        except InvctlError as exc:
            partial = getattr(exc, "partial", None)
            if throw or partial is None:
                raise
            partial.diagnostics.update(success=False, error=f"{type(exc).__name__}: {exc}")
            return partial
        finally:
            start_deferred_compiles()  # after the solve: the worker does not compete with it
        inv.diagnostics["wall_s"] = time.perf_counter() - t_all
        self.last = inv
        return inv

    # ------------------------------------------------------------ paths
    def _solve_bounded(self, opts, model, ref, ws, new_reference: bool) -> Inverse:
        """Bounds: the held exact inverse first (:meth:`_solve_square`, refined if ``tol``), then the relaxed
        problem held by :func:`~invctl.inversion.bounded.invert_bounded` (its last primal-dual optimum)."""
        from .bounded import invert_bounded

        t0 = time.perf_counter()
        plan_result = self._plan(opts, model, ref, new_reference)
        if plan_result[4] is not None and plan_result[4].path is not None:
            self._path = plan_result[4].path
        exact_info: dict = {}
        if ws is None or ws is not self.last:  # warm=False or another start: not from the last optimum
            self._bounded["last"] = None

        def exact(o, w):
            if w is not None and w is self.last:
                w = self._square_last  # the last exact inverse, not a bounded one
            inv = (self._refine(o, model, ref, w, new_reference) if o.discretization.tol is not None
                   else self._solve_square(o, model, ref, w, new_reference))
            self._square_last = inv
            exact_info.update(self.info)
            return inv

        setup_s = time.perf_counter() - t0
        inv = invert_bounded(model, ref, opts, warm_start=ws, hold=self._bounded, exact_solve=exact,
                             plan_result=plan_result)
        relaxed = not inv.diagnostics.get("tracking", {}).get("exact", False)
        src = self._bounded.get("info", {}) if relaxed else exact_info  # what the returned solution's solve did
        reused = list(src.get("reused", []))
        info: dict[str, Any] = {"held": True, "route": "bounded", "first": self.last is None, "relaxed": relaxed,
                                "reused": reused, "remapped": exact_info.get("remapped"), "rebuilt": src.get("rebuilt"),
                                "exact": exact_info or None, "setup_s": setup_s}
        self.builds += int(relaxed and "transcription" not in reused)
        inv.diagnostics["solver"] = info
        self.info = info
        return inv

    def _refine(self, opts, model, ref, ws, new_reference: bool) -> Inverse:
        """Mesh refinement to ``tol``, starting on the last refined mesh (mapped onto this solve's
        ``[T0, t0, tf, Tf]``): refined further only if its forward check misses ``tol``."""
        from .cache import servo_model
        from .refine import refine

        disc = opts.discretization
        T0, Tf, start, end, plan = self._plan(opts, model, ref, new_reference)
        if plan is not None and plan.path is not None:
            self._path = plan.path
        hz = replace(opts.horizon, T0=T0, Tf=Tf, start=start, end=end, plan=plan, plan_options=None)
        held_mesh = None
        if self._mesh is not None and disc.mesh is None:
            mesh, knots = self._mesh
            held_mesh = np.interp(mesh, knots, [T0, ref.t0, ref.tf, Tf])
            held_mesh[0], held_mesh[-1] = T0, Tf
            disc = replace(disc, mesh=tuple(held_mesh))
        o = replace(opts, horizon=hz, discretization=disc)
        servo = servo_model(model, disc.formulation, disc.omega)
        inv = refine(model, ref, o, ws, lambda oo, w: self._solve_square(oo, model, ref, w, new_reference), servo)
        self._mesh = (inv.t_mesh.copy(), np.array([inv.T0, ref.t0, ref.tf, inv.Tf]))
        inv.diagnostics["solver"] = dict(inv.diagnostics.get("solver", {}), held_mesh=held_mesh is not None)
        return inv

    def _plan(self, opts, model, ref, new_reference: bool):
        """``resolve_plan`` for ``model``, started from the last quasi-static path when only the
        parameters changed."""
        disc, hz = opts.discretization, opts.horizon
        if hz.plan is None and (hz.plan_options is not None or not hz.complete) and self._path is not None \
                and not new_reference:
            from .plan import plan_inversion

            plan = plan_inversion(model, ref, start=hz.start, end=hz.end, T0=hz.T0, Tf=hz.Tf,
                                  formulation=disc.formulation, omega=disc.omega, q_guess=hz.q_guess,
                                  path=self._path, **dict(hz.plan_options or {}))
            return resolve_plan(model, ref, disc, replace(hz, plan=plan, plan_options=None))
        return resolve_plan(model, ref, disc, hz)

    def _solve_square(self, opts, model, ref, ws, new_reference: bool) -> Inverse:
        from .cache import transcription
        from .square import solve_square

        disc = opts.discretization
        t0 = time.perf_counter()
        first = self._setup is None
        plan_result = self._plan(opts, model, ref, new_reference)
        ends = None if first or ws is None or new_reference else (self._setup.E0, self._setup.Ef)
        plan = plan_result[4]
        if ends is not None and plan is not None and plan.E0:  # the plan's equilibria: y_ref rests before t0, after tf
            ends = (np.array(plan.E0), np.array(plan.Ef))
        setup = prepare(model, ref, disc, opts.horizon, plan_result=plan_result, ends=ends)
        if setup.plan is not None and setup.plan.path is not None:
            self._path = setup.plan.path
        info: dict[str, Any] = {"held": True, "first": first, "reused": [], "remapped": None, "rebuilt": None}
        under = setup.underdetermined
        weight = opts.objective.energy if opts.objective is not None else (1.0 if under else 0.0)
        old = self._setup
        N = setup.t_mesh.size - 1
        tr = self._tr
        why = None if tr is None else (
            structure_change(tr, setup.servo, setup.selection, N)
            or (f"input-energy weight {tr.objective:g} -> {float(weight):g}" if tr.objective != float(weight) else None)
            or ("functions compiled in the background are ready" if tr.upgradable() else None))
        if tr is None or why:
            info["rebuilt"] = why
            tr = transcription(setup.servo, setup.selection, setup.scheme, N, weight,
                               compiled=disc.compiled if not under else False)
            self.builds += 1
            self._x = None
        else:
            info["reused"].append("transcription")
        if old is not None and not np.allclose([old.T0, old.Tf], [setup.T0, setup.Tf], rtol=0,
                                               atol=1e-12 * (setup.Tf - setup.T0)):
            info["remapped"] = {"T0": [old.T0, setup.T0], "Tf": [old.Tf, setup.Tf],
                                "why": "the automatic horizon moved with the parameters or the reference"}
        x0 = None
        if ws is not None and ws is self._square_last and self._x is not None and tr is self._tr \
                and np.array_equal(old.t_mesh, setup.t_mesh):
            x0 = self._x  # same mesh: the last solution vector itself
            info["reused"].append("last solution")
        elif ws is not None:
            tc = tr.collocation_times(setup.t_mesh)
            x0 = tr.pack(ws.X(setup.t_mesh), ws.X(tc) if tc.size else None)
        info["setup_s"] = time.perf_counter() - t0
        self._setup, self._tr = setup, tr
        try:
            inv = solve_square(model, ref, opts, ws if x0 is not None else None, setup=setup, tr=tr, x0=x0)
        except BaseException:
            self._x = None  # the next solve starts from ``last``, interpolated
            raise
        self._x = tr.pack(inv.X_mesh, inv.X_col)
        self._square_last = inv
        inv.diagnostics["solver"] = info
        self.info = info
        return inv


def invert(model, reference, *, discretization=None, solver=None, horizon=None, bounds=None, objective=None,
           warm_start: Inverse | None = None, **keywords) -> Inverse:
    """Stable inversion by servo constraints (003 (35)) with boundary conditions (36), optionally
    under bounds.

    Parameters
    ----------
    model : Model
        The reference model (003 (1)); ``h`` must depend on ``q`` only.
    reference : Reference
        ``y_ref``; needs three continuous derivatives (jerk-level index reduction).
    discretization : Discretization, optional
        Scheme (``hermite-simpson``, ``legendre<d>``, ``radau<d>``), ``N`` or ``mesh``, index
        reduction, mesh refinement to a forward-check ``tol``.  The default mesh has ``t0`` and
        ``tf`` as mesh points; piecewise uniform for a given horizon, graded outside
        ``[t0, tf]`` by the decay of the tails when the horizon is derived.
    solver : SolverOptions, optional
        ``backend`` (IPOPT with an exact zero Hessian, or Newton with banded LU), limits,
        ``ipopt_options`` passed verbatim, ``residual_tol``, ``progress``, ``continuation``.
    horizon : Horizon, optional
        ``T0``, ``Tf``, ``start``, ``end`` (:mod:`invctl.inversion.boundary`); what is ``None``
        is derived by :func:`invctl.inversion.plan.plan_inversion` (reported in
        ``diagnostics["plan"]``).  ``q_guess`` starts the equilibrium search.
    bounds : Bounds, optional
        Bounds on ``u``, ``u'``, ``q``, ``v`` and the pre-/post-actuation
        (:func:`invctl.inversion.bounded.invert_bounded`): exact tracking when the exact
        inverse satisfies them (then the result *is* the square solution), least-squares
        tracking with the servo constraint relaxed otherwise; ``diagnostics["bounds"]`` says
        which bounds are active, where, and the output error they cost.
    objective : Objective or float, optional
        Weights of the least-squares tracking (bounded problems).  A number is the weight of
        the input energy that selects among non-unique inverses (``allow_underdetermined``).
    warm_start : Inverse, optional
        An earlier solution (any mesh) used as initial guess.
    **keywords
        The fields of the option objects as flat keywords (``N=``, ``scheme=``, ``backend=``,
        ``T0=``, ``start=``, ``tol=``, ``max_iter=``, ...); a keyword overrides the same field
        of a given object.

    Raises
    ------
    OptionError, BoundsError
        Malformed options (``TypeError`` for unknown keywords).
    BoundaryConditionError, ReferenceSignalError, InversionFailed
        ``InversionFailed.partial`` is the last iterate as an :class:`Inverse`; subclasses name
        the cause: ``InfeasibleBoundsError`` (with the closest feasible relaxation),
        ``NoDichotomyError``, ``HorizonTooLongError``, ``ReferenceSmoothnessError``,
        ``SingularDecouplingError`` (a ``RelativeDegreeError``), ``PositionOutputError``
        (a ``ModelError``).
    """
    return InversionSolver(model, reference, discretization=discretization, solver=solver, horizon=horizon,
                           bounds=bounds, objective=objective, **keywords).solve(warm_start=warm_start)
