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
    """Unknown parameter name or invalid parameter value (one the scene rejects, or with which its model
    is not valid)."""

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


class ResultFileError(InvctlError, ValueError):
    """A result file is missing, truncated, foreign (not written by invctl) or of another version."""


class OutputPathError(InvctlError, ValueError):
    """An output path cannot be written (no such directory, not writable, exists without --force)."""


class AnimationError(InvctlError):
    """An animation or snapshot cannot be written (format, writer, times, frame count)."""


class DrawingError(AnimationError, ValueError):
    """A drawing of a mechanism is malformed (points, links, symbols, styles)."""


class FeedbackDesignError(InvctlError):
    """An automatic feedback design is impossible ((A1) cannot hold, a funnel cannot contain the start)."""


class PositionOutputError(ModelError):
    """An output is not a function ``h(q)`` that depends on the configuration (it is
    constant or depends on velocities): servo constraints ``h(q) = y_ref`` need one."""


class SingularDecouplingError(RelativeDegreeError):
    """The decoupling matrix ``A_z`` of the jerk-level index reduction is singular at a
    point of the inversion: the vector relative degree is not (2, ..., 2) there (e.g. a
    flat output of relative degree 4)."""


class ReferenceSmoothnessError(ReferenceSignalError):
    """A reference is less smooth than the inversion needs: declared smoothness too low, or a
    derivative that jumps (measured) although more smoothness is declared."""


class NoDichotomyError(BoundaryConditionError):
    """The internal (zero) dynamics at an equilibrium of the inverse model have eigenvalues on
    the imaginary axis, or different numbers of unstable modes at the two ends: no
    exponential dichotomy, so no bounded stable inverse and no boundary selection 003 (36)."""


class HorizonTooLongError(BoundaryConditionError):
    """The pre-/post-actuation needed for the requested truncation error exceeds the cap
    (a slow internal mode)."""


class LinearizationError(InvctlError):
    """A linearization is not available at the requested point (not an equilibrium, off the manifold)."""


class ZeroError(InvctlError):
    """System zeros cannot be computed or classified (degenerate system matrix, inconsistent tests)."""


class ResourceLimitError(InvctlError):
    """A run would need more memory (or another resource) than its budget allows.

    ``diagnostics`` holds the estimate, the budget and the settings that fit
    (e.g. ``record_every``); ``partial`` holds what was computed when the
    limit was hit during the run.
    """


class RecordingError(InvctlError, ValueError):
    """A quantity needs trajectory steps that were not recorded (decimated or
    event-only record); the exact run statistics or a full record give it."""


class LibraryError(InvctlError):
    """A trajectory library cannot be generated or read as asked (a point without a trajectory,
    an unknown axis)."""


class SingularHighGainError(RelativeDegreeError):
    """The high-gain matrix Gamma of the auxiliary ODE 003 (10) is singular at a point of a
    normal-form inverse: the relative degree of the outputs does not exist there, so 003 (15)
    cannot be solved for the multipliers and inputs."""


class WallTimeLimitError(InversionFailed):
    """A solve stopped at its wall-time limit (``max_wall_time``) before converging: the problem is
    too large for the limit, not necessarily ill-posed."""


class NumericalError(InvctlError):
    """A computation broke down numerically (singular or non-finite matrices, overflow) for the given
    parameter values: they are outside the range the model can be evaluated in."""


class RunInterrupted(KeyboardInterrupt):
    """The user interrupted a run (Ctrl-C, SIGINT).

    A ``KeyboardInterrupt`` (so ``except Exception`` never swallows it) that carries what was
    complete when it arrived: ``partial`` (study rows so far, the last accepted mesh's inverse, the
    simulated prefix) and ``diagnostics``; ``saved`` lists the files the command wrote them to.
    """

    def __init__(self, message: str = "interrupted", *, partial: Any = None, diagnostics: dict | None = None):
        super().__init__(message)
        self.partial = partial
        self.diagnostics = dict(diagnostics or {})
        self.saved: list[str] = []

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else "interrupted"


class watch_sigint:
    """Context manager noting a SIGINT that arrives inside it (``.seen``), chaining to the handler in
    place (so Ctrl-C still raises ``KeyboardInterrupt`` where Python code runs).

    Compiled solvers turn a ``KeyboardInterrupt`` raised in their callbacks into their own failure
    (IPOPT: ``User_Requested_Stop``; CVODES: a ``RuntimeError``); ``seen`` tells such a failure
    apart from a real one so it can be reported as :class:`RunInterrupted`.  Does nothing outside
    the main thread or when SIGINT is ignored.
    """

    def _note(self) -> None:
        self.seen = True

    def __enter__(self):
        import signal
        import threading

        self.seen, self._old = False, None
        if threading.current_thread() is threading.main_thread():
            old = signal.getsignal(signal.SIGINT)
            if callable(old):
                def handler(signum, frame):
                    self._note()
                    return old(signum, frame)

                self._old = old
                signal.signal(signal.SIGINT, handler)
        return self

    def __exit__(self, *exc):
        if self._old is not None:
            import signal

            signal.signal(signal.SIGINT, self._old)
        return False


