"""An n-link arm with elastic passive joints, driven at the shoulder: the scaling case.

n identical homogeneous links (length l, mass m) hang in a vertical plane.  The shoulder
motor drives link 1 with the torque u; links i and i + 1 are joined by passive joints with
a torsional spring k and damper d.  The coordinates are the absolute link angles
``theta_i`` from the downward vertical, so the mass matrix has the closed form

    M_ij = mu_ij cos(theta_i - theta_j),
    mu_ii = I + m lc^2 + l^2 m (n - i),      mu_ij = l (m lc + l m (n - j))  (i < j, 1-based),

(``I = m l^2 / 12``, ``lc = l / 2``, ``m (n - j)``: the mass beyond link j) and the
Lagrange equations are ``M theta'' = f`` with

    f_i = -sum_j mu_ij sin(theta_i - theta_j) theta_j'^2 - g (m lc + l m (n - i)) sin(theta_i)
          - (joint spring and damper torques) - alpha (M theta')_i + u delta_i1.

No inverse of ``M`` is ever formed here; every expression has O(n^2) nodes.  The last
term is mass-proportional (Rayleigh) damping of rate ``alpha``, the losses of the
structure to its surroundings: without it the slow modes of a long arm decay at rates
of 6e-3/s (n = 8) to 2e-3/s (n = 32), and the stable inversion would need a horizon of hours.  With
it every mode and every zero decays at least at about ``alpha / 2``.

Output.  ``y = theta_1 + w (theta_2 - theta_1)`` (default ``w = 1``: the absolute angle of
link 2).  The tip angle (``sum_i theta_i / n`` linearized) would be the classical choice
(Cannon and Schmitz 1984), but its high-gain matrix ``c^T M^-1 e_1`` falls exponentially in n
(the hub torque reaches the tip through n - 1 compliant joints: -2.6e-3 at n = 8, -3.4e-8 at
n = 16, 0 to rounding at n = 32).  The angle of link 2 keeps ``Gamma = (M^-1)_21 = -130`` for
every n and is non-minimum phase with one real unstable zero (+27.6/s for n = 2, +13/s for
n = 3, +6.6/s for n = 32 at the hanging arm, default parameters); the other 2n - 3 zeros
lie left of ``-alpha / 2``.

For n = 2 this is ``invctl_scenes/passive_arm.py`` in absolute coordinates (same physics,
independent construction: checked in ``tests/test_gallery.py``).

Cartesian (natural) coordinates, ``--set coordinates=cartesian``.  The same arm with the
redundant coordinates ``q = (x_1, y_1, theta_1, ..., x_n, y_n, theta_n)`` (centre of mass and
angle of every link, 3n coordinates, ``y`` upwards) and l = 2n holonomic pin constraints

    x_1 - lc sin theta_1 = 0,                  y_1 + lc cos theta_1 = 0            (shoulder),
    x_i + lc sin theta_i - x_{i+1} + lc sin theta_{i+1} = 0,
    y_i - lc cos theta_i - y_{i+1} - lc cos theta_{i+1} = 0                       (joint i, i + 1),

so that ``M = diag(m, m, I, ..., m, m, I)`` is constant and

    M v' = f + e_theta1 u - G(q)^T lam,
    f = (0, -m g, 0, ...) - (joint spring and damper torques on theta_i, theta_{i+1}) - alpha M v,

with the same output ``y = theta_1 + w (theta_2 - theta_1)``.  Projected on the angles
(``v = J(theta) theta'``, ``J^T M J = M_theta`` of the first formulation), the Rayleigh term
``-alpha M v`` is ``-alpha M_theta theta'``: the two formulations are the same physics
(``tests/test_flexible_arm_cartesian.py``).  Every row of ``g``, ``f`` and ``h`` touches at most
two neighbouring links, but the index-reduced inverse model of the inversion solves for the
multipliers and the input through a dense system, so its Jacobian blocks are dense, (8n + 1)^2 per
collocation node against (2n + 1)^2 for angles: this formulation is the slower one
(``benchmarks/bench_scaling.py`` compares the two: 14 s against 1 s at n = 8, peak 1.8 GB; n = 16 needed
more than 22 GB).  It is therefore limited to n <= MAX_N_CARTESIAN.
"""
from __future__ import annotations

import casadi as ca
import numpy as np

from invctl.model import Model, ParamSet
from invctl.reference import Reference, rest_to_rest
from invctl.scenes import Scene, Tracking

PARAMS = {"l": 0.25, "m": 0.25, "k": 5.0, "d": 0.05, "alpha": 2.0, "g": 9.81, "w": 1.0}
DEFAULT_N = 3
#: the coordinates of ``build`` (``--set coordinates=...``; the first is the default)
COORDINATES = ("angles", "cartesian")
MAX_N_CARTESIAN = 10  # memory: measured 1.8 GB at n = 8, more than 22 GB at n = 16


