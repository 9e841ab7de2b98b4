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
    if stable[0 if want_stable_above else -1]:
        return float(lo if want_stable_above else hi)
    idx = np.flatnonzero((stable[:-1] != stable[1:]) & (stable[1:] == want_stable_above))
    if not idx.size:
        raise StabilityError(f"no GUAS design with {name} in [{lo:.4g}, {hi:.4g}]",
                             diagnostics={"grid": grid.tolist(), "ln_Lambda": m.tolist()})
    k = int(idx[0] if want_stable_above else idx[-1])
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
    return _border(p, "bt", bt_range[0], bt_range[1], method, want_stable_above=True)


def design_kt_max(p: dict, *, method: str = "closed", kt_range=(10.0, 1e9)) -> float:
    """Largest wrist stiffness ``kt`` with GUAS of the reduced model at the given ``bt``."""
    return _border(p, "kt", kt_range[0], kt_range[1], method, want_stable_above=False)


def design_bf_min(p: dict, *, method: str = "closed", bf_range=(1e-3, 1e7)) -> float:
    """Smallest force-controller damping ``bf`` with GUAS (rigid wall or wrist)."""
    return _border(p, "bf", bf_range[0], bf_range[1], method, want_stable_above=True)


def design_bt_visible(p: dict, *, bt_range=(1.0, 1e6)) -> float:
    """Smallest ``bt`` for which a visible stable eigenvector exists (no bouncing for any reference)."""
    grid = np.geomspace(bt_range[0], bt_range[1], 200)
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
    return GluedReference(xp, Fp, ((p["t_c"], p["t_b"]),), p["gamma1"], p["gamma2"], p["ke_hat"], p["be_hat"],
                          contact_start="crossing" if p.get("glue_at_crossing", 1.0) else "time")


def build_loop(p: dict, *, reduced: bool = False) -> ClosedLoop:
    """Closed loop of the scenario: rigid wall (1)-(2), full wrist (24)-(25) or its reduced model (27)-(28)."""
    ctrl = SwitchedForceController(p["Ma"], p["kp"], p["kd"], p["kf"], p["bf"])
    ref = build_reference(p)
    plant: CompliantWristPlant | RigidWallPlant
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
# the problem object a switched scene builds
# ---------------------------------------------------------------------------
@dataclass(frozen=True)
class SwitchedProblem:
    """Parameters of a switched position/force scenario and what is built from them; a switched scene's ``build``
    returns one. The scene declares its plant (``Switched(plant=...)``), and loading checks that the parameters
    are that plant's (the wrist's ``Mt, kt, bt`` exactly when it declares ``"compliant_wrist"``), so the functions
    here, which take the parameter dict, can tell the plants apart by them."""

    name: str
    params: dict

    def error_system(self) -> SwitchedErrorSystem:
        return error_system(self.params)

    def analyze(self, **kw):
        from ..stability.conewise import analyze

        return analyze(self.error_system(), **kw)

    def loop(self, *, reduced: bool = False) -> ClosedLoop:
        return build_loop(self.params, reduced=reduced)

    def simulate(self, *, reduced: bool = False, t_end: float | None = None, **options) -> SwitchedSimulation:
        return simulate_scenario(self.params, reduced=reduced, t_end=t_end,
                                 label=self.name + (" (reduced)" if reduced else ""), **options)

    def with_params(self, **overrides) -> "SwitchedProblem":
        return SwitchedProblem(self.name, {**self.params, **{k: float(v) for k, v in overrides.items()}})
