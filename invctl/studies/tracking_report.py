"""The commands of tracking scenes (003): analyze, invert, design, simulate, pipeline.

Each function takes the :class:`~invctl.scenes.BoundScene` (the scene, its values, its model) and the
command's options (already checked by :mod:`invctl.studies.commands` and the workflow) and returns a
:class:`~invctl.scenes.CommandResult` whose text is built only from what the scene declares.
"""
from __future__ import annotations

import sys
import time
from typing import Any

import numpy as np

from ..plot import close
from ..scenes import CommandResult
from . import pipeline
from .pipeline import Step
from .reports import add_reports, write_run
from .tracking import (CONTROLLERS, NEEDS_INVERSE, TrackingStudy, check_controller, compare_runs, design_configuration,
                       invert_tracking, output_structure, run_controller, setup_tracking, tracking_linearization,
                       tracking_model)

#: frames per second of the animations the pipeline writes (GIF delays are whole 1/100 s: 10, 20, 25, 50 are exact)
ANIMATION_FPS = 20


def _fmt(M) -> str:
    M = np.atleast_2d(M)
    return "[" + "; ".join(" ".join(f"{v:10.5g}" for v in row) for row in M) + "]"


# ------------------------------------------------------------------ analyze
def analyze(bound, *, samples: int = 200) -> CommandResult:
    """Relative degree, Gamma, internal dynamics (two routes), linearization, (A1)/(A2), eta2_ref^0."""
    from ..analysis.summary import analyze as analyze_model

    t0 = time.perf_counter()
    scene, params, model = bound.scene, bound.params, bound.model
    t = scene.tracking
    ref = t.reference(model) if t.reference is not None else None
    point = design_configuration(scene, model, ref)
    if output_structure(model, point).r_bar == 2 * model.n:
        return _analyze_flat(scene, model, ref, point, samples, t0)
    setup: dict[str, Any] = {"point": point}
    if ref is not None and model.region is None:
        from ..analysis.equilibrium import operating_points

        setup["points"] = list(operating_points(model, ref, 11, guess_q=point))
    elif ref is None and model.region is None:
        setup["points"] = [point]
    if ref is not None:
        setup["reference"] = ref
        setup["linearization"] = tracking_linearization(scene, model, ref, samples=samples)
        setup["internal"] = setup["linearization"].internal
    elif t.internal_coordinates is not None:
        from ..analysis import internal_dynamics

        setup["internal"] = internal_dynamics(model, "sect3", t.internal_coordinates(model), point=point,
                                              samples=samples)
    a1 = {name: dict(v) for name, v in t.a1.items()}
    fb = dict(t.feedback)
    if all(k in fb for k in ("K", "k_i", "rho")):
        a1["K of the declared feedback"] = {k: fb[k] for k in ("K", "k_i", "rho")}
    if a1:
        setup["A1"] = a1
    res = analyze_model(model, setup, samples)
    rd, internal, lin, checks = res["rd"], res["internal"], res["lin"], res["checks"]
    wall = time.perf_counter() - t0
    p, l, m = rd.blocks
    eig = lin.eigenvalues
    lines = _header(scene, model, rd, f"l = {l}, p = {p}, m = {m}") + [
        f"  worst condition number {rd.worst_condition:.4g} at q = {np.round(rd.worst_point[0], 4).tolist()}",
        f"  smallest singular value {rd.min_singular_value:.4g}; det Gamma in [{rd.det_range[0]:.4g}, "
        f"{rd.det_range[1]:.4g}]",
        f"internal dynamics: dimension 2n - r_bar = {internal.dim} ({internal.method}, {internal.coordinates})",
        f"  checks: max |L_K phi| = {checks['L_K_phi_max']:.2g}, min sigma(Phi') = "
        f"{checks['Phi_prime_sigma_min']:.3g} at the design point"
        + (f", Sect. 2 vs Sect. 3 rhs differ by {checks['sect2_vs_sect3_max_diff']:.2g} (relative, near the "
           "linearization points)" if checks["sect2_vs_sect3_max_diff"] is not None else ""),
    ]
    if checks.get("Phi_prime_singular_sample") is not None:
        lines.append(f"  Phi' singular at {checks['Phi_prime_singular_count']} of {rd.samples} region samples "
                     "(the coordinates are local; a sample of the singular set: q = "
                     f"{np.round(checks['Phi_prime_singular_sample'], 5).tolist()})")
    lines += [
        f"linearization (37) at {len(lin.points)} point(s)"
        + (f" (configurations in the region: {lin.diagnostics['points_in_region']})"
           if "points_in_region" in lin.diagnostics else "")
        + ", derivative removal (38): eta' = Q eta + P y",
        f"  Q = {_fmt(lin.Q)}",
        f"  P = {_fmt(lin.P)}",
        f"  eigenvalues of Q: {np.round(eig, 6).tolist()}  ({lin.k} in the closed right half plane)",
    ]
    zeros = res["zeros"]
    if zeros is not None:
        lines.append(f"  zeros of the plant linearized at the design point: {zeros.describe()}")
    elif "zeros_error" in checks:
        lines.append(f"  zeros not classified: {checks['zeros_error']}")
    if lin.k:
        lines.append(f"  split (39, T by {lin.split}): Q~ = {_fmt(lin.Q_tilde)}, P~ = {_fmt(lin.P_tilde)}")
    lines.append(f"  (A2): {'holds' if checks['A2']['passed'] else 'NOT shown'} - {checks['A2']['message']}")
    for name, rep in checks.get("A1_all", {}).items():
        lines.append(
            f"  (A1), {name} (rho = {rep['rho']}): {'holds' if rep['passed'] else 'does NOT hold'} on all "
            f"region samples ({100 * rep['fraction_satisfied']:.0f}% of {rep['samples']} points; min eig of sym. "
            f"part {rep['min_eig_sym']:.3g}, at the design point {rep['min_eig_at_design_point']:.3g})")
    if res["eta2_ref0"] is not None:
        lines.append(f"  eta2_ref^0 by (43): {np.round(res['eta2_ref0'], 6).tolist()}")
    rdata = add_reports(lines, scene, model, params, {}, "analyze")
    lines.append(f"analysis time {wall:.3f} s")
    data = {
        "scene": scene.name, "params": dict(model.values), "relative_degree": list(rd.r_aux), "r_hat": rd.r_hat,
        "r_bar": rd.r_bar, "gamma": rd.to_dict(), "internal_dim": internal.dim, "internal_method": internal.method,
        "internal_eigs": eig.real.tolist() if np.all(eig.imag == 0) else [[e.real, e.imag] for e in eig],
        "minimum_phase": zeros.minimum_phase if zeros is not None else lin.minimum_phase,
        "zeros": zeros.to_dict() if zeros is not None else None, "Q": lin.Q, "P": lin.P, "P_list": lin.P_list, "T": lin.T, "k": lin.k,
        "Q_tilde": lin.Q_tilde, "P_tilde": lin.P_tilde, "eta2_ref0": res["eta2_ref0"], "checks": checks,
        "design_point": point, "reports": rdata, "timings": {**res["timings"], "total_s": wall},
    }
    return CommandResult("\n".join(lines), data)


