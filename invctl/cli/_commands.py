"""Options of each ``invctl`` command (the scene handler receives them as keywords).

A handler must accept every option of its command; options a scene cannot
honour must raise a clear error rather than be ignored.
"""
from __future__ import annotations

import argparse


def _analyze(p: argparse.ArgumentParser) -> None:
    p.add_argument("--samples", type=int, default=200, help="sample points of the operating region for checks")


def _invert(p: argparse.ArgumentParser) -> None:
    p.add_argument("--N", type=int, default=None, help="number of collocation intervals (default: scene's)")
    p.add_argument("--scheme", default=None, help="collocation scheme, e.g. hermite-simpson, legendre3, radau3")
    p.add_argument("--tol", type=float, default=None, help="requested output error: refine the mesh until met")
    p.add_argument("--out", default=None, help="write the trajectory to this .npz file")
    p.add_argument("--dt", type=float, default=None, help="sampling step of the saved trajectory")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.add_argument("--backend", default=None, choices=["ipopt", "newton"],
                   help="solver of the collocation equations (default ipopt)")


def _simulate(p: argparse.ArgumentParser) -> None:
    p.add_argument("--controller", default=None, help="controller name (scene-specific, e.g. C1, C2, C3)")
    p.add_argument("--plant-set", dest="plant_set", action="append", default=[], metavar="NAME=VALUE",
                   help="override a parameter of the simulated plant only (repeatable)")
    p.add_argument("--t-end", dest="t_end", type=float, default=None, help="simulation end time")
    p.add_argument("--out", default=None, help="write the trajectory to this .npz file")
    p.add_argument("--plot", default=None, help="write a figure to this file (.png/.pdf)")


def _design(p: argparse.ArgumentParser) -> None:
    p.add_argument("--plot", default=None, help="write a figure to this file (.png/.pdf)")


def _study(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out-dir", dest="out_dir", default="invctl-out", help="folder for tables and figures")
    p.add_argument("--job", default=None, help="which job's trade-off when a scene has several "
                   "(manipulator: invert (default) or simulate)")
    p.add_argument("--quiet", action="store_true", help="no progress output")


def _pipeline(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out-dir", dest="out_dir", default="invctl-out", help="folder for figures and data")
    p.add_argument("--t-end", dest="t_end", type=float, default=None, help="simulation end time")
    p.add_argument("--quiet", action="store_true", help="no progress output")


COMMAND_OPTIONS = {
    "analyze": ("relative degree, internal dynamics, stability analysis of a scene", _analyze),
    "invert": ("stable inversion by servo constraints and collocation (feedforward)", _invert),
    "simulate": ("closed-loop simulation of a scene", _simulate),
    "design": ("design tools of a scene (e.g. wrist damping)", _design),
    "study": ("studies: speed-versus-accuracy trade-off, sweeps", _study),
    "pipeline": ("the scene's full job (manipulator: invert, simulate C1/C2/C3, compare, plot)", _pipeline),
}
