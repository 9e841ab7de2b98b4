"""The ``invctl`` command.

``invctl <command> <scene> [--set name=value ...] [--json] [options]`` runs one of the commands of
:mod:`invctl.studies.commands` (the same calls notebooks and scripts use); ``invctl animate RUN.npz``
draws a saved run.  With ``--json`` the last line of output is one JSON object: the command's data,
or ``{"error": <class>, "message": ..., "diagnostics": ...}``.

Exit codes: 0 success; 2 a specific error (:mod:`invctl.errors`, docs/errors.md; usage errors too);
3 an internal error (a bug: ``INVCTL_DEBUG=1`` shows the traceback); 130 interrupted (Ctrl-C), with
what was complete saved next to the requested output (``"partial"``: the files).
"""
from __future__ import annotations

import argparse
import json
import sys
import time

from ..errors import InvctlError, ResourceLimitError, check_interrupt, remember_sigint
from ..scenes import jsonable

_HELP = {
    "analyze": "relative degree, internal dynamics, stability analysis of a scene",
    "invert": "stable inversion by servo constraints and collocation (feedforward with pre-actuation)",
    "design": "feedback design of a scene (funnel controller; wrist damping)",
    "simulate": "one closed-loop or contact run of a scene",
    "pipeline": "the scene's whole job (tracking: invert, design, C1/C2/C3, compare, figures)",
    "study": "studies: speed-versus-accuracy trade-off",
    "animate": "draw a saved run of a scene as a GIF/MP4",
    "generate": "a trajectory library: stable inverses over a grid of end points, durations, parameters",
}


class _UsageError(Exception):
    pass


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        raise _UsageError(f"{self.prog}: {message}")