def _header(scene, model, rd, sizes, r_bar_note="") -> list[str]:
    """The first lines of an analysis: the scene, its parameters, the relative degree, Gamma's heading."""
    head = [f"invctl analyze {scene.name}: n = {model.n}, {sizes}"]
    return head + ([f"  {scene.description}"] if scene.description else []) + [
        "parameters: " + ", ".join(f"{k}={v:.6g}" for k, v in model.values.items()),
        f"vector relative degree of the auxiliary ODE (10): {list(rd.r_aux)}  ->  r_hat = {rd.r_hat}, "
        f"r_bar = {rd.r_bar}{r_bar_note}",
        f"high-gain matrix Gamma on {rd.samples} points of {rd.region or 'the sample box'}:",
    ]


def _analyze_flat(scene, model, ref, point, samples, t0) -> CommandResult:
    """The analysis of an output without internal dynamics (r_bar = 2n: a flat output)."""
    from ..analysis import relative_degree

    points = None
    if model.region is None:
        from ..analysis.equilibrium import operating_points

        points = list(operating_points(model, ref, 11, guess_q=point)) if ref is not None else [point]
    rd = relative_degree(model, samples=samples, points=points)
    lines = _header(scene, model, rd, f"m = {model.m}", " = 2n") + [
        f"  worst condition number {rd.worst_condition:.4g}, smallest singular value {rd.min_singular_value:.4g}",
        "internal dynamics: none (r_bar = 2n): the output is flat; the state and the input are algebraic "
        f"functions of y_ref and its first {rd.r_hat} derivatives (no pre- or post-actuation)",
    ]
    rdata = add_reports(lines, scene, model, {}, {}, "analyze")
    wall = time.perf_counter() - t0
    lines.append(f"analysis time {wall:.3f} s")
    data = {"scene": scene.name, "params": dict(model.values), "relative_degree": list(rd.r_aux), "r_hat": rd.r_hat,
            "r_bar": rd.r_bar, "gamma": rd.to_dict(), "internal_dim": 0, "minimum_phase": True, "flat": True,
            "design_point": point, "reports": rdata, "timings": {"total_s": wall}}
    return CommandResult("\n".join(lines), data)


