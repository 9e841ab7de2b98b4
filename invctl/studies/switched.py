"""Studies of the switched position/force loop: scenarios, Lambda maps, wrist design (002 Sect. 4-5).

Everything here works on plain parameter dicts (the scene's ``PARAMS`` with
overrides) so that scenes, the CLI and notebooks share one call:

* :func:`error_system` -- ``K_i, B_i`` of (11) for the rigid wall, or of (30)
  with the effective wall ``ke_bar, be_bar`` (28) of the compliant wrist;
* :func:`lambda_sweep`, :func:`lambda_map` -- Lambda over ``bf`` or ``(kt, bt)``;
* :func:`design_bt_min`, :func:`design_kt_max`, :func:`design_bt_visible` --
  the wrist design of Sect. 5.3 (smallest damping / largest stiffness with
  GUAS, and the border of the bounce-free region with a visible eigenvector);
* :func:`build_loop`, :func:`simulate_scenario` -- the simulations of Figs. 3,
  4, 6 and 7 (full 4-state wrist and its reduced model (27)-(28)).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from ..control.switched import ClosedLoop, CompliantWristPlant, RigidWallPlant, SwitchedForceController
from ..errors import ParameterError, StabilityError
from ..reference.gluing import GluedReference, approach_retract, force_bump
from ..simulate.switched import SwitchedSimulation, simulate_switched
from ..stability.conewise import (SwitchedErrorSystem, lambda_closed_form, lambda_numerical,
                                  visible_eigenvectors)


# ---------------------------------------------------------------------------
# reduced model (27)-(28)
# ---------------------------------------------------------------------------
def effective_wall(kt: float, bt: float, ke: float) -> tuple[float, float]:
    """``(ke_bar, be_bar) = (kt ke/(kt + ke), bt ke/(kt + ke))`` of (28)."""
    if kt <= 0 or ke <= 0:
        raise ParameterError(f"effective wall needs kt > 0 and ke > 0, got kt = {kt}, ke = {ke}")
    f = ke / (kt + ke)
    return kt * f, bt * f


def is_wrist(p: dict) -> bool:
    return "kt" in p


def error_system(p: dict) -> SwitchedErrorSystem:
    """``K_i, B_i`` of (11a)-(11b) (rigid wall) or (11a), (30) (wrist, reduced model)."""
    if is_wrist(p):
        ke, be = effective_wall(p["kt"], p["bt"], p["ke"])
    else:
        ke, be = p["ke"], p["be"]
    return SwitchedErrorSystem.from_params(M=p["M"], b=p["b"], kp=p["kp"], kd=p["kd"], ke=ke, be=be,
                                           kf=p["kf"], bf=p["bf"])


def reduction_check(p: dict) -> dict:
    """Poles of the full closed loop against those of the analysed 2-state error system.

    For each subsystem (1: free, all surfaces off; 2: contact, all on) every eigenvalue of
    ``A_i`` is matched to the nearest eigenvalue of the full closed loop's plant block; the
    relative distance measures how well (27)-(28) (wrist) captures the slow dynamics.  For the
    rigid wall the two coincide exactly (the error system (9)-(11) is the closed loop itself).
    """
    loop = build_loop(p)
    s = error_system(p)
    nb = len(loop.surfaces)
    out = {}
    for i, name, bits in ((1, "free", (False,) * nb), (2, "contact", (True,) * nb)):
        full = np.sort_complex(loop.plant_eigenvalues(bits, False).astype(complex))
        red = np.atleast_1d(s.eigenvalues(i)).astype(complex)
        err = max(float(np.min(np.abs(full - r)) / abs(r)) for r in red)
        out[name] = {"full": full, "reduced": red, "rel_error": err}
    return out


# ---------------------------------------------------------------------------
# Lambda and GUAS as functions of parameters
# ---------------------------------------------------------------------------
@dataclass(frozen=True)
class LambdaPoint:
    Lambda: float      # nan when a visible eigenvector exists
    visible: bool
    guas: bool


def lambda_point(p: dict, *, method: str = "closed") -> LambdaPoint:
    """Lambda (closed form or numerical return map) and the GUAS verdict at one parameter set."""
    s = error_system(p)
    if visible_eigenvectors(s):
        return LambdaPoint(float("nan"), True, True)
    if method == "closed":
        lam = lambda_closed_form(s)[2]
    elif method == "numerical":
        lam = lambda_numerical(s).Lambda
    else:
        raise ParameterError(f"method must be 'closed' or 'numerical', got {method!r}")
    return LambdaPoint(lam, False, bool(lam < 1))


def lambda_sweep(p: dict, name: str, values, *, method: str = "closed") -> dict:
    """Lambda over one parameter; returns arrays ``values, Lambda`` (nan where visible), ``visible, guas``."""
    if name not in p:
        raise ParameterError(f"unknown parameter {name!r} for the sweep; known: {sorted(p)}")
    values = np.asarray(values, float)
    pts = [lambda_point({**p, name: float(v)}, method=method) for v in values]
    return {"name": name, "values": values, "Lambda": np.array([q.Lambda for q in pts]),
            "visible": np.array([q.visible for q in pts]), "guas": np.array([q.guas for q in pts])}


def lambda_map(p: dict, kt_values, bt_values) -> dict:
    """Lambda of the reduced wrist model over a ``(kt, bt)`` grid (arrays indexed ``[i_kt, i_bt]``)."""
    kt_values, bt_values = np.asarray(kt_values, float), np.asarray(bt_values, float)
    lam = np.full((kt_values.size, bt_values.size), np.nan)
    vis = np.zeros(lam.shape, bool)
    for i, kt in enumerate(kt_values):
        for j, bt in enumerate(bt_values):
            q = lambda_point({**p, "kt": float(kt), "bt": float(bt)})
            lam[i, j], vis[i, j] = q.Lambda, q.visible
    return {"kt": kt_values, "bt": bt_values, "Lambda": lam, "visible": vis,
            "guas": vis | (np.nan_to_num(lam, nan=np.inf) < 1)}


# ---------------------------------------------------------------------------
# design (Sect. 5.3)
# ---------------------------------------------------------------------------
def _margin(p: dict, method: str) -> float:
    """``ln Lambda`` (negative = GUAS); ``-inf`` with a visible eigenvector; ``+inf`` where
    Theorem 1 does not apply (``K2 <= K1``: not certified)."""
    try:
        q = lambda_point(p, method=method)
    except StabilityError:
        if error_system(p).dK >= 0:
            return math.inf
        raise
    return -math.inf if q.visible else math.log(q.Lambda)


def _border(p: dict, name: str, lo: float, hi: float, method: str, *, want_stable_above: bool,
            n_scan: int = 60, rtol: float = 1e-10) -> float:
    """Border value of parameter ``name`` in ``[lo, hi]`` where GUAS starts (log-spaced scan, then refine)."""
    grid = np.geomspace(lo, hi, n_scan)
    m = np.array([_margin({**p, name: float(v)}, method) for v in grid])
    stable = m < 0
    if want_stable_above:
        idx = np.flatnonzero(~stable[:-1] & stable[1:])
        if stable[0]:
            return float(lo)
        if not idx.size:
            raise StabilityError(f"no GUAS design with {name} in [{lo:.4g}, {hi:.4g}]",
                                 diagnostics={"grid": grid.tolist(), "ln_Lambda": m.tolist()})
        k = int(idx[0])
    else:
        idx = np.flatnonzero(stable[:-1] & ~stable[1:])
        if stable[-1]:
            return float(hi)
        if not idx.size:
            raise StabilityError(f"no GUAS design with {name} in [{lo:.4g}, {hi:.4g}]",
                                 diagnostics={"grid": grid.tolist(), "ln_Lambda": m.tolist()})
        k = int(idx[-1])
    a, b = float(grid[k]), float(grid[k + 1])
    ma, mb = m[k], m[k + 1]
    if math.isfinite(ma) and math.isfinite(mb):
        return brentq(lambda v: _margin({**p, name: v}, method), a, b, xtol=1e-14, rtol=rtol)
    # the border is where a visible eigenvector appears: bisection on the verdict
    for _ in range(100):
        mid = 0.5 * (a + b)
        if (_margin({**p, name: mid}, method) < 0) == (ma < 0):
            a = mid
        else:
            b = mid
        if b - a <= rtol * b:
            break
    return 0.5 * (a + b)


def design_bt_min(p: dict, *, method: str = "closed", bt_range=(1.0, 1e5)) -> float:
    """Smallest wrist damping ``bt`` with GUAS of the reduced model (Lambda < 1 or visible eigenvector)."""
    return _border(p, "bt", *bt_range, method, want_stable_above=True)


def design_kt_max(p: dict, *, method: str = "closed", kt_range=(10.0, 1e9)) -> float:
    """Largest wrist stiffness ``kt`` with GUAS of the reduced model at the given ``bt``."""
    return _border(p, "kt", *kt_range, method, want_stable_above=False)


def design_bf_min(p: dict, *, method: str = "closed", bf_range=(1e-3, 1e7)) -> float:
    """Smallest force-controller damping ``bf`` with GUAS (rigid wall or wrist)."""
    return _border(p, "bf", *bf_range, method, want_stable_above=True)


def design_bt_visible(p: dict, *, bt_range=(1.0, 1e6)) -> float:
    """Smallest ``bt`` for which a visible stable eigenvector exists (no bouncing for any reference)."""
    grid = np.geomspace(*bt_range, 200)
    vis = np.array([bool(visible_eigenvectors(error_system({**p, "bt": float(v)}))) for v in grid])
    if not vis.any():
        raise StabilityError(f"no visible eigenvector for bt in [{bt_range[0]:.4g}, {bt_range[1]:.4g}]")
    k = int(np.argmax(vis))
    if k == 0:
        return float(grid[0])
    a, b = float(grid[k - 1]), float(grid[k])
    for _ in range(200):
        mid = 0.5 * (a + b)
        if visible_eigenvectors(error_system({**p, "bt": mid})):
            b = mid
        else:
            a = mid
        if b - a <= 1e-12 * b:
            break
    return b


def visible_region(p: dict, kt_values, *, bt_range=(1.0, 1e6)) -> np.ndarray:
    """For each ``kt``, the smallest ``bt`` giving a visible eigenvector (inf if none in range)."""
    out = []
    for kt in np.asarray(kt_values, float):
        try:
            out.append(design_bt_visible({**p, "kt": float(kt)}, bt_range=bt_range))
        except StabilityError:
            out.append(math.inf)
    return np.array(out)


# ---------------------------------------------------------------------------
# scenarios (Figs. 3, 4, 6, 7)
# ---------------------------------------------------------------------------
def build_reference(p: dict, *, reduced_estimates: bool | None = None) -> GluedReference:
    """The glued reference of the scenario: approach, one intended contact ``[t_c, t_b]``, retract."""
    xp = approach_retract(p["t_c"], p["t_b"], p["v_app"], p["x_ret"], overshoot_time=p["overshoot"])
    Fp = force_bump(p["t_c"], p["t_b"], p["F_max"])
    return GluedReference(xp, Fp, [(p["t_c"], p["t_b"])], p["gamma1"], p["gamma2"], p["ke_hat"], p["be_hat"],
                          contact_start="crossing" if p.get("glue_at_crossing", 1.0) else "time")


def build_loop(p: dict, *, reduced: bool = False) -> ClosedLoop:
    """Closed loop of the scenario: rigid wall (1)-(2), full wrist (24)-(25) or its reduced model (27)-(28)."""
    ctrl = SwitchedForceController(p["Ma"], p["kp"], p["kd"], p["kf"], p["bf"])
    ref = build_reference(p)
    if is_wrist(p) and not reduced:
        plant = CompliantWristPlant(p["M"], p["b"], p["Mt"], p["kt"], p["bt"], p["ke"], p["be"],
                                    controller_on="tip" if p.get("switch_on_tip", 0.0) else "arm")
    elif is_wrist(p):
        ke_bar, be_bar = effective_wall(p["kt"], p["bt"], p["ke"])
        plant = RigidWallPlant(p["M"], p["b"], ke_bar, be_bar)
    else:
        plant = RigidWallPlant(p["M"], p["b"], p["ke"], p["be"])
    return ClosedLoop(plant, ctrl, ref)


def simulate_scenario(p: dict, *, reduced: bool = False, t_end: float | None = None, label: str = "",
                      **options) -> SwitchedSimulation:
    """Simulate the scenario exactly (see :func:`invctl.simulate.switched.simulate_switched`)."""
    loop = build_loop(p, reduced=reduced)
    t_end = p["t_end"] if t_end is None else t_end
    options.setdefault("h_max", p.get("h_max", 2e-4))
    return simulate_switched(loop, t_end, label=label, meta={k: float(v) for k, v in p.items()}, **options)


# ---------------------------------------------------------------------------
# command handlers shared by problems/stiff_wall.py and problems/compliant_wrist.py
# ---------------------------------------------------------------------------
def _scene_params(scene, params: dict) -> dict:
    from ..model.params import resolve_params

    return resolve_params(scene.PARAMS, getattr(scene, "DERIVED", None), params)


def analyze_command(scene, params: dict, *, samples: int = 200, **options):
    """``invctl analyze``: Theorem 1 (visible eigenvectors, Lambda three ways, GUAS) and Theorem 2 (ISS)."""
    from ..errors import SceneError
    from ..scenes import CommandResult, scene_name
    from ..stability.conewise import analyze

    _reject(options, "analyze")
    if samples < 8:
        raise SceneError(f"--samples {samples}: need at least 8 initial directions for the ISS constant")
    p = _scene_params(scene, params)
    s = error_system(p)
    rep = analyze(s, with_iss=True, n_angles=min(int(samples), 720))
    head = f"scene {scene_name(scene)}: switched motion/force control against a stiff wall (002)"
    data = rep.to_dict()
    if is_wrist(p):
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


def simulate_command(scene, params: dict, *, controller=None, plant_set=None, t_end=None, out=None,
                     plot=None, **options):
    """``invctl simulate``: exact switched simulation; peak force, bounces, force RMS error."""
    from ..errors import SceneError
    from ..scenes import CommandResult, scene_name

    _reject(options, "simulate")
    name = scene_name(scene)
    if controller is not None:
        raise SceneError(f"scene {name!r} has one controller, the switched law 002 (3); "
                         "--controller is not applicable (change its gains with --set kp=..., bf=...)")
    if plant_set:
        raise SceneError(f"scene {name!r}: the controller (3) uses no plant model, so plant and model "
                         "parameters coincide; --plant-set is not applicable (use --set)")
    p = _scene_params(scene, params)
    sim = simulate_scenario(p, t_end=t_end, label=name)
    text = sim.summary()
    data = sim.to_dict()
    if is_wrist(p):
        red = simulate_scenario(p, reduced=True, t_end=t_end, label=f"{name} (reduced model)")
        data["reduced"] = red.to_dict()
        text += "\n" + red.summary()
    if out:
        sim.to_npz(out)
        text += f"\n  trajectory written to {out}"
    if plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        axes = sim.plot() if not is_wrist(p) else _plot_fig7(sim, red)
        axes[0].figure.savefig(plot, dpi=130)
        plt.close(axes[0].figure)
        text += f"\n  figure written to {plot}"
    return CommandResult(text, data)


def _plot_fig7(full, reduced):
    from ..plot.switched import plot_simulation

    return plot_simulation(full, overlay=reduced, overlay_label="(reduced)")


def design_command(scene, params: dict, *, plot=None, **options):
    """``invctl design``: smallest bt, largest kt (wrist) or smallest bf (rigid wall) with GUAS."""
    from ..scenes import CommandResult, scene_name

    _reject(options, "design")
    p = _scene_params(scene, params)
    name = scene_name(scene)
    data: dict = {}
    lines = [f"scene {name}: design by Theorem 1 (002 Sect. 5.3)"]
    if not is_wrist(p):
        bf_min = design_bf_min(p)
        data["bf_min"] = bf_min
        data["bf_min_numerical"] = design_bf_min(p, method="numerical")
        q = lambda_point(p)
        data.update({"Lambda": None if q.visible else q.Lambda, "visible_eigenvector": q.visible,
                     "guas": q.guas, "bf": p["bf"]})
        lines.append(f"  smallest controller damping bf with GUAS: {bf_min:.8g} Ns/m "
                     f"(numerical return map: {data['bf_min_numerical']:.8g})")
        lines.append(f"  at bf = {p['bf']:.6g}: " + ("visible eigenvector" if q.visible else
                                                     f"Lambda = {q.Lambda:.6g}") + f", GUAS {q.guas}")
    if is_wrist(p):
        bt_min = design_bt_min(p)
        data["bt_min"] = bt_min
        data["bt_min_numerical"] = design_bt_min(p, method="numerical")
        data["kt_max"] = design_kt_max(p)
        data["kt_max_numerical"] = design_kt_max(p, method="numerical")
        try:
            data["bt_visible"] = design_bt_visible(p)
        except StabilityError:
            data["bt_visible"] = None
        q = lambda_point(p)
        data.update({"Lambda": None if q.visible else q.Lambda, "visible_eigenvector": q.visible,
                     "guas": q.guas, "kt": p["kt"], "bt": p["bt"], "bf": p["bf"]})
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
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        from ..plot.switched import plot_lambda_curve, plot_lambda_map

        if is_wrist(p):
            m = lambda_map(p, np.geomspace(3e3, 1e6, 40), np.geomspace(10, 3000, 40))
            ax = plot_lambda_map(m["kt"], m["bt"], m["Lambda"], m["visible"], design=(p["kt"], p["bt"]))
        else:
            sw = lambda_sweep(p, "bf", np.geomspace(1, 1e5, 120))
            ax = plot_lambda_curve(sw["values"], sw["Lambda"], sw["visible"])
        ax.figure.tight_layout()
        ax.figure.savefig(plot, dpi=130)
        plt.close(ax.figure)
        lines.append(f"  figure written to {plot}")
    return CommandResult("\n".join(lines), data)


def _reject(options: dict, command: str) -> None:
    from ..errors import SceneError

    if options:
        raise SceneError(f"invctl {command}: unexpected options {sorted(options)} for a switched-contact scene")
