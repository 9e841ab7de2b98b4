"""``invctl invert <scene>``: stable inversion of a scene, report, JSON, ``.npz``."""
from __future__ import annotations

import sys
import time

import numpy as np

from ..errors import SceneError
from ..scenes import CommandResult, scene_name
from .scene import invert_scene, scene_defaults
from .verify import forward_check

_OPTIONS = {"N", "scheme", "tol", "out", "dt", "quiet", "backend"}


def invert_command(scene, params: dict, **options) -> CommandResult:
    """Handler of ``invctl invert``: invert with the scene's defaults, forward-check, report.

    JSON data: ``status``, ``iterations``, ``build_s``, ``solve_s``, ``max_output_error``,
    ``N``, ``scheme``, ``residuals``, ``meshes`` (with ``--tol``), ``u_before_t0`` ...
    """
    name = scene_name(scene)
    unknown = sorted(k for k, v in options.items() if k not in _OPTIONS and v not in (None, False))
    if unknown:
        raise SceneError(f"{name}: invert does not take option(s) {unknown}")
    scene_defaults(scene)
    if options.get("dt") is not None and not options.get("out"):
        raise SceneError(f"{name}: --dt sets the sampling of the saved trajectory; give --out FILE.npz too")
    if options.get("dt") is not None and not options["dt"] > 0:
        raise SceneError(f"{name}: --dt must be positive, got {options['dt']}")
    if options.get("N") is not None and options["N"] < 4:
        raise SceneError(f"{name}: --N must be at least 4, got {options['N']}")
    if options.get("scheme") is not None:
        from .collocation import get_scheme

        try:
            get_scheme(options["scheme"])
        except ValueError as exc:
            raise SceneError(f"{name}: --scheme: {exc}") from None
    if options.get("tol") is not None and not options["tol"] > 0:
        raise SceneError(f"{name}: --tol must be positive, got {options['tol']}")
    quiet = bool(options.get("quiet"))
    opts = {"progress": not quiet}
    for k in ("N", "scheme", "tol", "backend"):
        if options.get(k) is not None:
            opts[k] = options[k]
    t_wall = time.perf_counter()
    model = scene.build(**(params or {}))
    reference = scene.reference(model)
    inv = invert_scene(scene, params, model=model, reference=reference, **opts)
    fc = forward_check(model, inv, reference)
    wall = time.perf_counter() - t_wall
    d = inv.diagnostics
    tt = np.linspace(inv.T0, inv.t0, 200, endpoint=False)
    pre = float(np.max(np.abs(inv.u(tt)))) if tt.size else 0.0
    data = {
        "scene": name, "status": d["status"], "success": d["success"], "iterations": d["iterations"],
        "build_s": d["build_s"], "solve_s": d["solve_s"], "wall_s": wall, "N": inv.N, "scheme": d["scheme"],
        "backend": d["backend"], "formulation": d["formulation"], "T0": inv.T0, "Tf": inv.Tf,
        "t0": inv.t0, "tf": inv.tf, "selection": d["selection"], "max_output_error": fc["error"],
        "forward_check": {k: fc[k] for k in ("error", "t_worst", "window", "windows", "rate")},
        "residuals": d["residuals"], "max_u_pre_actuation": pre, "params": dict(params or {}),
    }
    if "meshes" in d:
        data["meshes"] = d["meshes"]
    lines = [
        f"invctl invert {name}: {d['status']} after {d['iterations']} iterations ({d['backend']}, "
        f"{d['scheme']}, N = {inv.N}, {d['formulation']} index reduction)",
        f"  horizon [T0, Tf] = [{inv.T0:g}, {inv.Tf:g}] around [t0, tf] = [{inv.t0:g}, {inv.tf:g}]",
        f"  boundary conditions (003 (36)): {d['selection']}",
        f"  build {d['build_s']:.3f} s, solve {d['solve_s']:.3f} s, total {wall:.2f} s",
        f"  residuals: position {d['residuals']['position']:.2e}, velocity "
        f"{max(d['residuals']['velocity_mesh'], d['residuals']['velocity_between']):.2e}, acceleration "
        f"{max(d['residuals']['acceleration_mesh'], d['residuals']['acceleration_between']):.2e}",
        f"  forward check: max |y - y_ref| = {fc['error']:.3e} at t = {fc['t_worst']:.3g} s "
        f"({fc['windows']} window(s))",
        f"  pre-actuation: max |u_ff| before t0 = {pre:.3g} (the causal feedforward sets it to 0)",
    ]
    if "meshes" in d:
        lines.append("  meshes tried: " + ", ".join(f"N={m['N']} (err {m['error']:.1e})" for m in d["meshes"]))
    if options.get("out"):
        inv.to_npz(options["out"], options.get("dt"))
        data["out"] = str(options["out"])
        lines.append(f"  trajectory written to {options['out']}")
    if not quiet:
        print(f"invert {name}: done in {wall:.2f} s", file=sys.stderr)
    return CommandResult("\n".join(lines), data)
