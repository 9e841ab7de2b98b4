"""Inversion of a scene with the scene's reference, boundary selection and defaults.

A scene offers, in its ``# --- inversion`` section, ``INVERSION = {"T0": ...,
"Tf": ..., "N": ..., "scheme": ..., "start": {...}, "end": {...}}`` (any key
of :func:`invctl.inversion.invert`), a ``reference(model)`` and optionally
``initial_configuration(model)`` (start of the equilibrium search).
"""
from __future__ import annotations

from ..errors import SceneError
from ..scenes import scene_name
from .solve import invert


def scene_defaults(scene) -> dict:
    """The scene's inversion defaults (``INVERSION``), checked."""
    cfg = getattr(scene, "INVERSION", None)
    if not isinstance(cfg, dict) or not {"T0", "Tf", "start", "end"} <= set(cfg):
        raise SceneError(f"scene {scene_name(scene)!r} has no INVERSION dict with T0, Tf, start, end "
                         "(boundary selection of 003 (36)); add one to its '# --- inversion' section")
    if not hasattr(scene, "reference"):
        raise SceneError(f"scene {scene_name(scene)!r} has no reference(model) function")
    return dict(cfg)


def invert_scene(scene, params: dict | None = None, *, model=None, reference=None, **opts):
    """Invert a scene: ``invert(model, scene.reference(model), **scene.INVERSION, **opts)``.

    Returns the :class:`Inverse`; ``opts`` override the scene's defaults.
    """
    cfg = scene_defaults(scene)
    model = model if model is not None else scene.build(**(params or {}))
    reference = reference if reference is not None else scene.reference(model)
    if "q_guess" not in opts and hasattr(scene, "initial_configuration"):
        opts["q_guess"] = scene.initial_configuration(model)
    cfg.update({k: v for k, v in opts.items() if v is not None})
    return invert(model, reference, **cfg)
