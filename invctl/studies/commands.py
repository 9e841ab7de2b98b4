"""The ``invctl`` commands, written once against :class:`invctl.scenes.Scene`.

Every command takes a scene (object, name or path), the ``--set`` values and its options, checks
the options once (:data:`OPTIONS`), checks output paths before any computation, and dispatches to
the module of the scene's kind (:mod:`.tracking_report`, :mod:`.contact`, :mod:`.switched_report`).
The same calls serve the command line and, through the scene's methods, notebooks and scripts::

    scene = invctl.load_scene("cartpole", mp=0.3)
    res = scene.run("invert", N=300)          # this module's invert(): res.text, res.data, res.result
    inv = scene.invert(N=300)                 # the typed result alone

Around every run: the memory a long run records is estimated before it starts
(:class:`~invctl.errors.ResourceLimitError` naming the option that fits); a contact run whose
penetration is large against the clearance warns or fails with the numbers; Ctrl-C
(:class:`~invctl.errors.RunInterrupted`) saves what is complete next to the requested output
(``x.partial.npz``, ``tradeoff_<scene>.partial.csv``, the runs of a pipeline with a note) and
re-raises with ``exc.saved`` naming the files.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, replace
from typing import Any, Callable

from pathlib import Path

from ..errors import (InvctlError, NumericalError, OptionError, ParameterError, ResourceLimitError, RunInterrupted,
                      SceneError, SimulationFailed, watch_sigint)
from ..io import check_output_dir, check_output_path
from ..scenes import SCENE_COMMANDS, CommandResult, Scene, load_scene
from .pipeline import run_pipeline
from .workflow import workflow

__all__ = ["OPTIONS", "Option", "run_command", "analyze", "invert", "design", "simulate", "pipeline", "study"]



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
    "no_animation": Option(bool, "do not write animations of the runs", ("pipeline",), False, flag=True),
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


def _scene(scene) -> Scene:
    return scene if isinstance(scene, Scene) else load_scene(scene)


def _kind(scene: Scene):
    return workflow(scene).verbs


def _plant_params(items, scene: Scene | None = None) -> dict:
    """``--plant-set`` values, checked against the scene before any work (names, applicability)."""
    from ..model.params import parse_assignments

    plant = dict(items) if isinstance(items, dict) else parse_assignments(items, option="--plant-set")
    if plant and scene is not None:
        if not workflow(scene).plant_mismatch:
            raise OptionError(f"scene {scene.name!r}: the controller (3) uses no plant model, so plant and model "
                              "parameters coincide; --plant-set is not applicable (use --set)")
        unknown = sorted(set(plant) - set(scene.params))
        if unknown:
            raise ParameterError(f"--plant-set: unknown plant parameter(s) {unknown}; known: {sorted(scene.params)}")
    return plant


def _figure_path(path, force):
    from ..errors import OutputPathError

    p = check_output_path(path, force=force, option="--plot")
    if p.suffix.lower() not in _FIGURE_SUFFIXES:
        raise OutputPathError(f"--plot {path}: use one of {', '.join(_FIGURE_SUFFIXES)}")
    return p


# ---------------------------------------------------------------- resources
#: below this many samples a run is never large (no model is built to estimate it)
_SMALL = 2e5
#: share of the available memory a run may plan to use
_MEMORY_SHARE = 0.75


def usable_memory() -> float:
    """Bytes a run may plan to use: 75 % of the available memory (``MemAvailable``), or
    ``INVCTL_MAX_MEMORY`` (bytes, e.g. ``4e9``) when that is smaller."""
    avail = math.inf
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    avail = float(line.split()[1]) * 1024
                    break
    except OSError:
        try:
            avail = float(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
        except (ValueError, OSError, AttributeError):
            pass
    limit = _MEMORY_SHARE * avail
    env = os.environ.get("INVCTL_MAX_MEMORY")
    if env:
        try:
            limit = min(limit, float(env))
        except ValueError:
            raise ParameterError(f"INVCTL_MAX_MEMORY={env!r}: expected a number of bytes (e.g. 4e9)") from None
    return limit


def _gib(b: float) -> str:
    return f"{b / 2**30:.3g} GiB"


#: seconds a run may plan to take unless ``INVCTL_MAX_TIME`` says otherwise
MAX_TIME_S = 1800.0


def usable_time() -> float:
    """Seconds a run may plan to take: ``INVCTL_MAX_TIME`` (seconds), default :data:`MAX_TIME_S`."""
    env = os.environ.get("INVCTL_MAX_TIME")
    if not env:
        return MAX_TIME_S
    try:
        t = float(env)
    except ValueError:
        t = math.nan
    if not (math.isfinite(t) and t > 0):
        raise ParameterError(f"INVCTL_MAX_TIME={env!r}: expected a positive number of seconds (e.g. 7200)")
    return t


def _duration(s: float) -> str:
    return f"{s:.3g} s" if s < 120 else f"{s / 60:.3g} min" if s < 7200 else f"{s / 3600:.3g} h"


def check_budget(what: str, count: int, seconds_each: float, bytes_each: float, fits: str, *,
                 diagnostics: dict | None = None) -> None:
    """Refuse ``count`` units of work before it starts when ``count * seconds_each`` exceeds
    :func:`usable_time` or ``count * bytes_each`` exceeds :func:`usable_memory`.

    ``what`` names the command and the option as typed; ``fits`` is the advice with ``{fit}``, the
    largest count within both budgets.

    Raises
    ------
    ResourceLimitError
    """
    limit_t, limit_m = usable_time(), usable_memory()
    secs, need = count * seconds_each, count * bytes_each
    if secs <= limit_t and need <= limit_m:
        return
    fit = int(min(limit_t / seconds_each if seconds_each > 0 else math.inf,
                  limit_m / bytes_each if bytes_each > 0 else math.inf))
    over = " and ".join(x for x, bad in ((f"{_duration(secs)} (budget {_duration(limit_t)}: INVCTL_MAX_TIME "
                                          "seconds)", secs > limit_t),
                                         (f"{_gib(need)} of memory (usable {_gib(limit_m)}: "
                                          f"{int(100 * _MEMORY_SHARE)} % of the available memory or "
                                          "INVCTL_MAX_MEMORY)", need > limit_m)) if bad)
    raise ResourceLimitError(f"{what} would take about {over}; {fits.format(fit=fit)}",
                             diagnostics={**(diagnostics or {}), "count": count, "seconds_estimated": secs,
                                          "seconds_budget": limit_t, "bytes_needed": need,
                                          "bytes_usable": limit_m, "count_that_fits": fit})




def _check_samples(scene: Scene, params, samples: int) -> None:
    """``analyze --samples``: time and memory of the sampled checks (switched scenes use at most 720)."""
    cost = workflow(scene).sample_cost
    if cost is None or samples <= 1000:
        return
    model = scene.model(params)
    per_s, per_s_constrained, per_b = cost
    if model.region is not None and model.region.constraints:
        per_s = per_s_constrained
    check_budget(f"{scene.name}: analyze --samples {samples}", samples, per_s, per_b * model.n * model.n,
                 "use --samples {fit} or less (the default, 200, samples the region well)")


def check_resources(command: str, scene: Scene, params, settings, o) -> None:
    """Estimate the memory a command's run records (before it starts).

    Raises
    ------
    ResourceLimitError
        The estimate exceeds :func:`usable_memory`; the message names the horizon (and step) that fit.
    """
    if command == "invert":
        return _check_inversion(scene, params, o)
    sizer = workflow(scene).run_size
    size = sizer(command, scene, params, o) if sizer else None
    if size is None:
        return
    samples, runs, step, t_end, t_opt, h_opt = size
    if not samples * runs > _SMALL:
        return
    n = gaps = m = ny = 0
    wf = workflow(scene)
    if wf.builds_model:
        model = scene.model(params)
        n, gaps, m, ny = model.n, len(model.gaps), model.m, model.ny
    per = 8.0 * wf.doubles(n, gaps, m, ny)
    need = samples * runs * per
    limit = usable_memory()
    if need <= limit:
        return
    fit_t = limit / (runs * per) * step
    fits = f"use {t_opt}{fit_t:.3g} or less"
    if h_opt:
        fits += f", or {h_opt}{step * need / limit:.3g} or more"
    raise ResourceLimitError(
        f"{scene.name}: {command} would record {samples:.3g} samples (t_end = {t_end:g} s at a step of {step:g} s"
        + (f", {runs} runs" if runs > 1 else "") + f"): about {_gib(need)} of memory, but {_gib(limit)} is usable "
        f"({int(100 * _MEMORY_SHARE)} % of the available memory or INVCTL_MAX_MEMORY); {fits}",
        diagnostics={"samples": samples, "runs": runs, "bytes_needed": need, "bytes_usable": limit,
                     "t_end_that_fits": fit_t})


#: bytes per collocation interval of an inversion (transcription, IPOPT and MUMPS together):
#: ``600 (s nx)^1.7`` with ``s`` = 2 (Hermite-Simpson) or d + 1 (d-stage Legendre/Radau); measured peak RSS
#: growth per interval: manipulator (nx = 14) 108 KB (HS) and 490 KB (radau3), cartpole (nx = 5) 19 KB
#: (HS); the formula gives 172, 561 and 30 KB
_INVERSION_BYTES = (600.0, 1.7)
#: seconds per byte of that estimate: cartpole HS from N = 4000 to 20000 took 0.45 ms more per interval
#: (estimate 30 KB per interval)
_INVERSION_SECONDS_PER_BYTE = 1.5e-8


def _check_inversion(scene: Scene, params, o, command: str = "invert") -> None:
    """``--N`` of an inversion (``invert``, the base solve of ``generate``): time and memory of the
    transcription and its solver (:data:`_INVERSION_BYTES`) within the budgets (:func:`check_budget`)."""
    N = o.get("N")
    if N is None or N <= 2000:
        return
    from ..inversion.schemes import get_scheme

    sch = get_scheme(o.get("scheme") or "hermite-simpson")
    stages = sch.stages
    model = scene.model(params)
    nx = 2 * model.n + model.ell + model.p + model.m
    per = _INVERSION_BYTES[0] * (stages * nx) ** _INVERSION_BYTES[1]
    check_budget(f"{scene.name}: {command} --N {N} ({sch.name}, {nx} unknowns per node)", N,
                 per * _INVERSION_SECONDS_PER_BYTE, per,
                 "use --N {fit} or less (or --tol to refine only where needed)",
                 diagnostics={"N_that_fits": int(min(usable_memory() / per,
                                                     usable_time() / (per * _INVERSION_SECONDS_PER_BYTE)))})


def check_saved_samples(duration: float, dt: float, rows: int, *, more: str = "", partial=None) -> None:
    """A trajectory saved at step ``dt`` over ``duration`` (``rows`` signals) must fit in memory
    (``partial``: the solved inverse, kept in the error).

    Raises
    ------
    ResourceLimitError
        It would not; the message names the ``--dt`` that fits.
    """
    samples = duration / dt + 1
    per = 16.0 * rows  # the sampled signals and their interpolation temporaries
    need, limit = samples * per, usable_memory()
    if need <= limit:
        return
    fit = duration * per / limit
    raise ResourceLimitError(
        f"invert --dt {dt:g}: the saved trajectory would have {samples:.3g} samples ({duration:g} s{more}): about "
        f"{_gib(need)} of memory, but {_gib(limit)} is usable; use --dt {fit:.3g} or more, or leave out --dt (1000 "
        "samples over the horizon)", partial=partial,
        diagnostics={"samples": samples, "bytes_needed": need, "bytes_usable": limit, "dt_that_fits": fit})


def _check_dt(scene: Scene, params, o) -> None:
    """``--dt`` against the memory before the solve, over the reference's transition (the horizon adds the
    pre- and post-actuation; :func:`check_saved_samples` checks it again after the solve)."""
    if o["dt"] is None:
        return
    from .tracking import tracking_model

    model, ref = tracking_model(scene, params)
    duration = ref.tf - ref.t0
    if o["minimum_time"]:  # the transition is retimed; its shortest length is known only from --duration
        if o["duration"] is None:
            return
        duration = min(duration, float(o["duration"].partition(":")[0]))
    rows = 1 + 2 * model.n + model.ell + model.p + 2 * model.m + model.ny
    check_saved_samples(duration, o["dt"], rows, more=" of the reference's transition alone, before the pre- and "
                                                      "post-actuation")


# ------------------------------------------------------------- after a run
#: a contact run warns when it penetrates more than this share of the clearance, and fails beyond 1
GAP_WARN = 0.1


def _check_contact_data(name: str, d: dict) -> tuple[str | None, str | None]:
    """(warning, failure) texts for one contact run's data: its largest penetration against the
    clearance the scene declares (``Contact.clearance``) or, by default, the largest gap at the start
    (the free room of a joint started in its clearance, the drop height of a ball; the largest gap seen
    later would count the penetration of one side of a joint as room on the other).  A run that starts
    with every contact closed and declares no clearance gives no scale: not judged."""
    viol, gaps0 = d.get("max_gap_violation"), d.get("initial_gaps")
    if viol is None or not gaps0:
        return None, None
    room = d.get("clearance") or max(gaps0)
    if d.get("clearance") is None and room <= 1e-12:
        return None, None
    ratio = viol / room if room > 0 else (math.inf if viol > 0 else 0.0)
    d["clearance_scale"], d["gap_violation_ratio"] = room, ratio
    source = "the clearance the scene declares" if d.get("clearance") else "the largest gap at the start"
    what = f"{name}: the largest penetration {viol:.3g} is {ratio:.3g} times the clearance scale ({source}, {room:.3g})"
    fix = "use a smaller step (--set h=...), the projection (--set projection=1) or a larger clearance"
    if not ratio <= 1.0:
        return None, f"{what}: the contacts of this run are not resolved; {fix}"
    if ratio > GAP_WARN:
        return f"warning: {what}; {fix}", None
    return None, None


def check_contact_result(scene: Scene, result: CommandResult) -> CommandResult:
    """Warn about, or fail on, the penetration of the runs in ``result`` (simulate or pipeline)."""
    runs = result.data["runs"] if "runs" in result.data else {result.data.get("controller", scene.name): result.data}
    warnings, failures = [], []
    for name, d in runs.items():
        w, f = _check_contact_data(f"{scene.name} ({name})", d)
        warnings += [w] if w else []
        failures += [f] if f else []
    if failures:
        written = result.data.get("out") or result.data.get("out_dir")
        raise SimulationFailed("; ".join(failures) + (f" (the run was written to {written})" if written else ""),
                               partial=result, diagnostics={"runs": {k: {kk: v.get(kk) for kk in (
                                   "max_gap_violation", "clearance_scale", "gap_violation_ratio")}
                                   for k, v in runs.items()}})
    if warnings:
        result.data.setdefault("warnings", []).extend(warnings)
        result.text = result.text + "\n" + "\n".join(warnings)
    return result


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
    except Exception as err:  # noqa: BLE001 - the interruption is what must reach the user
        exc.args = (f"{note}; writing the partial result failed ({type(err).__name__}: {err})",)


def _interruptible(run, **where):
    """``run()``, saving what is complete on Ctrl-C (see :func:`_save_partial`). A failure after a
    SIGINT is the interruption (compiled solvers turn Ctrl-C into their own errors)."""
    with watch_sigint() as sigint:
        try:
            return run()
        except RunInterrupted as exc:
            _save_partial(exc, **where)
            raise
        except KeyboardInterrupt as exc:
            ri = RunInterrupted(str(exc) or "interrupted")
        except Exception as exc:
            if not sigint.seen:
                raise
            ri = RunInterrupted(f"interrupted (the solver stopped with {type(exc).__name__}: {str(exc)[:200]})",
                                partial=getattr(exc, "partial", None) if isinstance(exc, InvctlError) else None)
    _save_partial(ri, **where)
    raise ri from None


def _load_inverse(path, scene: Scene, params) -> Any:
    """A saved inverse for ``scene``: its recorded scene and its sizes must be this scene's."""
    from ..errors import ResultFileError
    from ..inversion import Inverse
    from ..scenes import scene_reference

    inv = Inverse.load(path)
    recorded, here = inv.meta.get("scene"), scene_reference(scene)
    if recorded is not None and recorded != here:
        raise ResultFileError(f"--inverse {path}: the inverse was computed for scene {recorded!r}, not {here!r}")
    model = scene.model(params)
    sizes = {"n": model.n, "l": model.ell, "p": model.p, "m": model.m}
    if {k: int(inv.sizes.get(k, -1)) for k in sizes} != sizes:
        raise ResultFileError(f"--inverse {path}: its sizes {dict(inv.sizes)} are not those of {scene.name!r} {sizes}")
    saved = {k: float(v) for k, v in dict(inv.meta.get("params") or {}).items()}
    if saved != {k: float(v) for k, v in params.items()}:
        raise ResultFileError(f"--inverse {path}: the inverse was computed with the parameters {saved}, this run "
                              f"uses {dict(params)}; pass the same --set values or invert again")
    return inv


