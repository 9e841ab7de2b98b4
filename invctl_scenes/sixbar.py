"""The six-bar's clearance configurations of 000 Sect. 2 (Example 2) and Sect. 4 as one scene.

Geometry in ``invctl_scenes/_sixbar.py``; this scene defaults to the horizontal plane (``g = 0``), where
PD (36) on the actuated joints has the Lyapunov function (37) in every configuration.  Parameter
``structure`` (``--set structure=...``) selects the clearances and actuators:

=========  =====================  =========================  ==========================================
structure  clearances             actuators                  open system (000 Example 2 / Sect. 4)
=========  =====================  =========================  ==========================================
1          J3                     J1, J2, J4, J5, J6         S1: n = 5, n_ind = 2, both fully actuated
2          J3, J4 (Fig. 5(a))     J1, J2, J5, J6             S2: n = 7, n_ind = 3, B3 unactuated
3          J2, J4                 J1, J3, J5, J6             S3: n = 7, n_ind = 3, (B2, B3) actuated at J3
                                                             only: underactuated, centre of mass free
4          J3, J5 (Fig. 6(a))     J1, J2, J4, J6             n = 7, n_ind = 3, (B3, B4) actuated at J4
7          J4, J5, J6 (Fig. 7(a)) J1, J2, J3                 n = 9, n_ind = 3 (see also ``sixbar_pd``)
=========  =====================  =========================  ==========================================

``invctl analyze sixbar --set structure=3`` prints which subsystems are fully actuated, underactuated
or unactuated, the contacts between them, the juggling structure and the clearance-free degree of
actuation (Assumption 1), beside what 000 states.  Controller ``pd``: PD (36) on the actuated
coordinates to the nominal pose plus ``offset`` rad, from the nominal pose with the journals centred
and the unactuated bodies (if any) spinning at ``kick`` rad/s.
"""
from __future__ import annotations

import numpy as np

from invctl.scenes import Contact, Report, Scene
from invctl_scenes import _sixbar as sb

PARAMS = {**sb.PARAMS, "g": 0.0, "structure": 2.0}
SETTINGS = {"Kp": 10.0, "Kv": 1.0, "offset": 0.1, "kick": 3.0,
            "h": 1e-5, "theta": 0.5, "t_end": 3.0, "projection": 0.0, "activation_tol": 1e-12}


def build(**overrides: float):
    """The open six-bar of configuration ``structure``."""
    code = int(overrides.get("structure", PARAMS["structure"]))
    ov = {k: v for k, v in overrides.items() if k != "structure"}
    return sb.build("sixbar", code, {"g": PARAMS["g"], **ov})


def _pd(model, s):
    from invctl.control.pdplus import pd_gravity, selection_indices

    idx = selection_indices(model)
    unact = [k for k, sub in enumerate(model.linkage.subsystems) if not set(sub.coordinates) & set(idx)]
    return pd_gravity(model, Kp=s["Kp"], Kv=s["Kv"], q_d=model.linkage.nominal[idx] + s["offset"], idx=idx,
                      potential=model.linkage.potential_of(unact))


def _initial(model, s, controller):
    q0, v0 = model.linkage.nominal.copy(), np.zeros(model.n)
    for sub in model.linkage.subsystems:
        if not sub.grounded:
            v0[sub.coordinates[2]] = s["kick"]      # spin of the floating root body
    return q0, v0


def structure_report(ctx) -> dict:
    """The generic subsystem analysis beside 000's statement for this configuration."""
    from invctl.contact.structure import subsystem_report

    code = int(ctx.params.get("structure", PARAMS["structure"]))
    out = {"configuration": sb.CONFIGS[code][2], **subsystem_report(ctx)}
    n, nind, dofs = sb.PRINTED[code]
    out["000 states"] = f"n = {n}, n_ind = {nind}, DoFs {dofs}"
    out["agrees with 000"] = bool(out["n (open system)"] == n and out["n_ind"] == nind
                                  and list(out["DoFs per subsystem"]) == dofs)
    return out


def _check(values):
    sb.check(values)
    from invctl.errors import ParameterError

    if int(values["structure"]) not in sb.CONFIGS:
        raise ParameterError(f"sixbar: structure must be one of {sorted(sb.CONFIGS)} (see the scene's docstring), "
                             f"got {values['structure']}")


SCENE = Scene(
    "sixbar", build, params=PARAMS, settings=SETTINGS, integer=("structure",),
    positive=("d", "l1", "l2", "l3", "l4", "l5", "rho", "c", "Kp", "Kv", "h", "t_end"), validate=_check,
    contact=Contact(controllers={"pd": _pd}, initial_state=_initial),
    reports=(Report("000 Sect. 2: subsystems of the open six-bar", structure_report, command="analyze"),),
    drawing=sb.drawing,
    description="six-bar clearance configurations S1, S2, S3 of 000 Example 2 and Figs. 5(a), 6(a), 7(a): "
                "subsystems, actuation, juggling structure; PD (36) runs",
)
