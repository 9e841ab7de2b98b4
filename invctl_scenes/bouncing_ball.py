"""A ball dropped from rest at height H onto the ground (000 (1) with n = 1).

``q = (y,)``, ``M = m``, ``f = -m g``, one gap ``y >= 0`` with restitution
``e``.  Impact times and the rest time are known in closed form:
``t_1 = sqrt(2 H / g)``, ``t_{k+1} = t_k + 2 e^k v_1 / g`` (``v_1 = g t_1``),
rest (accumulation) time ``t_inf = t_1 (1 + e) / (1 - e)``; the post-impact
velocity of impact ``k`` is ``e^k v_1``.

``--set e=... h=...`` sets the restitution and the time step.
"""
from __future__ import annotations

import casadi as ca
import numpy as np

from invctl.model import Gap, Model, ParamSet
from invctl.scenes import Contact, Report, Scene

PARAMS = {"m": 1.0, "g": 9.81, "H": 1.0, "e": 0.8, "h": 1e-3, "theta": 0.5, "t_end": 3.0, "projection": 0.0}
MODEL_PARAMS = ("m", "g", "e")


def build(**overrides: float) -> Model:
    """The ball model (parameters m, g, e)."""
    P = ParamSet(list(MODEL_PARAMS))
    q = ca.SX.sym("q", 1)
    v = ca.SX.sym("v", 1)
    vals = {k: PARAMS[k] for k in MODEL_PARAMS}
    ov = {k: v_ for k, v_ in overrides.items() if k in MODEL_PARAMS}
    return Model("bouncing_ball", q, v, P, vals, M=ca.reshape(P["m"], 1, 1), f=-P["m"] * P["g"],
                 B=ca.SX.zeros(1, 0), gaps=[Gap("ground", q[0], "e")], overrides=ov,
                 q_names=["y"], u_names=[])


def potential(model: Model) -> ca.SX:
    """``m g y``."""
    return model.params["m"] * model.params["g"] * model.q[0]


def exact_impacts(H: float, g: float, e: float, t_max: float):
    """Closed-form impact times, pre- and post-impact velocities up to ``t_max``
    and the rest time (inf for e = 1)."""
    t1 = np.sqrt(2 * H / g)
    v1 = g * t1
    times, pre, post = [], [], []
    t, vk = t1, v1
    while t <= t_max and vk > 0 and len(times) < 100000:
        times.append(t)
        pre.append(-vk)
        post.append(e * vk)
        t = t + 2 * e * vk / g
        vk = e * vk
        if e == 0:
            break
    rest = t1 * (1 + e) / (1 - e) if e < 1 else np.inf
    return np.array(times), np.array(pre), np.array(post), rest


def _exact(model: Model, settings: dict, t_max: float):
    p = model.values
    times, _, post, _ = exact_impacts(settings["H"], p["g"], p["e"], t_max)
    return times, post


def _rest(model: Model, settings: dict) -> float:
    return float(exact_impacts(settings["H"], model.values["g"], model.values["e"], 0.0)[3])


def closed_form_report(ctx) -> dict:
    """Impact times, post-impact velocities and rest time against the closed form."""
    tr, p, s = ctx.result, ctx.model.values, ctx.settings
    ti, _, _, post, _ = tr.impacts()
    ex_t, _, ex_post, rest = exact_impacts(s["H"], p["g"], p["e"], float(tr.t[-1]))
    k = min(len(ti), len(ex_t), 5)
    t_rest = tr.rest_time()
    return {"impact times": ti[:k], "closed form": ex_t[:k], "impact time errors": ti[:k] - ex_t[:k],
            "post-impact velocity errors": post[:k] - ex_post[:k],
            "rest time": t_rest if np.isfinite(t_rest) else f"not at rest by t_end = {float(tr.t[-1]):.6g} s",
            "rest time, closed form": rest}


def drawing(model: Model):
    """The ball above the ground line."""
    from invctl.plot.animate import Drawing

    return Drawing(points={"ball": ca.vertcat(0, model.q[0])}, links=[], segments=[((-0.5, 0.0), (0.5, 0.0))])


def _check(v: dict) -> None:
    from invctl.errors import ParameterError

    if not 0 <= v["e"] <= 1:
        raise ParameterError(f"bouncing_ball: restitution e must lie in [0, 1], got {v['e']}")
    if not 0 <= v["theta"] <= 1:
        raise ParameterError(f"bouncing_ball: theta of the theta-method must lie in [0, 1], got {v['theta']}")
    if v["projection"] not in (0, 1):
        raise ParameterError(f"bouncing_ball: projection is a switch, 0 or 1, got {v['projection']}")


SCENE = Scene(
    "bouncing_ball", build, params={k: PARAMS[k] for k in MODEL_PARAMS},
    settings={k: v for k, v in PARAMS.items() if k not in MODEL_PARAMS},
    integer=("projection",), positive=("m", "g", "H", "h", "t_end"), validate=_check,
    contact=Contact(initial_state=lambda model, settings, controller: ([settings["H"]], [0.0]),
                    potential=potential, exact_impacts=_exact, exact_rest=_rest),
    reports=(Report("closed form (Newton's law, free fall)", closed_form_report),),
    drawing=drawing,
    description="a ball dropped onto the ground (000 (1) with n = 1); impacts and rest time in closed form",
)