# ------------------------------------------------------------------- invert
def invert(bound, *, N=None, scheme=None, tol=None, backend=None, out=None,
           dt=None, quiet=False, max_wall_time=None, bounds=None, objective=None, minimum_time=None) -> CommandResult:
    """Invert with the automatic setup (and the scene's overrides), forward-check, report.  ``bounds``
    (and ``objective``): the bounded inversion; ``minimum_time``: the shortest transition under them."""
    from ..inversion import forward_check

    opts = {k: v for k, v in {"N": N, "scheme": scheme, "tol": tol, "backend": backend,
                              "max_wall_time": max_wall_time, "bounds": bounds, "objective": objective,
                              "minimum_time": minimum_time}.items() if v is not None}
    t_wall = time.perf_counter()
    scene, params = bound.scene, bound.params
    model, reference = tracking_model(scene, params, model=bound.model)
    inv = invert_tracking(scene, model, reference, progress=not quiet, **opts)
    free = inv.diagnostics.get("free_time")
    # the retimed reference of a minimum-time transition is the one the inverse must track
    if free:
        from ..inversion import retime

        reference = retime(reference, free["duration"])
    fc = forward_check(model, inv, reference)
    wall = time.perf_counter() - t_wall
    d = inv.diagnostics
    # pre-actuation: how far u_ff moves away from the start equilibrium's input before t0
    tt = np.linspace(inv.T0, inv.t0, 200)
    pre = float(np.max(np.abs(inv.u(tt) - inv.u(inv.T0)))) if inv.t0 > inv.T0 else 0.0
    res = d.get("residuals", {})
    data = {
        "scene": scene.name, "method": d.get("method", "servo"), "status": d["status"], "success": d["success"],
        "iterations": d.get("iterations"), "build_s": d.get("build_s"), "solve_s": d.get("solve_s"), "wall_s": wall,
        "N": inv.N, "scheme": d.get("scheme"), "backend": d.get("backend"), "formulation": d.get("formulation"),
        "T0": inv.T0, "Tf": inv.Tf, "t0": inv.t0, "tf": inv.tf, "selection": d.get("selection"),
        "max_output_error": fc["error"], "forward_check": {k: fc[k] for k in ("error", "t_worst", "window", "windows", "rate")},
        "residuals": res, "max_u_pre_actuation": pre, "params": dict(params or {}), "plan": d.get("plan"),
    }
    for key in ("meshes", "bounds", "tracking", "free_time"):
        if key in d:
            data[key] = d[key]
    if d.get("method") == "normal-form":
        lines = [f"invctl invert {scene.name}: {d['status']} (normal form of 003 Sect. 2: relative degree "
                 f"{d.get('relative_degree')}, internal dynamics of dimension {d.get('internal_dim')}; "
                 f"{d.get('representation')}, N = {inv.N})",
                 f"  horizon [T0, Tf] = [{inv.T0:g}, {inv.Tf:g}] around [t0, tf] = [{inv.t0:g}, {inv.tf:g}]: "
                 f"{d.get('horizon', {}).get('describe', '')}"]
    else:
        lines = [
            f"invctl invert {scene.name}: {d['status']} after {d['iterations']} iterations ({d['backend']}, "
            f"{d['scheme']}, N = {inv.N}, {d['formulation']} index reduction)",
            f"  horizon [T0, Tf] = [{inv.T0:g}, {inv.Tf:g}] around [t0, tf] = [{inv.t0:g}, {inv.tf:g}]",
            f"  boundary conditions (003 (36)): {d['selection']}",
        ]
        plan = d.get("plan")
        if isinstance(plan, dict) and plan.get("describe"):
            lines.append("  automatic setup: " + plan["describe"].replace("\n", "\n  "))
    worst: dict[str, Any] = {}
    for k, v in res.items():
        if isinstance(v, (int, float)):
            key = k.rsplit("_", 1)[0] if k.endswith(("_mesh", "_between")) else k
            worst[key] = max(worst.get(key, 0.0), float(v))
    lines += [
        f"  build {d.get('build_s', 0.0):.3f} s, solve {d.get('solve_s', 0.0):.3f} s, total {wall:.2f} s",
        "  residuals: " + ", ".join(f"{k} {v:.2e}" for k, v in worst.items()),
        f"  forward check: max |y - y_ref| = {fc['error']:.3e} at t = {fc['t_worst']:.3g} s "
        f"({fc['windows']} window(s))",
        f"  pre-actuation: max |u_ff - u_ff(T0)| before t0 = {pre:.3g}"
        + (" (the causal feedforward leaves it out)" if pre > 0 else " (none)"),
    ]
    if "meshes" in d:
        lines.append("  meshes tried: " + ", ".join(f"N={m['N']} (err {m['error']:.1e})" for m in d["meshes"]))
    lines += _limit_lines(d)
    if out:
        if dt is not None:
            from .workflow import check_saved_samples

            rows = 1 + 2 * model.n + model.ell + model.p + 2 * model.m + model.ny
            check_saved_samples(inv.Tf - inv.T0, dt, rows, more=f" of the horizon [{inv.T0:g}, {inv.Tf:g}]",
                                partial=inv)
        written = inv.to_npz(out, dt, meta={"scene": bound.reference, "params": dict(params)})
        data["out"] = str(written)
        lines.append(f"  trajectory written to {written}")
    if not quiet:
        print(f"invert {scene.name}: done in {wall:.2f} s", file=sys.stderr)
    return CommandResult("\n".join(lines), data, inv)


