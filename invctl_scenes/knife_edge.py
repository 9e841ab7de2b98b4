"""Knife edge (skate) in the plane: a non-holonomic constraint, 003 (1) with p = 1.

q = (x, y, theta), M = diag(m, m, I); the blade cannot slide sideways:
J(q) v + j = x' sin(theta) - y' cos(theta) = 0.  Inputs: the force along the
blade and the steering torque; outputs y = (x, theta).  The auxiliary ODE
(10) has relative degree (1, 2, 2), det Gamma = cos(theta) / (m^2 I), so the
relative degree exists where cos(theta) != 0; r_bar = 5, the internal dynamics
are one-dimensional: eta = y (lateral position), eta' = tan(theta) x'.

With the position output (x, y) instead, Gamma is singular everywhere (the
classical obstruction for wheeled vehicles): ``build_position_output``.
"""
from __future__ import annotations

import math

import casadi as ca

from invctl.model import Model, OperatingRegion, ParamSet
from invctl.scenes import Scene, Tracking

PARAMS = {"m": 1.0, "I": 0.1, "Dth": 0.05}

REGION = OperatingRegion(
    q_lower=[-math.inf, -math.inf, -1.2], q_upper=[math.inf, math.inf, 1.2],
    sample_bounds=([-2.0, -2.0, -1.2], [2.0, 2.0, 1.2]), v_scale=1.0,
    description="|theta| < 1.2 (cos(theta) > 0)",
)


def _build(name, output, overrides):
    P = ParamSet(list(PARAMS))
    m, I, Dth = P["m"], P["I"], P["Dth"]
    q, v = ca.SX.sym("q", 3), ca.SX.sym("v", 3)
    th = q[2]
    J = ca.horzcat(ca.sin(th), -ca.cos(th), 0)
    B = ca.vertcat(ca.horzcat(ca.cos(th), 0), ca.horzcat(ca.sin(th), 0), ca.horzcat(0, 1))
    h = ca.vertcat(q[0], q[2]) if output == "x_theta" else ca.vertcat(q[0], q[1])
    return Model(name, q, v, P, PARAMS, M=ca.diag(ca.vertcat(m, m, I)), f=ca.vertcat(0, 0, -Dth * v[2]),
                 B=B, J=J, j=ca.SX.zeros(1), h=h, region=REGION, overrides=overrides, q_names=["x", "y", "theta"],
                 u_names=["F", "tau"], y_names=["x", "theta"] if output == "x_theta" else ["x", "y"])


def build(**overrides: float) -> Model:
    return _build("knife_edge", "x_theta", overrides)


def build_position_output(**overrides: float) -> Model:
    return _build("knife_edge_xy", "x_y", overrides)


def _check(v: dict) -> None:
    if v["Dth"] < 0:
        from invctl.errors import ParameterError

        raise ParameterError(f"knife_edge: the steering damping Dth must be >= 0, got {v['Dth']}")


SCENE = Scene(
    "knife_edge", build, params=PARAMS, positive=("m", "I"), validate=_check,
    tracking=Tracking(point=[0.0, 0.0, 0.3]),
    description="knife edge (skate) with a non-holonomic constraint, outputs (x, theta); analysis only",
)
