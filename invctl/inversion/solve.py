"""``invert``: stable inversion of 003 (35)-(36) by collocation and IPOPT (or Newton).

One call resolves its options (:mod:`invctl.inversion.options`), sets the problem up
(:mod:`invctl.inversion.problem`: selection, horizon, mesh, equilibria, quasi-static guess),
solves -- the square system in :mod:`invctl.inversion.square`, bounded problems in
:mod:`invctl.inversion.bounded` --,
checks the residuals and returns an :class:`Inverse`.  With ``tol`` it refines the mesh until
the forward-check output error is below ``tol`` (:mod:`invctl.inversion.refine`).
"""
from __future__ import annotations


from .backends import _TIME_LIMIT, IPOPT_DEFAULTS, IPOPT_SQUARE_DEFAULTS, _newton, _Progress, _progress_of  # noqa: F401
from .cache import _EQ_CACHE, _OCP_CACHE, _QS_LAST, _SERVO_CACHE, _TRANS_CACHE  # noqa: F401  (public handles)
from .cache import compiled_key as _compiled_key  # noqa: F401
from .cache import equilibrium_solver as _equilibrium_solver  # noqa: F401
from .cache import model_key, servo_model, transcription  # noqa: F401
from .guess import _split, default_mesh, quasi_static_guess  # noqa: F401
from .refine import interval_errors, refine  # noqa: F401
from .result import Inverse
from .square import _continuation, _solve, make_inverse, residuals, solve_square  # noqa: F401  (their former home)


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
    from .solver import InversionSolver

    return InversionSolver(model, reference, discretization=discretization, solver=solver, horizon=horizon,
                           bounds=bounds, objective=objective, **keywords).solve(warm_start=warm_start)


# names kept for callers of the former single module
_make_inverse = make_inverse
_residuals = residuals