def _limit_lines(d: dict) -> list[str]:
    """Report lines of a bounded or minimum-time inversion (none for a square one)."""
    lines = []
    b, tr, ft = d.get("bounds"), d.get("tracking"), d.get("free_time")
    if ft:
        act = ", ".join(f"{a.get('bound', '?')} {a.get('side', '')} {a.get('value', '')} at t = "
                        + ", ".join(f"{i[0]:.4g}" if i[0] == i[1] else f"[{i[0]:.4g}, {i[1]:.4g}]"
                                    for i in a.get("intervals", []))
                        if isinstance(a, dict) else str(a) for a in ft.get("active", [])) or "none"
        lines.append(f"  minimum time: duration {ft['duration']:.6g} s (the reference's {ft['reference_duration']:.6g} s"
                     f"), energy {ft['energy']:.4g} (weight {ft['energy_weight']:g}); active bounds: {act}"
                     + ("; AT THE LIMIT of the duration range searched" if ft.get("at_duration_limit") else "")
                     + ("; no bound is active: the duration is limited by the model (shorter moves of this shape "
                        "have no exact inverse nearby), not by the bounds" if ft.get("limited_by") == "model" else ""))
    if tr is not None:
        if tr.get("exact"):
            lines.append("  bounds: the exact inverse meets them (it is the answer)")
        else:
            lines.append(f"  bounds: exact tracking is not possible within them; least-squares tracking with max "
                         f"|y - y_ref| = {tr['max_output_error']:.3g} (RMS {tr['rms_output_error']:.3g})")
    if b:
        if b.get("describe"):
            lines.append("  " + str(b["describe"]).replace("\n", "\n  "))
        margins = b.get("margins") or {}
        if margins and tr is not None and tr.get("exact"):
            lines.append("  margins: " + ", ".join(f"{k} {v:.3g}" for k, v in margins.items()
                                                      if isinstance(v, (int, float))))
        if "max_violation_between_nodes" in b:
            lines.append(f"  bounds checked on the returned trajectory ({b['samples_per_interval']} points per mesh "
                         f"interval): largest violation {b['max_violation_between_nodes']:.3g}")
    return lines


