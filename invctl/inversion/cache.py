"""Where the inversion's derived objects live: each on the object it is derived from, none in module state.

A model keeps its servo models (per formulation and omega) and its equilibrium solver (in the store of
objects derived from its symbols, :func:`invctl.analysis.auxiliary.cache_of`, which ``with_params`` copies
share); a servo model keeps its transcriptions and OCP transcriptions (the most recent :data:`KEPT` of
each).  So one-shot calls on the same model, or on copies with other parameter values, build nothing
twice, and nothing outlives its model.  A model rebuilt by a scene builds its symbolic pieces again, but
the compiled pieces are loaded from the disk cache by name: :func:`compiled_key` is the model's
*structure* (its serialized symbolic functions), not the object."""
from __future__ import annotations

import hashlib
from pathlib import Path

from ..analysis.auxiliary import cache_of, cached
from ..analysis.equilibrium import EquilibriumSolver
from .collocation import Transcription
from .servo import ServoModel, remember

#: transcriptions (and OCP transcriptions) kept per servo model; the least recently used one goes beyond
KEPT = 16
#: hash of the source of the modules that derive the compiled functions (read once: it cannot change
#: while the process runs)
_SOURCE_KEY: str | None = None


def model_key(model) -> str:
    """A structural key of a model: the hash of its serialized symbolic functions (kept by the model)."""
    def make():
        text = "|".join(model.function(k).serialize() for k in ("M", "f", "B", "g", "J", "j", "h"))
        return hashlib.sha1((model.name + text).encode()).hexdigest()

    return cached(model, ("inversion_key",), make)


def servo_model(model, formulation: str = "baumgarte", omega: float = 10.0) -> ServoModel:
    """The :class:`ServoModel` of ``model`` (kept by the model; its functions take the parameter values as
    an argument, so ``with_params`` copies share it)."""
    return cached(model, ("servo_model", formulation, float(omega)), lambda: ServoModel(model, formulation, omega))


def share_servo(model, servo) -> None:
    """Let ``model`` use ``servo`` when it has the structure of ``servo``'s model (a held solver's model rebuilt by a
    scene with other parameter values): the held transcriptions are reused, not built again."""
    key = ("servo_model", servo.formulation, servo.omega)
    store = cache_of(model)
    if key not in store and model_key(model) == model_key(servo.model):
        store[key] = servo


def equilibrium_solver(model) -> EquilibriumSolver:
    """The :class:`EquilibriumSolver` of ``model`` (kept by the model; the analysis uses the same one)."""
    return cached(model, ("equilibrium_solver",), lambda: EquilibriumSolver(model))


def _kept(memo, key, make):
    """``remember`` for a servo model's transcriptions: one whose pieces compiled in the background have
    landed in the disk cache since it was built is made again (it would evaluate them in C)."""
    tr = memo.get(key)
    if tr is not None and getattr(tr, "upgradable", lambda: False)():
        del memo[key]
    return remember(memo, key, make, KEPT)


def transcription(servo, selection, scheme, N: int, objective: float = 0.0, compiled="auto") -> Transcription:
    """The :class:`Transcription` for (servo model, selection, scheme, N), kept by ``servo``."""
    key = (selection.start, selection.end, scheme.name, int(N), float(objective), compiled)
    return _kept(servo.transcriptions, key, lambda: Transcription(servo, selection, scheme, N, objective=objective,
                                                                  compiled=compiled,
                                                                  cache_key=compiled_key(servo, scheme)))


def ocp_transcription(servo, selection, scheme, N: int, **structure):
    """The :class:`~invctl.inversion.ocp.OCPTranscription` kept by ``servo`` (bound values and weights are
    parameters, so only the structure -- which entries are bounded, relaxed, free time -- keys it)."""
    from .ocp import OCPTranscription

    key = (selection.start, selection.end, scheme.name, int(N), tuple(sorted(structure.items())))
    return _kept(servo.ocp_transcriptions, key, lambda: OCPTranscription(servo, selection, scheme, N, **structure))


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
