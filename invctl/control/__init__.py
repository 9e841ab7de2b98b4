"""Controllers: funnel (003 Sect. 5) with its automatic design, switched motion/force (002), PD+/pre-loading (000).

Import from the submodules.  The funnel-design entry points are also available here, loaded on first
access (so that a scene using only, e.g., the switched controller never imports the analysis layer).
"""
from importlib import import_module

_LAZY = {
    "DesignRules": "funnel_design", "FunnelDesign": "funnel_design", "design_funnel_feedback": "funnel_design",
    "reference_time_scale": "funnel_design", "NMPFunnelController": "funnel_nmp", "A1Margin": "new_output",
    "NewOutput": "new_output", "a1_margin_along": "new_output", "controllability_indices": "new_output",
    "design_new_output": "new_output",
}

__all__ = sorted(_LAZY)


def __getattr__(name):
    if name in _LAZY:
        return getattr(import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
