"""One exception hierarchy for invctl.

Every error says what is wrong, where, and what to try.  Errors raised after
work was done carry that work in ``partial`` (a partial result) and a
``diagnostics`` dict, so nothing computed before the failure is lost.
"""
from __future__ import annotations

from typing import Any


class InvctlError(Exception):
    """Base class of all invctl errors.

    Parameters
    ----------
    message : str
        What went wrong, where, and what to try.
    partial : object, optional
        Whatever was computed before the failure (a partial result).
    diagnostics : dict, optional
        Numbers that explain the failure (residuals, solver status, ...).
    """

    def __init__(self, message: str, *, partial: Any = None, diagnostics: dict | None = None):
        super().__init__(message)
        self.partial = partial
        self.diagnostics = dict(diagnostics or {})


class ModelError(InvctlError):
    """A model is malformed (dimensions, G != g', M not SPD, ...)."""


class DimensionError(ModelError, ValueError):
    """An array or expression has the wrong shape."""


class ParameterError(InvctlError, KeyError):
    """Unknown parameter name or invalid parameter value."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else ""


class SceneError(InvctlError):
    """A scene cannot be found or does not offer the requested command."""


class RelativeDegreeError(InvctlError):
    """The (vector) relative degree does not exist at some point."""


class CoordinateError(InvctlError):
    """Internal coordinates are not admissible (Phi' singular, L_K phi != 0)."""


class ReferenceSignalError(InvctlError, ValueError):
    """A reference signal is not smooth enough or not admissible."""


class BoundaryConditionError(InvctlError, ValueError):
    """A boundary-condition selection is wrong (count, names, indices)."""


class InversionFailed(InvctlError):
    """The servo-constraint boundary value problem could not be solved."""


class SimulationFailed(InvctlError):
    """A simulation diverged or its integrator failed."""


class FunnelViolation(SimulationFailed):
    """The tracking error left the prescribed performance funnel."""


class StabilityError(InvctlError):
    """A subsystem is unstable or a stability analysis is not applicable."""


class ContactError(InvctlError):
    """A contact problem (LCP, impact) is unsolvable or not unique."""


class PreloadInfeasible(ContactError):
    """Persistent-contact (pre-loading) control does not exist (000 Lemma 1)."""


class ResourceLimitError(InvctlError):
    """A run would need more memory (or another resource) than its budget allows.

    ``diagnostics`` holds the estimate, the budget and the settings that fit
    (e.g. ``record_every``); ``partial`` holds what was computed when the
    limit was hit during the run.
    """


class RecordingError(InvctlError, ValueError):
    """A quantity needs trajectory steps that were not recorded (decimated or
    event-only record); the exact run statistics or a full record give it."""


__all__ = [
    "InvctlError", "ModelError", "DimensionError", "ParameterError", "SceneError",
    "RelativeDegreeError", "CoordinateError", "ReferenceSignalError",
    "BoundaryConditionError", "InversionFailed", "SimulationFailed", "FunnelViolation",
    "StabilityError", "ContactError", "PreloadInfeasible", "ResourceLimitError", "RecordingError",
]
