"""Caches of the inversion: servo models, transcriptions and equilibrium solvers are keyed by the
model's *structure* (its serialized symbolic functions), not its parameter values, so models
rebuilt by a scene with other parameters share them (and their compiled solvers)."""
from __future__ import annotations

import hashlib
from pathlib import Path

from ..analysis.equilibrium import EquilibriumSolver
from .collocation import Transcription
from .servo import ServoModel

_SERVO_CACHE: dict = {}
_TRANS_CACHE: dict = {}
_OCP_CACHE: dict = {}
_EQ_CACHE: dict = {}
_QS_LAST: dict = {}

_CACHE_SIZE = 16
_SOURCE_KEY: str | None = None


def model_key(model) -> str:
    """A structural key of a model: the hash of its serialized symbolic functions, so that
    models built repeatedly by a scene (other parameter values) share servo models,
    transcriptions and equilibrium solvers."""
    key = getattr(model, "_inversion_key", None)
    if key is None:
        text = "|".join(model.function(k).serialize() for k in ("M", "f", "B", "g", "J", "j", "h"))
        key = hashlib.sha1((model.name + text).encode()).hexdigest()
        try:
            model._inversion_key = key
        except AttributeError:
            pass
    return key


def remember(cache: dict, key, make):
    """``cache[key]``, made by ``make()`` when missing (the oldest entry goes beyond 16)."""
    if key not in cache:
        if len(cache) >= _CACHE_SIZE:
            cache.pop(next(iter(cache)))
        cache[key] = make()
    return cache[key]


def servo_model(model, formulation: str = "baumgarte", omega: float = 10.0) -> ServoModel:
    """The cached :class:`ServoModel` (keyed by the model's structure, not its parameter values)."""
    return remember(_SERVO_CACHE, (model_key(model), formulation, float(omega)),
                    lambda: ServoModel(model, formulation, omega))


def _held(cache: dict, key, servo, make):
    """``remember`` for objects built on ``servo`` (keyed by its id: an entry whose servo model was evicted and
    its id reused, or whose compiled pieces landed in the disk cache since it was built, is made again)."""
    tr = cache.get(key)
    if tr is not None and (tr.servo is not servo or getattr(tr, "upgradable", lambda: False)()):
        del cache[key]
    return remember(cache, key, make)


def transcription(servo, selection, scheme, N: int, objective: float = 0.0, compiled="auto") -> Transcription:
    """The cached :class:`Transcription` for (servo model, selection, scheme, N)."""
    key = (id(servo), selection.start, selection.end, scheme.name, int(N), float(objective), compiled)
    return _held(_TRANS_CACHE, key, servo, lambda: Transcription(servo, selection, scheme, N, objective=objective,
                                                                 compiled=compiled, cache_key=compiled_key(servo, scheme)))


def ocp_transcription(servo, selection, scheme, N: int, **structure):
    """The cached :class:`~invctl.inversion.ocp.OCPTranscription` (bound values and weights are
    parameters, so only the structure -- which entries are bounded, relaxed, free time -- keys it)."""
    from .ocp import OCPTranscription

    key = (id(servo), selection.start, selection.end, scheme.name, int(N), tuple(sorted(structure.items())))
    return _held(_OCP_CACHE, key, servo, lambda: OCPTranscription(servo, selection, scheme, N, **structure))


def compiled_key(servo, scheme) -> str:
    """Disk-cache key of the compiled transcription functions: the model's structure, the index
    reduction, the scheme and the source of the modules that derive the functions from them
    (so that editing them never loads stale code)."""
    global _SOURCE_KEY
    if _SOURCE_KEY is None:
        here = Path(__file__).parent
        text = "".join((here / f).read_text() for f in ("servo.py", "schemes.py", "collocation.py"))
        _SOURCE_KEY = hashlib.sha1(text.encode()).hexdigest()
    return "|".join([model_key(servo.model), servo.formulation, repr(servo.omega), scheme.name, _SOURCE_KEY])


def equilibrium_solver(model) -> EquilibriumSolver:
    """The cached :class:`EquilibriumSolver` of ``model``'s structure."""
    return remember(_EQ_CACHE, model_key(model), lambda: EquilibriumSolver(model))
