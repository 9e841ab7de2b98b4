"""The commands of switched position/force scenes (002): analyze, simulate, design, pipeline.

The scene's ``build`` returns a :class:`~invctl.studies.switched.SwitchedProblem`; a compliant wrist is
recognised by its parameters (``kt``), and is analysed by its reduced model (27)-(28).
"""
from __future__ import annotations

import math

import numpy as np

from ..errors import OptionError, RunInterrupted, SceneError, StabilityError
from ..scenes import CommandResult
from . import pipeline
from .pipeline import Step
from .reports import write_run
from .switched import (design_bf_min, design_bt_min, design_bt_visible, design_kt_max, effective_wall, error_system,
                       lambda_map, lambda_point, lambda_sweep, reduction_check, simulate_scenario)


def analyze(bound, *, samples: int = 200) -> CommandResult:
    """Theorem 1 (visible eigenvectors, Lambda three ways, GUAS) and Theorem 2 (ISS)."""
    from ..stability.conewise import analyze as analyze_system

    if samples < 8:
        raise OptionError(f"--samples {samples}: need at least 8 initial directions for the ISS constant")
    scene, p = bound.scene, bound.model.params
    s = error_system(p)
    rep = analyze_system(s, with_iss=True, n_angles=min(int(samples), 720))
    head = f"scene {scene.name}: switched motion/force control against a stiff wall (002)"
    data = rep.to_dict()
    if scene.switched.wrist:
        ke_bar, be_bar = effective_wall(p["kt"], p["bt"], p["ke"])
        head += (f"\n  compliant wrist analysed by its reduced model (27)-(28): ke_bar = {ke_bar:.6g} N/m, "
                 f"be_bar = {be_bar:.6g} Ns/m")
        # time-scale separation (26) on which the reduction rests
        ratios = {"Mt/M": p["Mt"] / p["M"], "kt/ke": p["kt"] / p["ke"],
                  "be/bt": p["be"] / p["bt"] if p["bt"] > 0 else math.inf, "bt/ke [s]": p["bt"] / p["ke"]}
        weak = [f"{k} = {v:.3g}" for k, v in ratios.items() if v > 0.1]
        rc = reduction_check(p)
        head += ("\n  slow poles, full 4-state loop vs reduced model: relative distance "
                 f"{rc['free']['rel_error']:.3g} (free), {rc['contact']['rel_error']:.3g} (contact)")
        weak += [f"{k} pole distance {v['rel_error']:.3g}" for k, v in rc.items() if v["rel_error"] > 0.1]
        data["reduction_pole_error"] = {k: v["rel_error"] for k, v in rc.items()}
        head += "\n  assumptions (26): " + ", ".join(f"{k} = {v:.3g}" for k, v in ratios.items())
        if weak:
            head += f"\n  WARNING: (26) is not well satisfied ({', '.join(weak)}): the reduced model may be inaccurate"
        data.update({"ke_bar": ke_bar, "be_bar": be_bar, "assumptions_26": ratios, "reduction_ok": not weak})
    return CommandResult(head + "\n" + rep.summary(), data)




def _run(bound, t_end=None):
    """The exact switched run (and, for the compliant wrist, the reduced model's run): ``(sim, reduced or None,
    text, data)``."""
    scene, p = bound.scene, bound.model.params
    name = scene.name
    sim = simulate_scenario(p, t_end=t_end, label=name)
    text = sim.summary()
    data = sim.to_dict()
    red = None
    if scene.switched.wrist:
        try:
            red = simulate_scenario(p, reduced=True, t_end=t_end, label=f"{name} (reduced model)")
        except RunInterrupted as exc:  # the full model's run is complete: that is what --out writes
            exc.args = (f"{name}: the run of the reduced model was interrupted; the full model's run is complete "
                        "and in exc.partial",)
            exc.partial = sim
            raise
        data["reduced"] = red.to_dict()
        text += "\n" + red.summary()
    return sim, red, text, data


def _figure(sim, red, path) -> None:
    import matplotlib.pyplot as plt

    from ..plot import save
    from ..plot.switched import plot_simulation

    fig = sim.plot() if red is None else plot_simulation(sim, overlay=red, overlay_label="(reduced)")[0].figure
    save(fig, path)
    plt.close(fig)


def simulate(bound, *, controller=None, plant_params=None, t_end=None, out=None, plot=None,
             quiet=False) -> CommandResult:
    """Exact switched simulation; peak force, bounces, force RMS error (the workflow has refused --plant-set)."""
    if controller is not None:
        raise SceneError(f"scene {bound.scene.name!r} has one controller, the switched law 002 (3); "
                         "--controller is not applicable (change its gains with --set kp=..., bf=...)")
    sim, red, text, data = _run(bound, t_end)
    lines = [text]
    write_run(lines, data, sim, out=out, plot=plot, what="trajectory", draw=lambda p: _figure(sim, red, p))
    return CommandResult("\n".join(lines), data, sim)


