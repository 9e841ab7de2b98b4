"""Controllers: funnel (003 Sect. 5) with its automatic design, switched motion/force (002), PD+/pre-loading (000).

Import from the submodules; the funnel design entry points are re-exported here."""
from .funnel_design import DesignRules, FunnelDesign, design_funnel_feedback, reference_time_scale
from .new_output import A1Margin, NewOutput, a1_margin_along, controllability_indices, design_new_output

__all__ = ["A1Margin", "DesignRules", "FunnelDesign", "NewOutput", "a1_margin_along", "controllability_indices",
           "design_funnel_feedback", "design_new_output", "reference_time_scale"]
