"""Symbolic multibody models in the form 003 (1) with unilateral gaps."""
from .multibody import Gap, Model
from .params import ParamSet, parse_assignments, resolve_params
from .region import OperatingRegion

__all__ = ["Gap", "Model", "OperatingRegion", "ParamSet", "parse_assignments", "resolve_params"]