# ------------------------------------------------------------------- design
def design(bound, *, plot=None) -> CommandResult:
    """The funnel controller (48) of the scene: new output (41), (A1), funnels and gains, with the reasons."""
    scene = bound.scene
    setup = setup_tracking(scene, bound.params, invert=False, model=bound.model)
    d, c = setup.design, setup.controller
    lines = [f"invctl design {scene.name}: funnel controller (48) of 003 Sect. 5",
             (f"  linearized internal dynamics: {setup.lin.k} unstable mode(s) of {setup.lin.Q.shape[0]}"
              if setup.lin is not None else "  no internal dynamics (flat output): y_new = K y"),
             f"  q = {c.q_rows}, k_i = {list(c.k_i)}, rho = {c.rho}, pairing = {list(c.pairing)}",
             "  K = " + "; ".join(np.array2string(np.asarray(k), precision=5) for k in c.K),
             f"  relative degrees of the new output: {list(c.levels.r)}",
             f"  (A1) margin at the design point {d.a1_design_point:.4g}, smallest over the design points "
             f"{float(np.min(d.a1_points)):.4g} ({d.a1_points.size} points)",
             "  " + d.describe().replace("\n", "\n  ")]
    data = d.to_dict()
    if plot:
        from ..plot.tracking import plot_funnels

        write_run(lines, data, None, plot=plot, draw=lambda p: plot_funnels(c, setup.t_end, p))
    return CommandResult("\n".join(lines), data, d)


def load_inverse(path, bound):
    """The saved inverse of ``simulate --inverse``: its recorded scene, sizes and parameters must be ``bound``'s."""
    from ..errors import ResultFileError
    from ..inversion import Inverse

    inv, params = Inverse.load(path), bound.params
    recorded, here = inv.meta.get("scene"), bound.reference
    if recorded is not None and recorded != here:
        raise ResultFileError(f"--inverse {path}: the inverse was computed for scene {recorded!r}, not {here!r}")
    model = bound.model
    sizes = {"n": model.n, "l": model.ell, "p": model.p, "m": model.m}
    if {k: int(inv.sizes.get(k, -1)) for k in sizes} != sizes:
        raise ResultFileError(f"--inverse {path}: its sizes {dict(inv.sizes)} are not those of {bound.scene.name!r} {sizes}")
    saved = {k: float(v) for k, v in dict(inv.meta.get("params") or {}).items()}
    if saved != {k: float(v) for k, v in params.items()}:
        raise ResultFileError(f"--inverse {path}: the inverse was computed with the parameters {saved}, this run "
                              f"uses {dict(params)}; pass the same --set values or invert again")
    return inv


# ----------------------------------------------------------------- simulate
def _step(dt) -> dict:
    """``dt=`` for :func:`setup_tracking` when given (its default otherwise)."""
    return {} if dt is None else {"dt": dt}


