"""Reference signals with exact derivatives.

Kinds (docs/references.md): :func:`rest_to_rest` (polynomial move between two rests),
:func:`waypoints` (spline or stop-and-go path through waypoints), :func:`from_samples`
(smoothing spline of sampled data), :meth:`Reference.stack` (one reference from
per-output references), and :func:`poly9_timing_law` (the law of 003 Sect. 6).
"""
from .paths import rest_to_rest, waypoints
from .signals import Reference, poly9_timing_law

__all__ = ["Reference", "from_samples", "poly9_timing_law", "rest_to_rest", "waypoints"]


def __getattr__(name):
    """``from_samples`` (and its scipy fitting machinery) is imported on first use."""
    if name == "from_samples":
        from .samples import from_samples

        return from_samples
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
