"""Analysis of multibody models (003 Sect. 1.3-3, 5 steps 1-4).

Relative degree and high-gain matrix of the auxiliary ODE (10), Byrnes-Isidori
coordinates, internal dynamics by Sect. 2 and Sect. 3, linearization (37),
derivative removal (38), stable/unstable split (39), checks (A1)/(A2) and the
initial value (43)/(44) of the new reference dynamics; equilibria and operating
points along a reference; plant linearizations as python-control state-space
systems and their transmission/decoupling zeros.
"""
from .auxiliary import AuxiliarySystem, auxiliary_system, consistent_state, neighbourhood_samples
from .equilibrium import EquilibriumSolver, OperatingPoints, operating_points
from .internal import InternalDynamics, default_coordinates, design_point, internal_dynamics, xi_expression
from .linearize import A1Report, A2Report, LinearizedInternal, from_matrices, linearize_internal, load_linearization
from .relative_degree import (
    ColocationReport, RelativeDegree, colocated_check, is_position_output, position_output_gamma,
    relative_degree, schur_complement,
)
from .statespace import PlantLinearization, holding_input, internal_statespace, plant_linearization, plant_statespace
from .zeros import (
    ZeroReport, classify_statespace, classify_zeros, invariant_zeros, minimal_realization, transmission_zeros,
)

__all__ = [
    "A1Report", "A2Report", "AuxiliarySystem", "ColocationReport", "EquilibriumSolver", "InternalDynamics",
    "LinearizedInternal", "OperatingPoints", "PlantLinearization", "RelativeDegree", "ZeroReport",
    "auxiliary_system", "classify_statespace", "classify_zeros", "colocated_check", "consistent_state",
    "default_coordinates", "design_point", "from_matrices", "holding_input", "internal_dynamics",
    "internal_statespace", "invariant_zeros", "is_position_output", "linearize_internal", "load_linearization",
    "minimal_realization", "neighbourhood_samples", "operating_points", "plant_linearization", "plant_statespace",
    "position_output_gamma", "relative_degree", "schur_complement", "transmission_zeros", "xi_expression",
]