def design(bound, *, plot=None) -> CommandResult:
    """Smallest bt, largest kt (wrist) or smallest bf (rigid wall) with GUAS."""
    scene, p = bound.scene, bound.model.params
    q = lambda_point(p)
    data: dict = {"Lambda": None if q.visible else q.Lambda, "visible_eigenvector": q.visible, "guas": q.guas,
                  "bf": p["bf"]}
    lines = [f"scene {scene.name}: design by Theorem 1 (002 Sect. 5.3)"]
    if not scene.switched.wrist:
        bf_min = design_bf_min(p)
        data["bf_min"] = bf_min
        data["bf_min_numerical"] = design_bf_min(p, method="numerical")
        lines.append(f"  smallest controller damping bf with GUAS: {bf_min:.8g} Ns/m "
                     f"(numerical return map: {data['bf_min_numerical']:.8g})")
        lines.append(f"  at bf = {p['bf']:.6g}: " + ("visible eigenvector" if q.visible else
                                                     f"Lambda = {q.Lambda:.6g}") + f", GUAS {q.guas}")
    else:
        bt_min = design_bt_min(p)
        data["bt_min"] = bt_min
        data["bt_min_numerical"] = design_bt_min(p, method="numerical")
        data["kt_max"] = design_kt_max(p)
        data["kt_max_numerical"] = design_kt_max(p, method="numerical")
        try:
            data["bt_visible"] = design_bt_visible(p)
        except StabilityError:
            data["bt_visible"] = None
        data.update({"kt": p["kt"], "bt": p["bt"]})
        bt_txt = (f"GUAS already at the lower end of the search, bt = {bt_min:.6g}" if bt_min <= 1.0 else
                  f"bt_min = {bt_min:.8g} Ns/m (numerical return map: {data['bt_min_numerical']:.8g})")
        kt_txt = (f"GUAS up to the end of the search, kt = {data['kt_max']:.6g} N/m" if data["kt_max"] >= 1e9 else
                  f"kt_max = {data['kt_max']:.8g} N/m (numerical: {data['kt_max_numerical']:.8g})")
        lines += [
            f"  at kt = {p['kt']:.6g} N/m, bf = {p['bf']:.6g} Ns/m: smallest wrist damping bt with Lambda < 1: "
            + bt_txt,
            f"  at bt = {p['bt']:.6g} Ns/m: largest wrist stiffness kt with GUAS: " + kt_txt,
            "  bounce-free (visible stable eigenvector) from bt = "
            + (f"{data['bt_visible']:.8g} Ns/m" if data["bt_visible"] is not None else
               "-- none for bt in [1, 1e6] at this kt"
               + (" (A_1 has complex eigenvalues, and no real contact eigenvector enters S_2)"
                  if error_system(p).damping_case(1) == "complex" else "")),
            f"  design point bt = {p['bt']:.6g}: " + ("visible eigenvector" if q.visible else
                                                      f"Lambda = {q.Lambda:.6g}") + f", GUAS {q.guas}",
        ]
    if plot:
        from ..plot import close, save
        from ..plot.switched import plot_lambda_curve, plot_lambda_map

        if scene.switched.wrist:
            m = lambda_map(p, np.geomspace(3e3, 1e6, 40), np.geomspace(10, 3000, 40))
            ax = plot_lambda_map(m["kt"], m["bt"], m["Lambda"], m["visible"], design=(p["kt"], p["bt"]))
        else:
            sw = lambda_sweep(p, "bf", np.geomspace(1, 1e5, 120))
            ax = plot_lambda_curve(sw["values"], sw["Lambda"], sw["visible"])
        ax.figure.tight_layout()
        save(ax.figure, plot)
        close(ax)
        lines.append(f"  figure written to {plot}")
    return CommandResult("\n".join(lines), data)


class Session(pipeline.Session):
    """The switched pipeline's session (:mod:`.pipeline`): the analysis and the design (``design.png``) first,
    then the one controller, the switched law 002 (3) (``run_switched.npz``, ``run_switched.png``)."""

    controllers = ("switched",)

    def __init__(self, bound, *, t_end=None, plant_params=None, quiet=False):
        self.bound, self.t_end = bound, t_end
        self._reduced = None

    def head(self, out):
        a = analyze(self.bound)
        d = design(self.bound, plot=out / "design.png")
        return [a.text, "", d.text, ""], {"analyze": a.data, "design": d.data}

    def run(self, name):
        sim, self._reduced, text, data = _run(self.bound, self.t_end)
        return Step(sim, [text], data)

    def figure(self, name, step, out):
        _figure(step.trajectory, self._reduced, out / f"run_{name}.png")
