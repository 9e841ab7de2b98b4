"""Analysis of multibody models (003 Sect. 1.3-3, 5 steps 1-4).

Relative degree and high-gain matrix of the auxiliary ODE (10), Byrnes-Isidori
coordinates, internal dynamics by Sect. 2 and Sect. 3, linearization (37),
derivative removal (38), stable/unstable split (39), checks (A1)/(A2) and the
initial value (43)/(44) of the new reference dynamics.
"""
from .auxiliary import AuxiliarySystem, auxiliary_system, consistent_state
from .equilibrium import EquilibriumSolver
from .internal import InternalDynamics, default_coordinates, design_point, internal_dynamics, xi_expression
from .linearize import A1Report, A2Report, LinearizedInternal, from_matrices, linearize_internal, load_linearization
from .relative_degree import (
    ColocationReport, RelativeDegree, colocated_check, is_position_output, position_output_gamma,
    relative_degree, schur_complement,
)

__all__ = [
    "A1Report", "A2Report", "AuxiliarySystem", "ColocationReport", "EquilibriumSolver", "InternalDynamics", "LinearizedInternal",
    "RelativeDegree", "auxiliary_system", "colocated_check", "consistent_state", "default_coordinates",
    "design_point", "from_matrices", "internal_dynamics", "is_position_output", "linearize_internal",
    "load_linearization", "position_output_gamma", "relative_degree", "schur_complement", "xi_expression",
]
