"""Which parameter errors cost how much tracking error when only the feedforward acts (C3).

For every parameter ``p`` of a tracking scene and a relative error ``delta``:

* the feedforward change the plant would need, ``du_ff = d u_ff/dp * delta p``, from the parameter
  sensitivities of the stable inverse (:mod:`invctl.inversion.sensitivity`: one factorization of
  the collocation Jacobian for all parameters), checked against the true re-solve of the inverse
  for the perturbed parameters (the first-order prediction error);
* the C3 run (causal feedforward of the nominal model, no feedback, 003 Sect. 6) on plants with
  ``p (1 +- delta)``: the cumulative output error ``int ||y - y_ref|| dt`` and the part the error of
  ``p`` causes, ``int ||e_delta - e_0|| dt`` (``e_0``: the nominal plant's error, which the causal
  cut of the pre-actuation leaves);
* a first-order estimate of that part without simulating the perturbed plant: the nominal plant
  driven by ``u_ff - du_ff`` (to first order the perturbed plant under ``u_ff`` and the nominal
  plant under ``u_ff - du_ff`` deviate alike, because the exact inverse of the perturbed plant is
  ``u_ff + du_ff``).

Rows are sorted by the cost of the error.  The numbers for the manipulator are in
docs/trajectories.md.
"""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import InvctlError, ParameterError
from ..plot import finish
from ..scenes import jsonable


@dataclass
class RobustnessTable:
    """Rows (dicts) per parameter, the nominal C3 error and the settings (:func:`feedforward_robustness`)."""

    rows: list
    nominal: dict
    info: dict = field(default_factory=dict)

    def table(self) -> str:
        d = 100 * self.info["relative"]
        head = (f"{'param':8s} {'value':>9s} {'|du_ff| 1st':>11s} {'re-solve':>9s} {'pred.err':>8s} "
                f"{'dE +':>9s} {'dE -':>9s} {'dE est.':>9s} {'E +':>9s} {'E -':>9s}")
        lines = [f"feedforward only (C3) on {self.info['scene']} with parameter errors of +-{d:g} %: nominal plant "
                 f"E = int ||y - y_ref|| dt = {self.nominal['cumulative']:.4g} (max |e| {self.nominal['max']:.3g}; "
                 "the causal cut of the pre-actuation)",
                 "dE = int ||e - e_nominal|| dt (the cost of the parameter error), est. = first order from du_ff/dp; "
                 "|du_ff| = max_t |d u_ff/dp delta p| over the inputs, re-solve = the exact change",
                 head, "-" * len(head)]
        for r in self.rows:
            if r.get("skipped"):
                lines.append(f"{r['name']:8s} {r['value']:9.4g}  skipped: {r['skipped']}")
                continue
            lines.append(f"{r['name']:8s} {r['value']:9.4g} {r['du_first_order']:11.4g} {r['du_resolve']:9.4g} "
                         f"{r['prediction_error']:8.2g} {r['dE_plus']:9.4g} {r['dE_minus']:9.4g} "
                         f"{r['dE_estimate']:9.4g} {r['E_plus']:9.4g} {r['E_minus']:9.4g}"
                         + (f"  ({r['note']})" if r.get("note") else ""))
        lines.append(f"sensitivities of {len(self.rows)} parameters: {self.info['sensitivity_s']:.3f} s "
                     f"(one factorization); study {self.info['wall_s']:.1f} s")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return jsonable({"rows": self.rows, "nominal": self.nominal, "info": self.info})

    def plot(self, path=None):
        """Bars of the error cost ``dE`` at ``+delta``, ``-delta`` and its first-order estimate per parameter."""
        import matplotlib.pyplot as plt

        rows = [r for r in self.rows if not r.get("skipped")]
        y = np.arange(len(rows))
        fig, ax = plt.subplots(figsize=(7, 0.35 * len(rows) + 1.5))
        for k, (key, lab) in enumerate((("dE_plus", "+delta"), ("dE_minus", "-delta"),
                                        ("dE_estimate", "first-order estimate"))):
            ax.barh(y + (k - 1) * 0.27, [max(r[key], 1e-12) for r in rows], height=0.27, label=lab)
        ax.set_yticks(y, [r["name"] for r in rows])
        ax.invert_yaxis()
        ax.set_xscale("log")
        ax.set_xlabel(f"int ||e - e_nominal|| dt  (parameter error +-{100 * self.info['relative']:g} %)")
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3, axis="x")
        return finish(fig, path)


def _deviation(res, e0, t0):
    """``int ||e - e0|| dt`` on the common part of two runs' grids."""
    k = min(res.t.size, t0.size)
    de = np.linalg.norm((res.y - res.y_ref)[:, :k] - e0[:, :k], axis=0)
    return float(np.trapezoid(de, t0[:k]))


