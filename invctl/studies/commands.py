"""The ``invctl`` commands, written once against :class:`invctl.scenes.Scene`.

Every command takes a scene (object, name or path), the ``--set`` values and its options, checks
the options once (:data:`OPTIONS`), binds the scene with its values once (:func:`invctl.scenes.bind_scene`:
the values checked, the model built once and kept), checks output paths before any computation, lets the
scene's workflow check what depends on the scene (:meth:`.workflow.Workflow.prepare`: options of other kinds,
``--plant-set``, the time and memory of the run, :class:`~invctl.errors.ResourceLimitError` naming the option
that fits) and dispatches to the module of the scene's kind (:mod:`.tracking_report`, :mod:`.contact`,
:mod:`.switched_report`).
The same calls serve the command line and, through the scene's methods, notebooks and scripts::

    scene = invctl.load_scene("cartpole", mp=0.3)
    res = scene.run("invert", N=300)          # this module's invert(): res.text, res.data, res.result
    inv = scene.invert(N=300)                 # the typed result alone

Around every run: a contact run whose penetration is large against the clearance warns or fails with the numbers; Ctrl-C
(:class:`~invctl.errors.RunInterrupted`) saves what is complete next to the requested output
(``x.partial.npz``, ``tradeoff_<scene>.partial.csv``, the runs of a pipeline with a note) and
re-raises with ``exc.saved`` naming the files.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

from ..errors import InvctlError, NumericalError, OptionError, OutputPathError, RunInterrupted, SceneError, watch_sigint
from ..io import check_output_dir, check_output_path
from ..plot import close, finish
from ..scenes import SCENE_COMMANDS, CommandResult, Scene, bind_scene
from .pipeline import run_pipeline
from .workflow import workflow


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
    from ..inversion.schemes import get_scheme

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
    "animate": Option(bool, "also write an animation of each run (anim_<controller>.gif; scenes with a drawing)",
                      ("pipeline",), False, flag=True),
    "no_animation": Option(bool, "write no animations (the default; kept for earlier command lines)", ("pipeline",),
                           False, flag=True),
    "record_every": Option(int, "contact runs: keep every k-th step (default: at most 20000 samples per run; "
                           "1: every step; the run's statistics and impacts stay exact)",
                           ("simulate", "pipeline"), None, _at_least(1)),
    "record": Option(str, "contact runs: record every step ('steps') or only impacts and contact changes "
                          "('events')", ("simulate", "pipeline"), None, choices=("steps", "events")),
    "rtol": Option(float, "tracking runs: relative tolerance of the closed-loop integrator (CVODES; default 1e-8)",
                   ("simulate", "pipeline"), None, _positive),
    "atol": Option(float, "tracking runs: absolute tolerance of the closed-loop integrator (default 1e-10)",
                   ("simulate", "pipeline"), None, _positive),
    "max_steps": Option(int, "tracking runs: most integrator steps per output step (default 20000)",
                        ("simulate", "pipeline"), None, _at_least(1)),
    "max_wall_time": Option(float, "stop the inversion's solver after this many seconds", ("invert",), None,
                            _positive),
    "bound": Option(str, "a bound of the inversion: u=8, u.NAME=-5:8, u_rate=100, q.NAME=-0.2:0.2, v.NAME=1.5, "
                    "pre=0.3, post=0.5 (repeatable; an open side: q.NAME=:0.2); the exact inverse when it "
                    "meets them, least-squares tracking otherwise", ("invert",), None, repeat=True,
                    metavar="NAME=VALUE"),
    "weight": Option(str, "a weight of the least-squares tracking under bounds (and of --minimum-time): output=1, "
                     "output.NAME=10, slack=1e-2, energy=1e-3, rate=0 (repeatable)", ("invert",), None, repeat=True,
                     metavar="NAME=VALUE"),
    "minimum_time": Option(bool, "the shortest duration of the reference's transition (its shape kept) under "
                           "--bound; with --energy W the time-energy trade", ("invert",), False, flag=True),
    "energy": Option(float, "--minimum-time: weight of the input energy against the duration", ("invert",), None,
                     lambda v: None if math.isfinite(v) and v >= 0 else "must be a nonnegative number"),
    "duration": Option(str, "--minimum-time: range LO:HI of the duration searched (s)", ("invert",), None,
                       metavar="LO:HI"),
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
    "no_compile": Option(bool, "Newton in CasADi's virtual machine (default: the collocation residual and Jacobian "
                         "as C code, compiled once per machine when a C compiler is found)", ("generate",), False,
                         flag=True),
})
OPTIONS["dt"] = replace(OPTIONS["dt"], commands=OPTIONS["dt"].commands + ("simulate", "pipeline"),
                        help=OPTIONS["dt"].help + "; tracking runs: output step of the closed loop (default 1e-3 s)")
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
        raise OptionError(f"invctl {command} does not take option(s) {unknown}; it takes: "
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
                raise OptionError(f"--{name.replace('_', '-')} {v!r}: expected {opt.type.__name__}") from None
            if opt.choices and v not in opt.choices:
                raise OptionError(f"--{name.replace('_', '-')} {v!r}: choose one of {list(opt.choices)}")
            msg = opt.check(v) if opt.check else None
            if msg:
                raise OptionError(f"--{name.replace('_', '-')} {v!r}: {msg}")
        out[name] = v
    return out


def _figure_path(path, force):
    p = check_output_path(path, force=force, option="--plot")
    if p.suffix.lower() not in _FIGURE_SUFFIXES:
        raise OutputPathError(f"--plot {path}: use one of {', '.join(_FIGURE_SUFFIXES)}")
    return p


# --------------------------------------------------------- interruptions
def _free(path: Path) -> Path:
    """``path``, or ``stem-2.ext``, ``stem-3.ext`` ... when it exists (a partial never replaces a file)."""
    k, p = 2, path
    while p.exists():
        p = path.with_name(f"{path.stem}-{k}{path.suffix}")
        k += 1
    return p


def _partial_name(out, suffix=None) -> Path:
    p = Path(out)
    suffix = suffix or p.suffix
    return _free(p.with_name(f"{p.name[:len(p.name) - len(p.suffix)] if p.suffix else p.name}.partial{suffix}"))


def _save_partial(exc: RunInterrupted, *, out=None, out_dir=None, meta=None, dt=None) -> None:
    """Write ``exc.partial`` next to the requested output (noting that it is partial); record the
    files in ``exc.saved``. Failures to write are reported in the message, never raised."""
    part, note = exc.partial, str(exc)
    try:
        if out_dir is not None:
            d = Path(out_dir)
            d.mkdir(parents=True, exist_ok=True)
            if part is not None and hasattr(part, "to_csv") and hasattr(part, "rows"):  # trade-off rows
                stem = f"tradeoff_{part.scene or 'study'}"
                for ext in ("csv", "json"):
                    path = _free(d / f"{stem}.partial.{ext}")
                    getattr(part, f"to_{ext}")(path)
                    exc.saved.append(str(path))
            elif part is not None and hasattr(part, "runs") and hasattr(part, "save"):  # tracking runs so far
                if part.runs:
                    part.info["partial"] = note
                    part.save(d, meta=meta)
                    exc.saved += [str(d / f"run_{k}.npz") for k in part.runs] + [str(d / "study.json")]
            elif part is not None and hasattr(part, "to_npz"):  # the simulated prefix of the run under way
                path = _partial_name(d / exc.diagnostics.pop("run_file", "run.npz"), ".npz")
                exc.saved.append(str(part.to_npz(path, meta={**(meta or {}), "partial": note})))
            exc.saved += [f for f in exc.diagnostics.pop("complete", []) if Path(f).is_file()]
            files = sorted(q.name for q in d.iterdir() if q.name != "INTERRUPTED.txt")
            nf = d / "INTERRUPTED.txt"
            nf.write_text(f"PARTIAL RESULTS: {note}\nfiles present: {', '.join(files) or 'none'}\n")
            exc.saved.append(str(nf))
        elif out is not None and part is not None:
            csv = str(out).lower().endswith(".csv")
            path = _partial_name(out)
            info = {**(meta or {}), "partial": note}
            if csv and hasattr(part, "to_csv"):
                part.to_csv(path)
            elif hasattr(part, "to_npz"):
                path = path if path.suffix == ".npz" else _partial_name(out, ".npz")
                if dt is not None:
                    path = part.to_npz(path, dt, meta=info)
                else:
                    path = part.to_npz(path, meta=info)
            elif hasattr(part, "save"):
                path = part.save(path)
            else:
                return
            exc.saved.append(str(path))
    except (OSError, ValueError, TypeError, InvctlError) as err:  # the interruption is what must reach the user
        exc.args = (f"{note}; writing the partial result failed ({type(err).__name__}: {err})",)


def _interruptible(run, **where):
    """``run()``, saving what is complete on Ctrl-C (see :func:`_save_partial`). A failure after a
    SIGINT is the interruption (compiled solvers turn Ctrl-C into their own errors: a solver's failure, CasADi's
    ``RuntimeError``, numbers of a cut-short solve, or what :data:`~invctl.errors.INTERRUPT_LIKE` lists)."""
    with watch_sigint() as sigint:
        try:
            return run()
        except RunInterrupted as exc:
            _save_partial(exc, **where)
            raise
        except KeyboardInterrupt as exc:
            ri = RunInterrupted(str(exc) or "interrupted")
        except (InvctlError, RuntimeError, ValueError, ArithmeticError, SystemError, NotImplementedError) as exc:
            if not sigint.seen:
                raise
            ri = RunInterrupted(f"interrupted (the solver stopped with {type(exc).__name__}: {str(exc)[:200]})",
                                partial=getattr(exc, "partial", None) if isinstance(exc, InvctlError) else None)
    _save_partial(ri, **where)
    raise ri from None


# ------------------------------------------------------------------ commands
def analyze(scene, values=None, **options) -> CommandResult:
    """``invctl analyze``: what the scene's kind analyses (relative degree and internal dynamics for
    tracking scenes, Theorem 1 for switched ones, declared reports for contact scenes)."""
    o = check_options("analyze", options)
    bound = bind_scene(scene, "analyze", values, preset=o["preset"])
    wf = workflow(bound.scene)
    return wf.verbs.analyze(bound, **wf.prepare(bound, "analyze", o))


def invert(scene, values=None, **options) -> CommandResult:
    """``invctl invert``: the stable inversion (feedforward with pre-actuation), forward-checked."""
    o = check_options("invert", options)
    if o["dt"] is not None and not o["out"]:
        raise OptionError("--dt sets the sampling of the saved trajectory; give --out FILE.npz too")
    out = str(check_output_path(o["out"], suffix=".npz", force=o["force"])) if o["out"] else None
    bound = bind_scene(scene, "invert", values, preset=o["preset"])
    wf = workflow(bound.scene)
    kw = {**_limits(o), **wf.prepare(bound, "invert", o)}
    return _interruptible(lambda: wf.verbs.invert(bound, out=out, **kw), out=out, dt=o["dt"],
                          meta={"scene": bound.reference, "params": bound.params})


def _limits(o: dict) -> dict:
    """``bounds``, ``objective`` and ``minimum_time`` of ``invctl invert`` from ``--bound``, ``--weight``,
    ``--minimum-time``, ``--energy`` and ``--duration`` (parsed, never evaluated)."""
    from ..inversion import Bounds, Objective

    out: dict[str, Any] = {}
    if o["bound"]:
        out["bounds"] = Bounds.parse(o["bound"])
    if o["weight"]:
        out["objective"] = Objective.parse(o["weight"])
    free = {k: o[k] for k in ("energy", "duration") if o[k] is not None}
    if free and not o["minimum_time"]:
        raise OptionError(f"{', '.join('--' + k for k in free)}: apply to --minimum-time only")
    if o["minimum_time"]:
        if "bounds" not in out and not (o["energy"] or 0) > 0:
            raise OptionError("--minimum-time needs bounds (--bound u=...) or an energy weight (--energy W > 0): "
                              "without either the shortest duration is zero")
        mt: dict[str, Any] = {"energy": float(o["energy"] or 0.0)}
        if o["duration"] is not None:
            lo, sep, hi = o["duration"].partition(":")
            try:
                mt["duration"] = (float(lo), float(hi))
            except ValueError:
                raise OptionError(f"--duration {o['duration']!r}: expected LO:HI in seconds, e.g. 0.2:5") from None
            if not (sep and 0 < mt["duration"][0] < mt["duration"][1] and math.isfinite(mt["duration"][1])):
                raise OptionError(f"--duration {o['duration']!r}: expected LO:HI with 0 < LO < HI")
        out["minimum_time"] = mt
    return out


def design(scene, values=None, **options) -> CommandResult:
    """``invctl design``: the feedback design of the scene (funnel controller, or wrist/damping design)."""
    o = check_options("design", options)
    plot = _figure_path(o["plot"], o["force"]) if o["plot"] else None
    bound = bind_scene(scene, "design", values, preset=o["preset"])
    wf = workflow(bound.scene)
    return wf.verbs.design(bound, plot=plot, **wf.prepare(bound, "design", o))


def simulate(scene, values=None, **options) -> CommandResult:
    """``invctl simulate``: one run of one controller (tracking: C1/C2/C3 on the mismatched plant)."""
    o = check_options("simulate", options)
    plot = _figure_path(o["plot"], o["force"]) if o["plot"] else None
    bound = bind_scene(scene, "simulate", values, preset=o["preset"])
    wf = workflow(bound.scene)
    out = None
    if o["out"]:
        suffix = ".csv" if str(o["out"]).lower().endswith(".csv") else ".npz"
        if suffix == ".csv" and not wf.csv:
            raise OutputPathError(f"--out {o['out']}: contact runs are written as .npz only; use --out FILE.npz")
        out = str(check_output_path(o["out"], suffix=suffix, force=o["force"]))
    kw = wf.prepare(bound, "simulate", o)
    result = _interruptible(lambda: wf.verbs.simulate(bound, out=out, plot=plot, **kw), out=out,
                            meta={"scene": bound.reference, "params": bound.params, "controller": o["controller"]})
    return wf.after_run(bound.scene, result) if wf.after_run else result


def pipeline(scene, values=None, **options) -> CommandResult:
    """``invctl pipeline``: the scene's whole job (tracking: invert, design, C1/C2/C3, compare, figures)."""
    o = check_options("pipeline", options)
    bound = bind_scene(scene, "pipeline", values, preset=o["preset"])
    out_dir = check_output_dir(o["out_dir"])
    wf = workflow(bound.scene)
    kw = wf.prepare(bound, "pipeline", o)
    result = _interruptible(lambda: run_pipeline(bound, wf.verbs.Session(bound, **kw), out_dir=out_dir,
                                                 animate=o["animate"] and not o["no_animation"]),
                            out_dir=out_dir, meta={"scene": bound.reference, "params": bound.params})
    stale = Path(out_dir) / "INTERRUPTED.txt"  # the note of an earlier interrupted run in this folder
    if stale.is_file():
        stale.unlink()
    return wf.after_run(bound.scene, result) if wf.after_run else result


