"""The ``invctl`` command.

``invctl <command> <scene> [--set name=value ...] [--json] [options]``.  Each
command's options are declared in its own module (``_commands.py``); the
work is done by the scene's handler, so the CLI and notebooks share one call.
"""
from __future__ import annotations

import argparse
import json
import sys
import time

from ..errors import InvctlError
from ..model.params import parse_assignments
from ..scenes import jsonable, load_scene, scene_command
from ._commands import COMMAND_OPTIONS


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="invctl",
        description="Model inversion and tracking control of multibody systems.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (help_text, add_options) in COMMAND_OPTIONS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name == "study":
            p.add_argument("kind", help="which study, e.g. tradeoff")
        p.add_argument("scene", help="scene name in problems/ (e.g. manipulator) or path to a scene file")
        p.add_argument("--set", dest="set", action="append", default=[], metavar="NAME=VALUE",
                       help="override a scene parameter (repeatable)")
        p.add_argument("--json", action="store_true", help="print one JSON object as the last line")
        add_options(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    options = {k: v for k, v in vars(args).items() if k not in ("command", "scene", "set", "json")}
    t0 = time.perf_counter()
    try:
        params = parse_assignments(args.set)
        scene = load_scene(args.scene)
        if args.command == "study" and "study" not in getattr(scene, "COMMANDS", {}):
            from ..studies.commands import study_command

            result = study_command(scene, options.pop("kind"), params, **options)
        else:
            handler = scene_command(scene, args.command)
            result = handler(params, **options)
    except InvctlError as exc:
        print(f"invctl {args.command} {args.scene}: {type(exc).__name__}: {exc}", file=sys.stderr)
        if args.json:
            print(json.dumps(jsonable({"error": type(exc).__name__, "message": str(exc),
                                        "diagnostics": exc.diagnostics})))
        return 2
    wall = time.perf_counter() - t0
    if result.text:
        print(result.text)
    if args.json:
        data = dict(result.data)
        data.setdefault("command_wall_s", wall)
        print(json.dumps(jsonable(data)))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
