"""The ``invctl`` commands, written once against :class:`invctl.scenes.Scene`.

Every command takes a scene (object, name or path), the ``--set`` values and its options, checks
the options once (:data:`OPTIONS`), checks output paths before any computation, and dispatches to
the module of the scene's kind (:mod:`.tracking_report`, :mod:`.contact`, :mod:`.switched_report`).
The same calls serve the command line, notebooks and scripts::

    from invctl.studies import commands
    res = commands.invert("cartpole", {"mp": 0.3}, N=300)
    print(res.text); res.data["max_output_error"]
"""
from __future__ import annotations

import importlib
import math
import os
from dataclasses import dataclass, replace
from typing import Any, Callable

from ..errors import ParameterError, SceneError
from ..io import check_output_dir, check_output_path
from ..scenes import SCENE_COMMANDS, CommandResult, Scene, load_scene

__all__ = ["OPTIONS", "Option", "run_command", "analyze", "invert", "design", "simulate", "pipeline", "study"]

_KIND_MODULES = {"tracking": "invctl.studies.tracking_report", "contact": "invctl.studies.contact",
                 "switched": "invctl.studies.switched_report"}


@dataclass(frozen=True)
class Option:
    """One command option: its type, its check and help (shared by the CLI and the Python calls)."""

    type: Callable
    help: str
    commands: tuple
    default: Any = None
    check: Callable | None = None       # value -> error text or None
    choices: tuple | None = None
    flag: bool = False
    repeat: bool = False
    metavar: str | None = None


def _positive(v):
    return None if (isinstance(v, (int, float)) and math.isfinite(v) and v > 0) else "must be a positive number"


def _at_least(k):
    return lambda v: None if v >= k else f"must be at least {k}"


def _scheme(v):
    from ..inversion.collocation import get_scheme

    try:
        get_scheme(v)
    except ValueError as exc:
        return str(exc)
    return None


#: every option of every command (name as in Python; the CLI spells ``_`` as ``-``)
OPTIONS: dict[str, Option] = {
    "preset": Option(str, "start from the scene's named parameter set (then --set overrides)",
                     ("analyze", "invert", "design", "simulate", "pipeline", "study")),
    "samples": Option(int, "sample points for the checks", ("analyze",), 200, _at_least(1)),
    "N": Option(int, "number of collocation intervals (default: automatic)", ("invert",), None, _at_least(4)),
    "scheme": Option(str, "collocation scheme: hermite-simpson, legendre<d>, radau<d>", ("invert",), None, _scheme),
    "tol": Option(float, "requested output error: refine the mesh until met", ("invert",), None, _positive),
    "backend": Option(str, "solver of the collocation equations (default ipopt)", ("invert",), None,
                      choices=("ipopt", "newton")),
    "dt": Option(float, "sampling step of the saved trajectory (with --out)", ("invert",), None, _positive),
    "controller": Option(str, "controller to run (tracking: C1, C2, C3, C1-inv; contact: the scene's)",
                         ("simulate",)),
    "plant_set": Option(str, "override a parameter of the simulated plant only (repeatable)",
                        ("simulate", "pipeline"), None, repeat=True, metavar="NAME=VALUE"),
    "t_end": Option(float, "end time of the simulation", ("simulate", "pipeline"), None, _positive),
    "inverse": Option(str, "use this saved inverse (invctl invert --out FILE.npz) as feedforward", ("simulate",)),
    "out": Option(str, "write the result to this file (.npz; simulate also .csv)", ("invert", "simulate")),
    "plot": Option(str, "write a figure to this file (.png/.pdf/.svg)", ("simulate", "design")),
    "out_dir": Option(str, "folder for figures, tables and runs", ("pipeline", "study"), "invctl-out"),
    "job": Option(str, "which job's trade-off (default: the scene's first; see docs/tradeoffs.md)", ("study",)),
    "force": Option(bool, "replace existing output files", ("invert", "simulate", "design"), False, flag=True),
    "quiet": Option(bool, "no progress output", ("invert", "simulate", "pipeline", "study"), False, flag=True),
    "no_animation": Option(bool, "do not write animations of the runs", ("pipeline",), False, flag=True),
}

#: ``invctl generate`` (trajectory libraries, :mod:`.library`): its own options; it shares N, scheme, tol,
#: backend, out, force and quiet with the commands above
OPTIONS.update({
    "grid": Option(str, "a grid axis: a scene parameter or a numeric argument of the scene's reference, "
                   "NAME=START:STOP:COUNT or NAME=V1,V2,... (repeatable; sequence arguments by component, "
                   "e.g. 'rf[0]=0.8:1.0:10')", ("generate",), None, repeat=True, metavar="NAME=START:STOP:COUNT"),
    "workers": Option(int, "worker processes (default: the CPU count; 1: in this process)", ("generate",), None,
                      _at_least(1)),
    "dask": Option(str, "solve on this Dask scheduler (address, e.g. tcp://host:8786)", ("generate",)),
    "verify": Option(str, "forward-check every point, the grid's corners or none", ("generate",), "corners",
                     choices=("all", "corners", "none")),
    "no_continuation": Option(bool, "solve every point from its quasi-static guess (no warm starts)", ("generate",),
                              False, flag=True),
})
for _name in ("N", "scheme", "tol", "backend", "out", "force", "quiet"):
    OPTIONS[_name] = replace(OPTIONS[_name], commands=OPTIONS[_name].commands + ("generate",))