def build_parser() -> argparse.ArgumentParser:
    from ..studies.commands import options_of

    parser = _Parser(prog="invctl", description="Model inversion and tracking control of multibody systems.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_Parser)
    for name in ("analyze", "invert", "design", "simulate", "pipeline", "study", "generate"):
        p = sub.add_parser(name, help=_HELP[name], description=_HELP[name])
        if name == "study":
            p.add_argument("kind", help="which study: tradeoff")
        p.add_argument("scene", help="scene name in invctl_scenes/ (e.g. manipulator) or path to a scene file")
        p.add_argument("--set", dest="set", action="append", default=[], metavar="NAME=VALUE",
                       help="override a scene parameter or setting (repeatable)")
        p.add_argument("--json", action="store_true", help="print one JSON object as the last line")
        for opt_name, opt in options_of(name).items():
            flag = "--" + opt_name.replace("_", "-")
            if opt.flag:
                p.add_argument(flag, dest=opt_name, action="store_true", help=opt.help)
            elif opt.repeat:
                p.add_argument(flag, dest=opt_name, action="append", default=[], metavar=opt.metavar, help=opt.help)
            else:
                p.add_argument(flag, dest=opt_name, type=str, default=None,
                               help=opt.help + (f" (default {opt.default})" if opt.default is not None else ""))
    p = sub.add_parser("animate", help=_HELP["animate"], description=_HELP["animate"])
    p.add_argument("run", help="a run written by invctl (simulate/pipeline/invert --out FILE.npz)")
    p.add_argument("--out", default=None, help="output file (.gif or .mp4; default: next to the run)")
    p.add_argument("--fps", default="25", help="frames per second (default 25)")
    p.add_argument("--speed", default="1", help="playback speed (default 1: real time)")
    p.add_argument("--scene", default=None, metavar="NAME_OR_PATH",
                   help="the scene to draw with (default: the shipped scene the run records; a scene file is "
                        "code and is loaded only when named here)")
    p.add_argument("--force", action="store_true", help="replace an existing output file")
    p.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    return parser


def _error(command, target, exc, as_json) -> int:
    print(f"invctl {command} {target}: {type(exc).__name__}: {exc}", file=sys.stderr)
    if as_json:
        print(json.dumps(jsonable({"error": type(exc).__name__, "message": str(exc),
                                    "diagnostics": getattr(exc, "diagnostics", {})})))
    return 2


def _memory_advice(command: str) -> str:
    """What to try after running out of memory, naming only options ``command`` takes."""
    if command == "animate":
        return "use a lower --fps or a higher --speed"
    from ..studies.commands import options_of

    opts = options_of(command)
    hints = [h for k, h in (("t_end", "a shorter run (--t-end)"), ("dt", "a larger --dt"),
                            ("N", "fewer intervals (--N)"), ("record_every", "a sparser record (--record-every)"))
             if k in opts]
    return "use " + ", ".join(hints + ["smaller sizes or horizons in the --set values"])


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        args = build_parser().parse_args(argv)
    except _UsageError as exc:
        print(str(exc), file=sys.stderr)
        if "--json" in argv:
            print(json.dumps({"error": "UsageError", "message": str(exc), "diagnostics": {}}))
        return 2
    t0 = time.perf_counter()
    target = getattr(args, "scene", getattr(args, "run", ""))
    with remember_sigint():
        return _run(args, target, t0)


def _run(args, target: str, t0: float) -> int:
    try:
        if args.command == "animate":
            from ..studies.animation import animate_run

            result = animate_run(args.run, out=args.out, fps=args.fps, speed=args.speed, force=args.force,
                                 scene=args.scene)
        else:
            from ..model.params import parse_assignments
            from ..studies.commands import run_command

            options = {k: v for k, v in vars(args).items() if k not in ("command", "scene", "set", "json")}
            values = parse_assignments(args.set, words=True)
            if args.command == "generate":
                from ..studies.commands import generate

                result = generate(args.scene, values, **options)
            else:
                result = run_command(args.command, args.scene, values, **options)
        # a Ctrl-C that a compiled library swallowed after the command's last check (e.g. in its last chunk)
        check_interrupt("interrupted as the command finished; what it wrote is complete")
    except InvctlError as exc:
        return _error(args.command, target, exc, args.json)
    except MemoryError as exc:  # an allocation no estimate foresaw: a resource limit, not a bug
        import os

        if os.environ.get("INVCTL_DEBUG"):
            raise
        return _error(args.command, target, ResourceLimitError(
            f"ran out of memory ({exc or 'MemoryError'}); {_memory_advice(args.command)}"), args.json)
    except Exception as exc:  # a bug: say so, without a traceback unless asked for
        import os

        if os.environ.get("INVCTL_DEBUG"):
            raise
        exc_msg = f"{type(exc).__name__}: {exc}"
        print(f"invctl {args.command} {target}: internal error ({exc_msg}); this is a bug in invctl - "
              "rerun with INVCTL_DEBUG=1 for the traceback and report it", file=sys.stderr)
        if args.json:
            print(json.dumps(jsonable({"error": "InternalError", "message": exc_msg, "diagnostics": {}})))
        return 3
    except KeyboardInterrupt as exc:
        saved = list(getattr(exc, "saved", []) or [])
        msg = str(exc) or "interrupted by the user"
        if saved:
            shown = saved if len(saved) <= 5 else saved[:3] + [f"... ({len(saved)} files; all in the JSON)"]
            where = f"; partial results written to {', '.join(shown)}"
        elif getattr(exc, "partial", None) is not None:
            where = "; the partial result was not saved: no output was requested (--out)"
        else:
            where = ""
        try:
            print(f"invctl {args.command} {target}: interrupted: {msg}{where}", file=sys.stderr)
            if args.json:
                print(json.dumps(jsonable({"error": "RunInterrupted", "message": msg + where, "partial": saved,
                                           "diagnostics": getattr(exc, "diagnostics", {})})))
        except KeyboardInterrupt:  # a second Ctrl-C while reporting
            pass
        return 130
    wall = time.perf_counter() - t0
    try:
        if result.text:
            print(result.text)
        if args.json:
            data = dict(result.data)
            data.setdefault("command_wall_s", wall)
            print(json.dumps(jsonable(data)))
    except BrokenPipeError:  # the reader (e.g. head) went away
        return 0
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
