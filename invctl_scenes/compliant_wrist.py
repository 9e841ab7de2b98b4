"""Manipulator with a compliant wrist against a stiff wall (002 Sect. 5).

Arm x (mass M) and tip x_t (mass Mt) joined by the wrist 002 (24)-(25),
F_t = kt (x - x_t) + bt (x' - x_t'); the Kelvin-Voigt wall (2) acts on the tip
at x_t = 0; the switched controller (3) acts on the arm and switches at x = 0
as printed in (3) (switch_on_tip = 1 switches it at the contact x_t = 0
instead).  Wrist of Sect. 5.4: Mt = 0.05 kg, kt = 5e4 N/m, bt = 171 Ns/m;
plant, wall and controller as in invctl_scenes/stiff_wall.py.

The stability analysis uses the reduced model (27)-(28) with the effective
wall ke_bar = kt ke/(kt + ke), be_bar = bt ke/(kt + ke) and K2, B2 of (30); the
map (29) uses the estimates ke_hat, be_hat of ke_bar, be_bar (default: exact).
"""
from __future__ import annotations


from invctl.model.params import resolve_params
from invctl.scenes import Scene, Switched

from invctl_scenes.stiff_wall import PARAMS as _WALL
from invctl_scenes.stiff_wall import check as _check_wall

PARAMS = {**_WALL, "Mt": 0.05, "kt": 5.0e4, "bt": 171.0, "switch_on_tip": 0.0,
          "ke_hat": 5.0e4 * 1e6 / (5.0e4 + 1e6), "be_hat": 171.0 * 1e6 / (5.0e4 + 1e6)}

DERIVED = {
    "ke_hat": lambda p: p["kt"] * p["ke"] / (p["kt"] + p["ke"]),
    "be_hat": lambda p: p["bt"] * p["ke"] / (p["kt"] + p["ke"]),
}


def build(**overrides: float):
    """The scenario with parameters resolved (unknown names raise ParameterError)."""
    from invctl.studies.switched import SwitchedProblem

    return SwitchedProblem("compliant_wrist", resolve_params(PARAMS, DERIVED, overrides))


def _check(v: dict) -> None:
    _check_wall(v, "compliant_wrist")


SCENE = Scene(
    "compliant_wrist", build, params=PARAMS, validate=_check,
    positive=("M", "ke", "Ma", "ke_hat", "t_b", "gamma1", "gamma2", "t_end", "h_max",
              "Mt", "kt", "bt"),
    switched=Switched(plant="compliant_wrist"),
    description="manipulator with a compliant wrist against a stiff wall (002 Sect. 5), analysed by its reduced "
                "model (27)-(28)",
)