OPTIONS["out"] = replace(OPTIONS["out"], help=OPTIONS["out"].help + "; generate: a .npz file or a folder (an "
                         "unfinished library of the same settings there is resumed)")
OPTIONS["force"] = replace(OPTIONS["force"], help=OPTIONS["force"].help + " (generate: start the library over)")
OPTIONS["backend"] = replace(OPTIONS["backend"], help=OPTIONS["backend"].help.replace(
    "(default ipopt)", "(default ipopt; generate: newton)"))

_FIGURE_SUFFIXES = (".png", ".pdf", ".svg")


def options_of(command: str) -> dict[str, Option]:
    return {k: o for k, o in OPTIONS.items() if command in o.commands}


def check_options(command: str, options: dict) -> dict:
    """Options with defaults filled in, each checked; unknown options are an error."""
    allowed = options_of(command)
    unknown = sorted(k for k, v in options.items() if k not in allowed and v not in (None, False, [], ()))
    if unknown:
        raise SceneError(f"invctl {command} does not take option(s) {unknown}; it takes: "
                         f"{', '.join(sorted(allowed)) or 'none'}")
    out = {}
    for name, opt in allowed.items():
        v = options.get(name)
        if v is None or (opt.repeat and not v):
            v = opt.default
        if v is None or (opt.flag and v is False) or (opt.repeat and not v):
            out[name] = v if not opt.repeat else (v or [])
            continue
        if not opt.repeat:
            try:
                v = opt.type(v)
            except (TypeError, ValueError):
                raise ParameterError(f"--{name.replace('_', '-')} {v!r}: expected {opt.type.__name__}") from None
            if opt.choices and v not in opt.choices:
                raise ParameterError(f"--{name.replace('_', '-')} {v!r}: choose one of {list(opt.choices)}")
            msg = opt.check(v) if opt.check else None
            if msg:
                raise ParameterError(f"--{name.replace('_', '-')} {v!r}: {msg}")
        out[name] = v
    return out


def _scene(scene) -> Scene:
    return scene if isinstance(scene, Scene) else load_scene(scene)


def _kind(scene: Scene):
    return importlib.import_module(_KIND_MODULES[scene.kind])


def _plant_params(items) -> dict:
    from ..model.params import parse_assignments

    if isinstance(items, dict):
        return dict(items)
    return parse_assignments(items, option="--plant-set")


def _figure_path(path, force):
    p = check_output_path(path, force=force, option="--plot")
    if p.suffix.lower() not in _FIGURE_SUFFIXES:
        raise ParameterError(f"--plot {path}: use one of {', '.join(_FIGURE_SUFFIXES)}")
    return p


# ------------------------------------------------------------------ commands
def analyze(scene, values=None, **options) -> CommandResult:
    """``invctl analyze``: what the scene's kind analyses (relative degree and internal dynamics for
    tracking scenes, Theorem 1 for switched ones, declared reports for contact scenes)."""
    scene = _scene(scene)
    scene.require("analyze")
    o = check_options("analyze", options)
    params, settings = scene.split(values, preset=o["preset"])
    return _kind(scene).analyze(scene, params, settings, samples=o["samples"])


def invert(scene, values=None, **options) -> CommandResult:
    """``invctl invert``: the stable inversion (feedforward with pre-actuation), forward-checked."""
    scene = _scene(scene)
    scene.require("invert")
    o = check_options("invert", options)
    if o["dt"] is not None and not o["out"]:
        raise ParameterError("--dt sets the sampling of the saved trajectory; give --out FILE.npz too")
    out = str(check_output_path(o["out"], suffix=".npz", force=o["force"])) if o["out"] else None
    params, settings = scene.split(values, preset=o["preset"])
    return _kind(scene).invert(scene, params, settings, N=o["N"], scheme=o["scheme"], tol=o["tol"],
                               backend=o["backend"], out=out, dt=o["dt"], quiet=o["quiet"])


def design(scene, values=None, **options) -> CommandResult:
    """``invctl design``: the feedback design of the scene (funnel controller, or wrist/damping design)."""
    scene = _scene(scene)
    scene.require("design")
    o = check_options("design", options)
    plot = _figure_path(o["plot"], o["force"]) if o["plot"] else None
    params, settings = scene.split(values, preset=o["preset"])
    return _kind(scene).design(scene, params, settings, plot=plot)


