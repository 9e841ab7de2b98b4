"""Stable inversion by servo constraints (003 Sect. 4): the inverse model (35),
boundary conditions (36) -- chosen automatically or by hand --, collocation through
IPOPT, the :class:`Inverse` result; and, independently, through the normal form
(003 Sect. 2) for any uniform relative degree (:func:`invert_normal_form`)."""
from .boundary import EquilibriumSolver, Selection, dichotomy, resolve_selection
from .collocation import Scheme, Transcription, get_scheme
from .normal_form import NormalForm, invert_normal_form, normal_form
from .plan import InversionPlan, check_reference, plan_inversion
from .result import Inverse
from .servo import ServoModel
from .solve import interval_errors, invert, quasi_static_guess, servo_model
from .verify import forward_check

__all__ = [
    "EquilibriumSolver", "Inverse", "InversionPlan", "NormalForm", "dichotomy", "Scheme", "Selection", "ServoModel",
    "Transcription", "check_reference", "forward_check", "get_scheme", "interval_errors", "invert",
    "invert_normal_form", "normal_form", "plan_inversion", "quasi_static_guess", "resolve_selection", "servo_model",
]