def _check_n(n) -> int:
    from invctl.errors import ParameterError

    if float(n) != round(float(n)) or int(round(float(n))) < 2:
        raise ParameterError(f"flexible_arm: n must be an integer >= 2 (the output uses links 1 and 2), got {n!r}")
    return int(round(float(n)))


def inertia_coefficients(n: int, l, m):
    """``mu`` (n x n, symmetric) of ``M_ij = mu_ij cos(theta_i - theta_j)`` and the gravity
    coefficients ``m lc + l m (n - i)`` (SX of the parameters, or numbers)."""
    lc, inertia = 0.5 * l, m * l * l / 12
    beyond = [m * (n - 1 - i) for i in range(n)]  # mass beyond link i (0-based)
    mu = [[None] * n for _ in range(n)]
    for i in range(n):
        mu[i][i] = inertia + m * lc * lc + l * l * beyond[i]
        for j in range(i + 1, n):
            mu[i][j] = mu[j][i] = l * (m * lc + l * beyond[j])
    grav = [m * lc + l * beyond[i] for i in range(n)]
    return mu, grav


def _check_coordinates(coordinates) -> str:
    from invctl.errors import ParameterError

    if not isinstance(coordinates, str) or coordinates not in COORDINATES:
        raise ParameterError(f"flexible_arm: coordinates must be one of {', '.join(COORDINATES)}, got {coordinates!r}")
    return coordinates


def build(n: float = DEFAULT_N, coordinates: str = COORDINATES[0], **overrides: float) -> Model:
    """The n-link arm in absolute angles (closed-form M and f, module doc), or in Cartesian
    coordinates with pin constraints (``coordinates="cartesian"``, :func:`build_cartesian`)."""
    n = _check_n(n)
    if _check_coordinates(coordinates) == "cartesian":
        return build_cartesian(n, **overrides)
    P = ParamSet(list(PARAMS))
    l, m, k, d, alpha, g, w = (P[name] for name in PARAMS)
    th, v = ca.SX.sym("theta", n), ca.SX.sym("v", n)
    mu, grav = inertia_coefficients(n, l, m)
    M = ca.SX(n, n)
    for i in range(n):
        for j in range(n):
            M[i, j] = mu[i][j] if i == j else mu[i][j] * ca.cos(th[i] - th[j])
    f = ca.SX.zeros(n)
    for i in range(n):
        f[i] = -g * grav[i] * ca.sin(th[i]) - sum(mu[i][j] * ca.sin(th[i] - th[j]) * v[j] ** 2
                                                  for j in range(n) if j != i)
    for i in range(1, n):  # joint i between links i - 1 and i (0-based)
        tau = k * (th[i] - th[i - 1]) + d * (v[i] - v[i - 1])
        f[i] -= tau
        f[i - 1] += tau
    f = f - alpha * ca.mtimes(M, v)
    B = ca.DM.zeros(n, 1)
    B[0] = 1
    return Model("flexible_arm", th, v, P, PARAMS, M=M, f=f, B=B, h=th[0] + w * (th[1] - th[0]),
                 overrides=overrides, q_names=[f"theta{i + 1}" for i in range(n)], u_names=["u"],
                 y_names=["link2_angle"])


def build_cartesian(n: int, **overrides: float) -> Model:
    """The n-link arm in Cartesian coordinates: link i has (x_i, y_i, theta_i), its centre of mass and
    angle; pin joints are the 2n holonomic constraints of the module doc (G derived by Model)."""
    n = _check_n(n)
    P = ParamSet(list(PARAMS))
    l, m, k, d, alpha, g, w = (P[name] for name in PARAMS)
    lc, inertia = 0.5 * l, m * l * l / 12
    q, v = ca.SX.sym("q", 3 * n), ca.SX.sym("v", 3 * n)
    x, y, th = ([q[3 * i + c] for i in range(n)] for c in range(3))
    vth = [v[3 * i + 2] for i in range(n)]
    mass = ca.vertcat(*[e for _ in range(n) for e in (m, m, inertia)])
    M = ca.diag(mass)
    cons = [x[0] - lc * ca.sin(th[0]), y[0] + lc * ca.cos(th[0])]
    for i in range(n - 1):  # the lower end of link i on the upper end of link i + 1
        cons += [x[i] + lc * ca.sin(th[i]) - x[i + 1] + lc * ca.sin(th[i + 1]),
                 y[i] - lc * ca.cos(th[i]) - y[i + 1] - lc * ca.cos(th[i + 1])]
    f = ca.SX.zeros(3 * n)
    for i in range(n):
        f[3 * i + 1] = -m * g
    for i in range(1, n):  # joint between links i - 1 and i (0-based)
        tau = k * (th[i] - th[i - 1]) + d * (vth[i] - vth[i - 1])
        f[3 * i + 2] -= tau
        f[3 * i - 1] += tau
    f = f - alpha * mass * v
    B = ca.DM.zeros(3 * n, 1)
    B[2] = 1
    names = [f"{c}{i + 1}" for i in range(n) for c in ("x", "y", "theta")]
    return Model("flexible_arm", q, v, P, PARAMS, M=M, f=f, B=B, g=ca.vertcat(*cons),
                 h=th[0] + w * (th[1] - th[0]), overrides=overrides, q_names=names, u_names=["u"],
                 y_names=["link2_angle"])