class remember_sigint(watch_sigint):
    """Context manager (the command line's) that also remembers a Ctrl-C, so that one swallowed by a
    compiled library is still honoured: CasADi's conversion of Python arguments catches any exception
    raised inside it, ``KeyboardInterrupt`` included, and carries on.  :func:`check_interrupt` at the
    loops' natural boundaries (closed-loop chunks, controllers of a study, contact chunks, sweep
    points, IPOPT solves) raises it there, and the command line once more when a command returns.  Restores
    the handler in place on exit."""

    def _note(self) -> None:
        global _SIGINT_PENDING
        self.seen = _SIGINT_PENDING = True

    def __enter__(self):
        global _SIGINT_PENDING
        _SIGINT_PENDING = False
        return super().__enter__()

    def __exit__(self, *exc):
        global _SIGINT_PENDING
        _SIGINT_PENDING = False
        return super().__exit__(*exc)


_SIGINT_PENDING = False


def check_interrupt(message: str | None = None) -> None:
    """Raise ``KeyboardInterrupt`` (:class:`RunInterrupted` with ``message``) if a Ctrl-C arrived inside
    :class:`remember_sigint` and was swallowed before reaching Python code (does nothing outside it)."""
    global _SIGINT_PENDING
    if _SIGINT_PENDING:
        _SIGINT_PENDING = False
        raise RunInterrupted(message) if message else KeyboardInterrupt


def is_interrupt(exc: BaseException) -> bool:
    """Whether ``exc`` is a Ctrl-C: a ``KeyboardInterrupt``; the ``SystemError`` Python raises when a
    compiled library returns with the ``KeyboardInterrupt`` of a Python callback still set; or, after a
    Ctrl-C remembered by :class:`remember_sigint`, the ``NotImplementedError`` CasADi's argument
    conversion reports when a ``KeyboardInterrupt`` cut it short (see :data:`INTERRUPT_LIKE`)."""
    seen = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        if not isinstance(e, SystemError):
            break
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return _SIGINT_PENDING and isinstance(exc, INTERRUPT_LIKE)


INTERRUPT_LIKE = (KeyboardInterrupt, SystemError, NotImplementedError)
"""What a Ctrl-C can surface as from compiled code (``except INTERRUPT_LIKE`` then :func:`is_interrupt`)."""


class JugglingInfeasible(FeedbackDesignError):
    """The recursive impact design of 000 (29)-(33) has no solution for a cycle: step 2 (no impact
    speeds of the right sign reach the target) or step 4 (viability) fails; ``partial`` holds the plan
    of the cycles before, ``diagnostics`` the start, the target and the search window."""



class OptionError(InvctlError, ValueError):
    """An option of a command (``--N 3``, ``--fps 0``) or of the inversion (:mod:`invctl.inversion.options`)
    has a wrong type or value, or does not apply."""


class BoundsError(OptionError):
    """Bounds of a bounded inversion are malformed (unknown names, lower > upper, negative limits)."""


class InfeasibleBoundsError(InversionFailed):
    """No trajectory satisfies the bounds together with the boundary conditions; the diagnostics
    hold the closest feasible relaxation found (``diagnostics["relaxation"]``)."""


class URDFError(ModelError):
    """A robot description (URDF) cannot be used: the file is missing or malformed (not XML, a
    missing attribute, a number that is not one, a joint naming an unknown link), or a joint or
    frame named in the model's declaration does not exist in it."""


class UnsupportedURDFError(URDFError):
    """A URDF uses an element invctl does not model (a closed kinematic loop, a mimic joint, a
    floating or planar joint); the message names the element."""


__all__ = [
    "InvctlError", "ModelError", "DimensionError", "ParameterError", "SceneError", "RelativeDegreeError",
    "CoordinateError", "ReferenceSignalError", "BoundaryConditionError", "InversionFailed", "SimulationFailed",
    "FunnelViolation", "StabilityError", "ContactError", "PreloadInfeasible", "ResultFileError",
    "OutputPathError", "AnimationError", "DrawingError", "FeedbackDesignError", "PositionOutputError",
    "SingularDecouplingError", "ReferenceSmoothnessError", "NoDichotomyError", "HorizonTooLongError",
    "LinearizationError", "ZeroError", "ResourceLimitError", "RecordingError", "LibraryError",
    "SingularHighGainError", "WallTimeLimitError", "NumericalError", "RunInterrupted", "watch_sigint",
    "remember_sigint", "check_interrupt", "is_interrupt", "INTERRUPT_LIKE",
    "JugglingInfeasible", "OptionError", "BoundsError", "InfeasibleBoundsError", "URDFError",
    "UnsupportedURDFError",
]
