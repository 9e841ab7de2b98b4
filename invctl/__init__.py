"""invctl: model inversion and tracking control of multibody systems on CasADi and IPOPT.

Data flow: ``invctl.model`` -> ``invctl.analysis`` -> ``invctl.inversion`` ->
``invctl.control`` -> ``invctl.simulate`` -> ``invctl.studies``; scenes live in
``invctl_scenes/`` and are loaded with :func:`invctl.load_scene`.
"""
from .errors import *  # noqa: F401,F403
from .errors import __all__ as _errors_all
from .model import Gap, Model, OperatingRegion, ParamSet
from .results import Status, Trajectory, load
from .scenes import CommandResult, available_scenes, load_scene

__version__ = "0.1.0"

__all__ = ["Gap", "Model", "OperatingRegion", "ParamSet", "CommandResult", "Status", "Trajectory", "available_scenes",
           "load", "load_scene", "__version__", *_errors_all]
