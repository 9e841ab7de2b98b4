"""Reference signals with exact derivatives."""
from .signals import Reference, poly9_timing_law

__all__ = ["Reference", "poly9_timing_law"]