def simulate(bound, *, controller=None, plant_params=None, t_end=None, out=None, plot=None, inverse=None, quiet=False,
             dt=None, integrator=None) -> CommandResult:
    """One closed-loop run of ``controller`` (C1, C2, C3, C1-42) on the mismatched plant (output step ``dt``,
    CVODES settings ``integrator``: see :func:`~invctl.studies.tracking.setup_tracking`)."""
    name = (controller or "C1").upper()
    t0 = time.perf_counter()
    scene, params, settings = bound.scene, bound.params, bound.settings
    setup = setup_tracking(scene, params, plant_params, inverse=inverse, invert=name in ("C1", "C3", "C1-42"),
                           t_end=t_end, progress=not quiet, integrator=integrator, model=bound.model, **_step(dt))
    res = run_controller(setup, name)
    wall_total = time.perf_counter() - t0
    s = res.summary()
    plant_diff = {k: v for k, v in setup.plant.values.items() if v != setup.model.values[k]}
    lines = [f"invctl simulate {scene.name} --controller {name} ({CONTROLLERS[name]}), plant: "
             + (", ".join(f"{k}={v:.6g}" for k, v in plant_diff.items()) or "= reference model")]
    for kind, val in res.cumulative_errors.items():
        lines.append(f"  cumulative {kind} error  int ||{kind} - ref|| dt = {val:.6g}")
    lines.append(f"  final output error = {s['final_output_error']:.4g}")
    if not res.success:
        lines.append(f"  status {res.status}: {res.message}")
    if s["max_funnel_ratio"] is not None:
        lines.append(f"  max funnel ratio phi|e| = {s['max_funnel_ratio']:.4f} (margin {s['funnel_margin']:.4f})")
    lines += [f"  input peaks |u| = {[round(x, 4) for x in s['input_peaks']]}",
              f"  max constraint drift = {s['max_constraint_drift']:.3g}",
              f"  closed loop {s['wall_s']:.3f} s wall (setup {wall_total - s['wall_s']:.2f} s)"]
    data = {**s, "setup_timings": setup.timings, "total_wall_s": wall_total, "plant": plant_diff}
    if rdata := add_reports(lines, scene, setup.model, params, settings, "simulate", result=res, controller=name):
        data["reports"] = rdata
    write_run(lines, data, res, out=out, meta={**setup.meta(), "controller": name}, plot=plot)
    return CommandResult("\n".join(lines), data, res)


# ----------------------------------------------------------------- pipeline
class Session(pipeline.Session):
    """The tracking pipeline's session (:mod:`.pipeline`): one setup (inverse, design) for C1, C2, C3 (and the
    scene's other controllers) on the mismatched plant; the comparison of 003 Sect. 6 and its figures."""

    def __init__(self, bound, *, t_end=None, plant_params=None, quiet=False, dt=None, integrator=None):
        self.scene, self.params, self.quiet = bound.scene, bound.params, quiet
        self.controllers = tuple(check_controller(c) for c in self.scene.tracking.controllers)
        self.setup = setup_tracking(self.scene, self.params, plant_params, t_end=t_end, progress=not quiet,
                                    invert=bool(set(NEEDS_INVERSE) & set(self.controllers)), integrator=integrator,
                                    model=bound.model, **_step(dt))

    def run(self, name):
        if not self.quiet:
            print(f"simulating {name} ({CONTROLLERS.get(name, '?')}) ...", file=sys.stderr)
        res = run_controller(self.setup, name, raise_on_violation=False)  # kept, truncated at a violation
        return Step(res, [], res.summary())

    def meta(self, name):
        return self.setup.meta()

    def animation(self, name):
        return {"fps": ANIMATION_FPS}

    def finish(self, runs, out):
        study = compare_runs(self.scene, self.params, self.setup, runs)
        study.save(out, runs=False)  # the runs are written already
        close(study.plot(out))
        return [study.table()], study.to_dict()

    def interrupted(self, runs, out, note):
        """The complete runs as a study (``study.json``, loadable with ``invctl.load``), marked partial."""
        return [str(TrackingStudy(runs, {"scene": self.scene.name, "partial": note}, self.setup).save(out, runs=False))]
