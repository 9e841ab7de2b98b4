"""Stable inversion by servo constraints (003 Sect. 4): the inverse model (35),
boundary conditions (36) -- chosen automatically or by hand --, collocation through
IPOPT, the :class:`Inverse` result; bounded inversion and free transition time as optimal
control problems on the same transcription; and, independently, through the normal form
(003 Sect. 2) for any uniform relative degree (:func:`invert_normal_form`)."""
from ..analysis.equilibrium import EquilibriumSolver
from .boundary import Selection, dichotomy, resolve_selection
from .collocation import Transcription
from .schemes import Scheme, get_scheme
from .normal_form import NormalForm, invert_normal_form, normal_form
from .options import Bounds, Discretization, Horizon, Objective, SolverOptions
from .plan import InversionPlan, check_reference, plan_inversion
from .result import Inverse
from .servo import ServoModel
from .cache import servo_model
from .guess import quasi_static_guess
from .refine import interval_errors
from .solver import InversionSolver, invert
from .mintime import MinimumTimeSolver, minimum_time, retime
from .verify import forward_check

__all__ = [
    "Bounds", "Discretization", "EquilibriumSolver", "Horizon", "Inverse", "InversionPlan", "InversionSolver", "MinimumTimeSolver",
    "NormalForm", "Objective",
    "dichotomy", "Scheme", "Selection", "ServoModel", "SolverOptions", "Transcription", "check_reference",
    "forward_check", "get_scheme", "interval_errors", "invert", "invert_normal_form", "minimum_time", "normal_form",
    "plan_inversion", "quasi_static_guess", "resolve_selection", "retime", "servo_model",
]