# ------------------------------------------------------------------ commands
def analyze(scene, values=None, **options) -> CommandResult:
    """``invctl analyze``: what the scene's kind analyses (relative degree and internal dynamics for
    tracking scenes, Theorem 1 for switched ones, declared reports for contact scenes)."""
    scene = _scene(scene)
    scene.require("analyze")
    o = check_options("analyze", options)
    params, settings = scene.split(values, preset=o["preset"])
    _check_samples(scene, params, o["samples"])
    return _kind(scene).analyze(scene, params, settings, samples=o["samples"])


def invert(scene, values=None, **options) -> CommandResult:
    """``invctl invert``: the stable inversion (feedforward with pre-actuation), forward-checked."""
    scene = _scene(scene)
    scene.require("invert")
    o = check_options("invert", options)
    if o["dt"] is not None and not o["out"]:
        raise OptionError("--dt sets the sampling of the saved trajectory; give --out FILE.npz too")
    out = str(check_output_path(o["out"], suffix=".npz", force=o["force"])) if o["out"] else None
    params, settings = scene.split(values, preset=o["preset"])
    limits = _limits(scene, o)
    check_resources("invert", scene, params, settings, o)
    _check_dt(scene, params, o)
    from ..scenes import scene_reference

    return _interruptible(lambda: _kind(scene).invert(scene, params, settings, N=o["N"], scheme=o["scheme"],
                                                      tol=o["tol"], backend=o["backend"], out=out, dt=o["dt"],
                                                      quiet=o["quiet"], max_wall_time=o["max_wall_time"], **limits),
                          out=out, dt=o["dt"], meta={"scene": scene_reference(scene), "params": params})


