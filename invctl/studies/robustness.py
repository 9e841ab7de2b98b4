"""Ready-made robustness and parameter sweeps on :func:`invctl.studies.sweep.sweep`.

Each sweep runs on any ``concurrent.futures.Executor`` (a local process pool
by default) or a ``dask.distributed.Client`` unchanged, reports failed points
with their exception instead of dropping them, and returns a
:class:`~invctl.studies.sweep.SweepResult` whose ``plot`` draws a heat map.

* :func:`funnel_mismatch` -- the tracking study of 003 Sect. 6 over a grid of
  plant mismatches (``m3`` factor x another parameter's factor): cumulative
  output and end-effector errors, the largest funnel ratio, input peaks; a run
  that leaves its funnel is a failed point (``FunnelViolation``).
* :func:`wrist_lambda_map` -- the return-map factor Lambda of the compliant
  wrist (002 Sect. 5) over ``(kt, bt)`` by the closed form (14)-(16) *and* the
  numerical return map, with the GUAS verdict and visible eigenvectors.
* :func:`clearance_grid` -- the prismatic clearance (000 Example 3) under PD
  (36) on body 1 over restitution x clearance: impacts, penetration, the
  largest Lyapunov increase (must not be positive at impacts, Prop. 2).

Workers build their scene objects once per process (module-level caches), so
a point costs one simulation, not one build.
"""
from __future__ import annotations

import functools
from typing import Any, Sequence

import numpy as np

from ..errors import ParameterError
from .sweep import SweepResult, grid, sweep

__all__ = ["funnel_mismatch", "wrist_lambda_map", "clearance_grid", "plot_sweep"]

_CACHE: dict[Any, Any] = {}


def _cached(key, build):
    if key not in _CACHE:
        _CACHE[key] = build()
    return _CACHE[key]


# ------------------------------------------------------------------- funnel
def _tracking_setup(controller: str, t_end: float):
    from ..scenes import load_scene
    from .tracking import setup_tracking

    scene = load_scene("manipulator")
    setup = setup_tracking(scene, invert=controller in ("C1", "C3"), t_end=t_end, plant_factors={})
    return scene, setup


def funnel_point(*, controller: str = "C1", t_end: float = 2.0, **factors) -> dict:
    """One closed-loop run of the manipulator with the plant's parameters scaled by ``factors``."""
    scene, setup = _cached(("tracking", controller, t_end), lambda: _tracking_setup(controller, t_end))
    plant = setup.model.scaled(**factors)
    q0 = scene.initial_configuration(plant)
    res = setup.loop(controller).run(q0, theta=plant.theta_values, controller_label=controller)
    peaks = res.input_peaks
    out = {"cumulative_output_error": res.cumulative_output_error,
           "cumulative_endeffector_error": res.cumulative_endeffector_error,
           "max_constraint_drift": res.max_constraint_drift, "wall_s": res.wall_s}
    if res.ratios.size:
        out["max_funnel_ratio"] = res.max_funnel_ratio
    out.update({f"input_peak_{i + 1}": float(p) for i, p in enumerate(peaks)})
    return out


def funnel_mismatch(m3: Sequence[float] = (0.8, 1.0, 1.2, 1.5), other: str = "m2",
                    other_factors: Sequence[float] = (0.8, 1.0, 1.2), *, controller: str = "C1",
                    t_end: float = 2.0, executor=None, max_workers: int | None = None,
                    progress: bool = True) -> SweepResult:
    """The tracking study over plant mismatches: plant = reference model with ``m3`` and
    ``other`` multiplied by the grid's factors (derived inertias follow)."""
    from ..scenes import load_scene

    model = load_scene("manipulator").build()
    if other not in model.values or other == "m3":
        raise ParameterError(f"other must be a manipulator parameter other than m3, got {other!r}; "
                             f"known: {sorted(model.values)}")
    fn = functools.partial(funnel_point, controller=controller, t_end=t_end)
    res = sweep(fn, grid(m3=list(m3), **{other: list(other_factors)}), executor=executor,
                max_workers=max_workers, progress=progress, label=f"funnel mismatch {controller}")
    res.meta.update({"study": "funnel_mismatch", "controller": controller,
                     "labels": {"m3": "m3 factor (plant / model)", other: f"{other} factor (plant / model)"}})
    return res


# -------------------------------------------------------------------- wrist
def wrist_point(*, kt: float, bt: float, **overrides) -> dict:
    """Lambda of the wrist at ``(kt, bt)`` by the closed form and the numerical return map."""
    from ..scenes import load_scene
    from .switched import lambda_point

    p = _cached(("wrist", tuple(sorted(overrides.items()))),
                lambda: dict(load_scene("compliant_wrist").build(**overrides).params))
    p = {**p, "kt": float(kt), "bt": float(bt)}
    closed = lambda_point(p, method="closed")
    out = {"visible": float(closed.visible), "guas": float(closed.guas)}
    if closed.visible:
        out.update({"Lambda": np.nan, "Lambda_numerical": np.nan, "log10_Lambda": np.nan})
    else:
        num = lambda_point(p, method="numerical")
        out.update({"Lambda": closed.Lambda, "Lambda_numerical": num.Lambda,
                    "log10_Lambda": float(np.log10(closed.Lambda)),
                    "closed_vs_numerical": abs(closed.Lambda - num.Lambda) / max(abs(num.Lambda), 1e-300)})
    return out