def simulate(scene, values=None, **options) -> CommandResult:
    """``invctl simulate``: one run of one controller (tracking: C1/C2/C3 on the mismatched plant)."""
    scene = _scene(scene)
    scene.require("simulate")
    o = check_options("simulate", options)
    out = None
    if o["out"]:
        suffix = ".csv" if str(o["out"]).lower().endswith(".csv") else ".npz"
        out = str(check_output_path(o["out"], suffix=suffix, force=o["force"]))
    plot = _figure_path(o["plot"], o["force"]) if o["plot"] else None
    params, settings = scene.split(values, preset=o["preset"])
    kw = dict(controller=o["controller"], plant_params=_plant_params(o["plant_set"]), t_end=o["t_end"], out=out,
              plot=plot, quiet=o["quiet"])
    if o["inverse"]:
        if scene.kind != "tracking":
            raise SceneError("--inverse applies to tracking scenes only")
        from ..inversion import Inverse

        kw["inverse"] = Inverse.load(o["inverse"])
    return _kind(scene).simulate(scene, params, settings, **kw)


def pipeline(scene, values=None, **options) -> CommandResult:
    """``invctl pipeline``: the scene's whole job (tracking: invert, design, C1/C2/C3, compare, figures)."""
    scene = _scene(scene)
    scene.require("pipeline")
    o = check_options("pipeline", options)
    out_dir = check_output_dir(o["out_dir"])
    params, settings = scene.split(values, preset=o["preset"])
    return _kind(scene).pipeline(scene, params, settings, out_dir=out_dir, t_end=o["t_end"],
                                 plant_params=_plant_params(o["plant_set"]), quiet=o["quiet"],
                                 animate=not o["no_animation"])


def study(scene, kind: str, values=None, **options) -> CommandResult:
    """``invctl study tradeoff``: speed versus accuracy of the scene's job (table, CSV, JSON, figure)."""
    from .tradeoff import run_tradeoff
    from .tradeoff_specs import spec_for

    scene = _scene(scene)
    scene.require("study")
    if kind != "tradeoff":
        raise SceneError(f"unknown study {kind!r}; available: tradeoff")
    o = check_options("study", options)
    out = check_output_dir(o["out_dir"])
    params, settings = scene.split(values, preset=o["preset"])
    smoke = os.environ.get("INVCTL_SMOKE") == "1"
    spec = spec_for(scene, params, settings, smoke=smoke, job=o["job"])
    result = run_tradeoff(spec, progress=not o["quiet"])
    stem = f"tradeoff_{spec.scene}"
    out.mkdir(parents=True, exist_ok=True)
    result.to_csv(out / f"{stem}.csv")
    result.to_json(out / f"{stem}.json")
    import matplotlib.pyplot as plt

    ax = result.plot()
    ax.figure.tight_layout()
    ax.figure.savefig(out / f"{stem}.png", dpi=120)
    plt.close(ax.figure)
    data = result.to_dict()
    data["files"] = {ext: str(out / f"{stem}.{ext}") for ext in ("csv", "json", "png")}
    return CommandResult(result.table() + f"\nwritten: {out / f'{stem}.csv'}, .json, .png", data)


def generate(scene, values=None, **options) -> CommandResult:
    """``invctl generate``: a trajectory library, the stable inverse at every point of a grid of scene
    parameters and reference arguments, warm-started from solved neighbours (:mod:`.library`)."""
    from pathlib import Path

    from .library import generate as generate_library

    scene = _scene(scene)
    scene.require("invert")
    o = check_options("generate", options)
    if not o["grid"]:
        raise ParameterError("invctl generate needs at least one --grid NAME=START:STOP:COUNT (a scene parameter "
                             "or a numeric argument of the scene's reference, e.g. --grid 'rf[0]=0.8:1.0:10')")
    out = o["out"]
    if out is None:
        out = str(check_output_dir("invctl-out") / f"library_{scene.name}.npz")
        Path(out).parent.mkdir(parents=True, exist_ok=True)
    params, _settings = scene.split(values)
    executor, client = ("serial" if o["workers"] == 1 else None), None
    if o["dask"]:
        try:
            from dask.distributed import Client
        except ImportError:
            raise ParameterError("--dask needs dask.distributed (pip install 'dask[distributed]')") from None
        client = executor = Client(o["dask"])
    try:
        lib = generate_library(scene, o["grid"], params=params, out=out, executor=executor, max_workers=o["workers"],
                               backend=o["backend"] or "newton", N=o["N"], scheme=o["scheme"], tol=o["tol"],
                               continuation=not o["no_continuation"], verify=o["verify"], force=o["force"],
                               progress=not o["quiet"])
    finally:
        if client is not None:
            client.close()
    return CommandResult(lib.table(), lib.to_dict())


__all__ += ["generate"]

_COMMANDS = {"analyze": analyze, "invert": invert, "design": design, "simulate": simulate, "pipeline": pipeline}


def run_command(command: str, scene, values=None, **options) -> CommandResult:
    """Run ``command`` (one of :data:`invctl.scenes.SCENE_COMMANDS`) on ``scene``."""
    if command not in SCENE_COMMANDS:
        raise SceneError(f"unknown command {command!r}; commands: {', '.join(SCENE_COMMANDS)}")
    if command == "study":
        kind = options.pop("kind", "tradeoff")
        return study(scene, kind, values, **options)
    return _COMMANDS[command](scene, values, **options)