def _limits(scene: Scene, o: dict) -> dict:
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
    workflow(scene).check_options(scene, {k: o[k] for k in ("bound", "weight", "minimum_time")})
    return out


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
        if suffix == ".csv" and not workflow(scene).csv:
            from ..errors import OutputPathError

            raise OutputPathError(f"--out {o['out']}: contact runs are written as .npz only; use --out FILE.npz")
        out = str(check_output_path(o["out"], suffix=suffix, force=o["force"]))
    plot = _figure_path(o["plot"], o["force"]) if o["plot"] else None
    params, settings = scene.split(values, preset=o["preset"])
    kw = dict(controller=o["controller"], plant_params=_plant_params(o["plant_set"], scene), t_end=o["t_end"], out=out,
              plot=plot, quiet=o["quiet"], **_recording(scene, o), **_integration(scene, o))
    if o["inverse"]:
        workflow(scene).check_options(scene, {"inverse": o["inverse"]})
        kw["inverse"] = _load_inverse(o["inverse"], scene, params)
    check_resources("simulate", scene, params, settings, o)
    from ..scenes import scene_reference

    result = _interruptible(lambda: _kind(scene).simulate(scene, params, settings, **kw), out=out,
                            meta={"scene": scene_reference(scene), "params": params, "controller": o["controller"]})
    check = workflow(scene).after_run
    return check(scene, result) if check else result


