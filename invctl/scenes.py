"""Finding scenes (``problems/<name>.py``) by name or by path.

A scene module declares what it needs and nothing else:

``PARAMS``
    dict of default parameter values;
``DERIVED`` (optional)
    dict name -> rule for derived parameters;
``build(**overrides)``
    returns the scene's model object;
``COMMANDS``
    dict command name (``analyze``, ``invert``, ``simulate``, ``design``,
    ``study``) -> handler ``handler(params: dict, **options) -> CommandResult``,
    usually a :class:`lazy_command` so that loading a scene imports nothing heavy.
"""
from __future__ import annotations

import importlib
import importlib.util
import pkgutil
import sys
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any

from .errors import SceneError


@dataclass
class CommandResult:
    """What a scene command returns: a readable report and JSON-able data (see :func:`jsonable`)."""

    text: str
    data: dict[str, Any] = field(default_factory=dict)


def jsonable(obj):
    """``obj`` with numpy scalars/arrays as Python numbers/lists, complex numbers as ``[re, im]``,
    non-finite floats as strings (``"inf"``, ``"nan"``: strict JSON has no such numbers) and
    anything else unknown as its ``str``."""
    import numpy as np

    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if np.isfinite(f) else str(f)
    if isinstance(obj, (complex, np.complexfloating)):
        return [jsonable(obj.real), jsonable(obj.imag)]
    if isinstance(obj, str) or obj is None:
        return obj
    return str(obj)


def available_scenes() -> list[str]:
    """Names of the scenes shipped in ``problems/``."""
    import problems

    return sorted(m.name for m in pkgutil.iter_modules(problems.__path__) if not m.name.startswith("_"))


def load_scene(name_or_path: str) -> ModuleType:
    """Import a scene by name (``manipulator``) or by path (``./my_scene.py``)."""
    path = Path(name_or_path)
    if path.suffix == ".py" or path.exists():
        if not path.is_file():
            raise SceneError(f"scene file {str(path)!r} does not exist")
        modname = f"invctl_scene_{path.stem}"
        spec = importlib.util.spec_from_file_location(modname, path)
        if spec is None or spec.loader is None:
            raise SceneError(f"cannot import scene file {str(path)!r}")
        module = importlib.util.module_from_spec(spec)
        sys.modules[modname] = module
        spec.loader.exec_module(module)
    else:
        try:
            module = importlib.import_module(f"problems.{name_or_path}")
        except ModuleNotFoundError as exc:
            if exc.name not in (f"problems.{name_or_path}", "problems"):
                raise
            raise SceneError(
                f"no scene named {name_or_path!r}; shipped scenes: {', '.join(available_scenes())} "
                "(or give a path to a scene file)"
            ) from None
    if not hasattr(module, "SCENE_NAME"):
        module.SCENE_NAME = path.stem if path.suffix == ".py" else name_or_path
    if not hasattr(module, "build"):
        raise SceneError(f"scene {name_or_path!r} has no build(**params) function")
    return module


def scene_name(module: ModuleType) -> str:
    """The short name of a scene module (file stem or name in problems/)."""
    return getattr(module, "SCENE_NAME", module.__name__.split(".")[-1])


def scene_command(module: ModuleType, command: str):
    """The handler of ``command`` in a scene, or a clear error."""
    commands = getattr(module, "COMMANDS", {})
    if command not in commands:
        offered = ", ".join(sorted(commands)) or "none"
        raise SceneError(
            f"scene {scene_name(module)!r} does not offer {command!r}; it offers: {offered}"
        )
    return commands[command]


@dataclass(frozen=True)
class lazy_command:  # noqa: N801 - used like a function in scene files
    """A scene's command handler that imports its implementation on first call, so that loading
    a scene stays light: ``COMMANDS = {"simulate": lazy_command(__name__, "invctl.studies.x:simulate_command")}``.
    The implementation is called as ``impl(scene_module, params, **options)``."""

    scene_module: str
    target: str

    def __call__(self, params: dict, **options):
        module_name, _, attr = self.target.partition(":")
        impl = getattr(importlib.import_module(module_name), attr)
        return impl(sys.modules[self.scene_module], params, **options)