def feedforward_robustness(scene, params=None, names=None, relative: float = 0.1, *,
                           dt: float = 1e-3, t_end: float | None = None, progress: bool = False,
                           inversion_options: dict | None = None) -> RobustnessTable:
    """The robustness table of the module doc for ``names`` (default: every parameter the model carries).

    Parameters
    ----------
    scene : Scene, name or path
    params : dict, optional
        Scene parameter overrides of the nominal model.
    relative : float
        Relative parameter error (0.1: +-10 %).
    dt, t_end : float
        Output step and end of the C3 runs (default: the scene's ``t_end``).
    inversion_options : dict, optional
        Extra keywords of the nominal inversion (default: the scene's, Newton backend).
    """
    from ..inversion.sensitivity import ParametricInverse
    from ..scenes import Scene, load_scene
    from ..simulate.closed_loop import ClosedLoop
    from .tracking import equilibrium_configuration, invert_tracking, tracking_model

    t_start = time.perf_counter()
    if not (np.isfinite(relative) and 0 < relative < 1):
        raise ParameterError(f"relative must be in (0, 1), got {relative}")
    scene = scene if isinstance(scene, Scene) else load_scene(scene)
    scene.require("simulate")
    params, _ = scene.split(params)
    model, ref = tracking_model(scene, params)
    names = [k for k in scene.params if k in model.values] if names is None else list(names)
    unknown = [k for k in names if k not in model.values]
    if unknown:
        raise ParameterError(f"{scene.name}: the model has no parameter(s) {unknown}; known: {sorted(model.values)}")
    inv = invert_tracking(scene, model, ref, **{"backend": "newton", **dict(inversion_options or {})})
    base = ParametricInverse.from_inverse(model, ref, inv)
    sens = base.sensitivities(names)
    t_end = float(scene.tracking.t_end or (ref.tf + (ref.tf - ref.t0))) if t_end is None else float(t_end)
    t = np.linspace(0.0, t_end, int(round(t_end / min(dt, 1e-3))) + 1)
    u_nom = inv.u_causal(t)
    loop = ClosedLoop(model, ref, u_ff=(t, u_nom), t_end=t_end, dt=dt, name="C3")
    q_nom = equilibrium_configuration(scene, model, ref(0.0))
    r0 = loop.run(q_nom, controller_label="C3")
    e0, t0 = r0.y - r0.y_ref, r0.t
    rows = []
    for name in names:
        v = model.values[name]
        row = {"name": name, "value": v}
        if v == 0:
            rows.append({**row, "skipped": "value 0 (a relative error is zero)"})
            continue
        dp = relative * v
        if progress:
            print(f"  {name} = {v:.4g} +- {abs(dp):.3g} ...", file=sys.stderr)
        try:
            du = sens.derivative(name).u_causal(t) * dp
            plant_p = model.with_params(**{name: v + dp})
            plant_m = model.with_params(**{name: v - dp})
            for pl in (plant_p, plant_m):
                scene.check_values({**scene.params, **{k: pl.values[k] for k in scene.params if k in pl.values}})
            true = base.resolve(plant_p).inverse.u_causal(t) - u_nom
            runs = {}
            for s, pl in (("plus", plant_p), ("minus", plant_m)):
                q0 = equilibrium_configuration(scene, pl, ref(0.0), guess=q_nom)
                runs[s] = loop.run(q0, theta=pl.theta_values, controller_label="C3", raise_on_violation=False)
            est_loop = ClosedLoop(model, ref, u_ff=(t, u_nom - du), t_end=t_end, dt=dt, name="C3 estimate")
            q0p = equilibrium_configuration(scene, plant_p, ref(0.0), guess=q_nom)
            est = est_loop.run(q0p, controller_label="C3 estimate", raise_on_violation=False)
        except InvctlError as exc:
            rows.append({**row, "skipped": f"{type(exc).__name__}: {exc}"})
            continue
        row.update({
            "delta": dp, "du_first_order": float(np.max(np.abs(du))), "du_resolve": float(np.max(np.abs(true))),
            "prediction_error": float(np.max(np.abs(du - true)) / max(np.max(np.abs(true)), 1e-300)),
            "E_plus": runs["plus"].cumulative_output_error, "E_minus": runs["minus"].cumulative_output_error,
            "dE_plus": _deviation(runs["plus"], e0, t0), "dE_minus": _deviation(runs["minus"], e0, t0),
            "dE_estimate": _deviation(est, e0, t0),
            "max_e_plus": float(np.max(runs["plus"].output_error)),
            "note": "; ".join(f"{k}: {r.status}" for k, r in runs.items() if not r.success)})
        rows.append(row)
    rows.sort(key=lambda r: -r.get("dE_plus", -1.0))
    info = {"scene": scene.name, "params": params, "relative": relative, "t_end": t_end, "dt": dt,
            "sensitivity_s": sens.wall_s, "wall_s": time.perf_counter() - t_start, "N": inv.N,
            "scheme": inv.scheme}
    return RobustnessTable(rows, {"cumulative": r0.cumulative_output_error,
                                  "max": float(np.max(r0.output_error))}, info)