def _recording(scene: Scene, o: dict) -> dict:
    """The recording options of a contact run (``--record-every``, ``--record``); an error for other kinds."""
    given = {k: o[k] for k in ("record_every", "record") if o.get(k) is not None}
    workflow(scene).check_options(scene, given)
    return given


def _integration(scene: Scene, o: dict) -> dict:
    """The closed-loop options of a tracking run (``--dt``, ``--rtol``, ``--atol``, ``--max-steps``); an error
    for other kinds."""
    keys = ("rtol", "atol", "max_steps")
    given = [k for k in ("dt",) + keys if o.get(k) is not None]
    workflow(scene).check_options(scene, {k: o[k] for k in given})
    out = {"integrator": {"max_num_steps" if k == "max_steps" else k: o[k] for k in keys if o.get(k) is not None}}
    if o.get("dt") is not None:
        out["dt"] = o["dt"]
    return out if given else {}


def pipeline(scene, values=None, **options) -> CommandResult:
    """``invctl pipeline``: the scene's whole job (tracking: invert, design, C1/C2/C3, compare, figures)."""
    scene = _scene(scene)
    scene.require("pipeline")
    o = check_options("pipeline", options)
    params, settings = scene.split(values, preset=o["preset"])
    plant = _plant_params(o["plant_set"], scene)
    check_resources("pipeline", scene, params, settings, o)
    out_dir = check_output_dir(o["out_dir"])
    from ..scenes import scene_reference

    rec = {**_recording(scene, o), **_integration(scene, o)}

    def run():
        session = _kind(scene).Session(scene, params, settings, t_end=o["t_end"], plant_params=plant, quiet=o["quiet"],
                                       **rec)
        return run_pipeline(scene, session, params, out_dir=out_dir, animate=not o["no_animation"])

    result = _interruptible(run, out_dir=out_dir, meta={"scene": scene_reference(scene), "params": params})
    stale = Path(out_dir) / "INTERRUPTED.txt"  # the note of an earlier interrupted run in this folder
    if stale.is_file():
        stale.unlink()
    check = workflow(scene).after_run
    return check(scene, result) if check else result