def is_cartesian(model: Model) -> bool:
    """Whether ``model`` is the Cartesian formulation (it has the pin constraints)."""
    return model.ell > 0


def angles_of(model: Model, q):
    """The link angles ``theta_1..theta_n`` of a configuration (either formulation; rows of ``q``)."""
    return q[2::3] if is_cartesian(model) else q


def cartesian_configuration(n: int, theta, l: float) -> np.ndarray:
    """The Cartesian coordinates (x_i, y_i, theta_i) of the arm with link angles ``theta``."""
    theta = np.asarray(theta, float).ravel()
    q, top = np.zeros(3 * n), np.zeros(2)
    for i in range(n):
        e = np.array([np.sin(theta[i]), -np.cos(theta[i])])
        q[3 * i:3 * i + 2], q[3 * i + 2] = top + 0.5 * l * e, theta[i]
        top = top + l * e
    return q


def linear_matrices(n: int, values: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(M, K, D)`` of the linearization at the hanging arm (theta = 0), assembled in numpy
    (an independent construction for the tests)."""
    p = values
    mu, grav = inertia_coefficients(n, p["l"], p["m"])
    M = np.array(mu, float)
    K = np.diag([p["g"] * c for c in grav])
    L = np.zeros((n, n))
    for i in range(1, n):
        L[np.ix_([i - 1, i], [i - 1, i])] += [[1, -1], [-1, 1]]
    return M, K + p["k"] * L, p["d"] * L + p["alpha"] * M


def reference(model: Model, *, y0: float = 0.0, yf: float = 0.05, t0: float = 0.0, tf: float = 1.0) -> Reference:
    """The output angle moved from y0 to yf (rad) with the C^4 timing law of 003 Sect. 6.

    The elbow carries the weight of the arm below it, so its static deflection grows with n
    (0.23 rad at n = 32 for the default 0.05 rad move); larger moves make the inverse of a long
    arm strongly nonlinear (docs/gallery.md)."""
    return rest_to_rest(y0, yf, t0, tf, smoothness=4, name="y_ref")


def initial_configuration(model: Model) -> np.ndarray:
    """The hanging arm (all link angles 0)."""
    if is_cartesian(model):
        n = model.n // 3
        return cartesian_configuration(n, np.zeros(n), model.values["l"])
    return np.zeros(model.n)


def drawing(model: Model):
    """The chain of links hanging from the shoulder."""
    from invctl.plot.animate import Drawing

    l = model.params["l"]
    pts = {"shoulder": ca.vertcat(0, 0)}
    pos = ca.vertcat(0, 0)
    theta = angles_of(model, model.q)
    for i in range(theta.shape[0]):
        pos = pos + l * ca.vertcat(ca.sin(theta[i]), -ca.cos(theta[i]))
        pts[f"j{i + 1}"] = pos
    names = list(pts)
    return Drawing(points=pts, links=list(zip(names[:-1], names[1:])))


def _check(values: dict) -> None:
    from invctl.errors import ParameterError

    n = _check_n(values["n"])
    if _check_coordinates(values.get("coordinates", COORDINATES[0])) == "cartesian" and n > MAX_N_CARTESIAN:
        raise ParameterError(f"flexible_arm: coordinates=cartesian is limited to n <= {MAX_N_CARTESIAN} (its "
                             "inverse model has dense (8n + 1)^2 blocks per node: n = 16 needed more than 22 GB); "
                             f"use coordinates=angles (the default) for n = {n}")
    bad = {k: values[k] for k in ("k", "d", "alpha", "g") if values[k] < 0}
    if bad:
        raise ParameterError(f"flexible_arm: springs, dampers, alpha and g must be >= 0, got {bad}")
    if values["w"] == 0:
        raise ParameterError("flexible_arm: w = 0 is the colocated output theta1 (minimum phase, the rest of the arm "
                             "is unobservable); choose w != 0")


SCENE = Scene(
    "flexible_arm", build, params={"n": DEFAULT_N, **PARAMS}, choices={"coordinates": COORDINATES},
    integer=("n",), positive=("n", "l", "m"),
    validate=_check,
    tracking=Tracking(reference=reference, plant={"m": 1.2}, initial_configuration=initial_configuration),
    drawing=drawing,
    description="n-link arm with elastic passive joints (Rayleigh damped), motor at the shoulder, output = angle of "
                "link 2: non-minimum phase (one real unstable zero); the simulated plant's links are 20 % heavier; "
                "--set coordinates=cartesian: the same arm in Cartesian coordinates with pin constraints",
)