def study(scene, kind: str, values=None, **options) -> CommandResult:
    """``invctl study tradeoff``: speed versus accuracy of the scene's job (table, CSV, JSON, figure)."""
    from .tradeoff import run_tradeoff
    from .tradeoff_specs import spec_for

    if kind != "tradeoff":
        raise SceneError(f"unknown study {kind!r}; available: tradeoff")
    o = check_options("study", options)
    bound = bind_scene(scene, "study", values, preset=o["preset"])
    workflow(bound.scene).prepare(bound, "study", o)
    out = check_output_dir(o["out_dir"])
    smoke = os.environ.get("INVCTL_SMOKE") == "1"
    spec = spec_for(bound.scene, bound.params, bound.settings, smoke=smoke, job=o["job"])
    result = _interruptible(lambda: run_tradeoff(spec, progress=not o["quiet"]), out_dir=out)
    stem = f"tradeoff_{spec.scene}"
    out.mkdir(parents=True, exist_ok=True)
    result.to_csv(out / f"{stem}.csv")
    result.to_json(out / f"{stem}.json")
    close(finish(result.plot().figure, out / f"{stem}.png"))
    data = result.to_dict()
    data["files"] = {ext: str(out / f"{stem}.{ext}") for ext in ("csv", "json", "png")}
    return CommandResult(result.table() + f"\nwritten: {out / f'{stem}.csv'}, .json, .png", data)