def study(scene, kind: str, values=None, **options) -> CommandResult:
    """``invctl study tradeoff``: speed versus accuracy of the scene's job (table, CSV, JSON, figure)."""
    from .tradeoff import run_tradeoff
    from .tradeoff_specs import spec_for

    scene = _scene(scene)
    scene.require("study")
    if kind != "tradeoff":
        raise SceneError(f"unknown study {kind!r}; available: tradeoff")
    o = check_options("study", options)
    params, settings = scene.split(values, preset=o["preset"])
    check_resources("study", scene, params, settings, o)
    out = check_output_dir(o["out_dir"])
    smoke = os.environ.get("INVCTL_SMOKE") == "1"
    spec = spec_for(scene, params, settings, smoke=smoke, job=o["job"])
    result = _interruptible(lambda: run_tradeoff(spec, progress=not o["quiet"]), out_dir=out)
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
        raise OptionError("invctl generate needs at least one --grid NAME=START:STOP:COUNT (a scene parameter "
                          "or a numeric argument of the scene's reference, e.g. --grid 'rf[0]=0.8:1.0:10')")
    out = o["out"]
    if out is None:
        out = str(check_output_dir("invctl-out") / f"library_{scene.name}.npz")
        Path(out).parent.mkdir(parents=True, exist_ok=True)
    params, _settings = scene.split(values)
    executor: Any = "serial" if o["workers"] == 1 else None
    client: Any = None
    if o["dask"]:
        try:
            from dask.distributed import Client
        except ImportError:
            raise OptionError("--dask needs dask.distributed (pip install 'dask[distributed]')") from None
        client = executor = Client(o["dask"])
    try:
        lib = generate_library(scene, o["grid"], params=params, out=out, executor=executor, max_workers=o["workers"],
                               backend=o["backend"] or "newton", N=o["N"], scheme=o["scheme"], tol=o["tol"],
                               continuation=not o["no_continuation"], verify=o["verify"], force=o["force"],
                               progress=not o["quiet"], compiled=False if o["no_compile"] else None)
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