def wrist_lambda_map(kt: Sequence[float] = tuple(np.geomspace(1e3, 1e6, 7)),
                     bt: Sequence[float] = tuple(np.geomspace(10.0, 1e4, 7)), *, executor=None,
                     max_workers: int | None = None, progress: bool = True, **overrides) -> SweepResult:
    """Lambda over a ``(kt, bt)`` grid of the compliant wrist (other parameters: the scene's,
    updated by ``overrides``); ``Lambda`` is NaN where a visible eigenvector exists (no rotation)."""
    fn = functools.partial(wrist_point, **overrides)
    res = sweep(fn, grid(kt=list(kt), bt=list(bt)), executor=executor, max_workers=max_workers,
                progress=progress, label="wrist Lambda map")
    res.meta.update({"study": "wrist_lambda_map", "labels": {"kt": "wrist stiffness kt [N/m]",
                                                             "bt": "wrist damping bt [Ns/m]"}})
    return res


# ---------------------------------------------------------------- clearance
def _prismatic_loop():
    from ..control.pdplus import pd_gravity
    from ..scenes import load_scene
    from ..simulate.timestepping import MoreauJean

    scene = load_scene("prismatic_clearance")
    p = scene.PARAMS
    model = scene.build(actuators=1)
    law = pd_gravity(model, Kp=p["Kp"], Kv=p["Kv"], q_d=p["qd"], idx=[0])
    return scene, model, MoreauJean(model, law)


def clearance_point(*, e: float, c: float, h: float = 1e-4, t_end: float = 1.0) -> dict:
    """PD regulation of body 1 of the prismatic clearance with restitution ``e`` and clearance ``c``."""
    if not 0 <= e <= 1 or not c >= 0:
        raise ParameterError(f"need 0 <= e <= 1 and c >= 0, got e = {e}, c = {c}")
    scene, model, mj = _cached("prismatic", _prismatic_loop)
    l = scene.PARAMS["l"]
    plant = model.with_params(e=float(e), L=2 * l + float(c))
    q0, v0 = [0.0, l + 0.5 * c], [0.0, scene.PARAMS["v20"]]
    tr = mj.run(q0, v0, t_end, h, params=plant.theta_values, ctrl_params=plant.theta_values)
    imp = tr.impact_mask()
    k = np.nonzero(imp.any(axis=1))[0]
    dV_imp = tr.V[k + 1] - tr.V[k] if k.size else np.zeros(0)
    return {"n_impacts": float(tr.impact_times.size), "max_gap_violation": tr.max_gap_violation,
            "max_V_jump_at_impacts": float(dV_imp.max(initial=-np.inf)) if dV_imp.size else 0.0,
            "q1_error_final": float(abs(tr.q[-1, 0] - scene.PARAMS["qd"])),
            "steps_per_s": float(tr.stats["steps_per_s"])}


def clearance_grid(e: Sequence[float] = (0.0, 0.25, 0.5, 0.75, 1.0),
                   c: Sequence[float] = (1e-9, 1e-6, 1e-4, 1e-3, 1e-2), *, h: float = 1e-4, t_end: float = 1.0,
                   executor=None, max_workers: int | None = None, progress: bool = True) -> SweepResult:
    """Restitution x clearance grid of the prismatic joint (Moreau-Jean, PD (36) on body 1)."""
    fn = functools.partial(clearance_point, h=h, t_end=t_end)
    res = sweep(fn, grid(e=list(e), c=list(c)), executor=executor, max_workers=max_workers,
                progress=progress, label="clearance grid")
    res.meta.update({"study": "clearance_grid", "h": h, "t_end": t_end,
                     "labels": {"e": "restitution e", "c": "clearance c [m]"}})
    return res


# ------------------------------------------------------------------- figure
def plot_sweep(res: SweepResult, keys: Sequence[str], path=None, *, log: Sequence[str] = (), contour=None):
    """Heat maps of several outputs side by side (one figure); ``log`` lists keys drawn as
    log10, ``contour`` maps a key to a level drawn as a black line (e.g. ``{"Lambda": 1}``)."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(keys), figsize=(5.2 * len(keys), 4.2), squeeze=False)
    for ax, key in zip(axes[0], keys):
        res.plot(key, ax=ax, log=key in log, contour=(contour or {}).get(key))
    fig.tight_layout()
    if path is not None:
        fig.savefig(path, dpi=120)
    return fig