def generate(scene, values=None, **options) -> CommandResult:
    """``invctl generate``: a trajectory library, the stable inverse at every point of a grid of scene
    parameters and reference arguments, warm-started from solved neighbours (:mod:`.library`)."""
    from .library import generate as generate_library

    o = check_options("generate", options)
    if not o["grid"]:
        raise OptionError("invctl generate needs at least one --grid NAME=START:STOP:COUNT (a scene parameter "
                          "or a numeric argument of the scene's reference, e.g. --grid 'rf[0]=0.8:1.0:10')")
    bound = bind_scene(scene, "invert", values)
    out = o["out"]
    if out is None:
        out = str(check_output_dir("invctl-out") / f"library_{bound.scene.name}.npz")
        Path(out).parent.mkdir(parents=True, exist_ok=True)
    executor: Any = "serial" if o["workers"] == 1 else None
    client: Any = None
    if o["dask"]:
        try:
            from dask.distributed import Client
        except ImportError:
            raise OptionError("--dask needs dask.distributed (pip install 'dask[distributed]')") from None
        client = executor = Client(o["dask"])
    try:
        lib = generate_library(bound.scene, o["grid"], params=bound.params, out=out, executor=executor,
                               max_workers=o["workers"], backend=o["backend"] or "newton", N=o["N"], scheme=o["scheme"], tol=o["tol"],
                               continuation=not o["no_continuation"], verify=o["verify"], force=o["force"],
                               progress=not o["quiet"], compiled=False if o["no_compile"] else None)
    finally:
        if client is not None:
            client.close()
    return CommandResult(lib.table(), lib.to_dict())

_COMMANDS = {"analyze": analyze, "invert": invert, "design": design, "simulate": simulate, "pipeline": pipeline}


def run_command(command: str, scene, values=None, **options) -> CommandResult:
    """Run ``command`` (one of :data:`invctl.scenes.SCENE_COMMANDS`) on ``scene``."""
    if command not in SCENE_COMMANDS:
        raise SceneError(f"unknown command {command!r}; commands: {', '.join(SCENE_COMMANDS)}")
    import numpy as np

    try:
        if command == "study":
            kind = options.pop("kind", "tradeoff")
            return study(scene, kind, values, **options)
        return _COMMANDS[command](scene, values, **options)
    except (np.linalg.LinAlgError, FloatingPointError, OverflowError, ZeroDivisionError) as exc:
        name = scene.name if isinstance(scene, Scene) else scene
        raise NumericalError(f"{command} {name}: the computation broke down numerically ({type(exc).__name__}: {exc}) "
                             f"with the values {dict(values or {})}; they are outside the range the model can be "
                             "evaluated in (or the model is singular there)") from exc

