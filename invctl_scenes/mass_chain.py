"""A chain of n masses on springs and dampers with a non-minimum-phase output.

A wall holds mass 1 by a spring-damper (k0, c0); masses i and i + 1 are joined by
spring-dampers (k, c); all masses are m.  The force u acts on mass 1, the output is

    y = x_1 - lam x_n,

so ``M = m I``, ``f = -K x - C x'``, ``B = e_1`` and the model is linear.

Zeros.  With ``P(s) = m s^2 I + C s + K`` the transfer function of ``x_j`` is
``adj(P)_j1 / det P``: ``x_1`` has the numerator ``N_1(s) = det P_22`` (rows and
columns 2..n: the chain with mass 1 held, degree 2n - 2, ``N_1(0) = k^(n-1)``) and
``x_n`` the numerator ``(c s + k)^(n-1)`` (a path through the n - 1 couplings).
The zeros of ``G(s) = Y(s)/U(s)`` are the roots of

    Z(s) = N_1(s) - lam (c s + k)^(n-1)        (degree 2n - 2, leading coefficient m^(n-1)),

independent of the wall (k0, c0).  ``Z(0) = k^(n-1) (1 - lam)``, so for ``lam > 1``
``Z(0) < 0 < Z(+inf)`` and ``Z`` has a real zero in the right half plane: the output is
non-minimum phase.  For ``n = 2``: ``Z(s) = m s^2 + c (1 - lam) s + k (1 - lam)``; with
the defaults (m = 1, k = 100, c = 5, lam = 2) the zeros are ``(5 +- sqrt(425))/2`` =
``+12.81`` and ``-7.81``.  The relative degree is 2 with ``Gamma = h' M^-1 B = 1/m``
(``x_n`` has relative degree n + 1 >= 3), so ``1/G`` has a polynomial part of degree 2.
The dampers c = 5 N s/m keep every other zero well inside the left half plane for
n <= 6 (the slowest stable zero is below -1.4/s; with c = 1, n = 5 has an unstable
complex pair and n = 4 a zero at -0.15 +- 16i).

:func:`exact_zeros` evaluates ``Z`` from numpy polynomials (independently of the
CasADi model); ``tests/test_gallery.py`` compares the feedforward of
:func:`invctl.inversion.invert` with the exact stable inverse of ``1/G(s)`` (partial
fractions).
"""
from __future__ import annotations

import casadi as ca
import numpy as np

from invctl.model import Model, ParamSet
from invctl.reference import Reference, rest_to_rest
from invctl.scenes import Scene, Tracking

#: physical parameters (n is structural: it fixes the number of coordinates)
PARAMS = {"m": 1.0, "k0": 100.0, "c0": 5.0, "k": 100.0, "c": 5.0, "lam": 2.0}
DEFAULT_N = 2


def _check_n(n) -> int:
    from invctl.errors import ParameterError

    if float(n) != round(float(n)) or int(round(float(n))) < 2:
        raise ParameterError(f"mass_chain: n must be an integer >= 2 (the output couples mass 1 and mass n), got {n!r}")
    return int(round(float(n)))


def build(n: float = DEFAULT_N, **overrides: float) -> Model:
    """The chain of ``n`` masses with output ``y = x_1 - lam x_n``."""
    n = _check_n(n)
    P = ParamSet(list(PARAMS))
    m, k0, c0, k, c, lam = (P[name] for name in PARAMS)
    x, v = ca.SX.sym("x", n), ca.SX.sym("v", n)
    # spring-damper forces: wall on mass 1, then between neighbours (s_i acts on i - 1 and i)
    f = ca.SX.zeros(n)
    f[0] = -k0 * x[0] - c0 * v[0]
    for i in range(1, n):
        s = k * (x[i] - x[i - 1]) + c * (v[i] - v[i - 1])
        f[i - 1] += s
        f[i] -= s
    B = ca.DM.zeros(n, 1)
    B[0] = 1
    return Model("mass_chain", x, v, P, PARAMS, M=m * ca.SX.eye(n), f=f, B=B, h=x[0] - lam * x[n - 1],
                 overrides=overrides, q_names=[f"x{i + 1}" for i in range(n)], u_names=["F"], y_names=["y"])


def reference(model: Model, *, y0: float = 0.0, yf: float = 0.1, t0: float = 0.0, tf: float = 1.0) -> Reference:
    """y moved from y0 to yf (metres) with the C^4 timing law of 003 Sect. 6."""
    return rest_to_rest(y0, yf, t0, tf, smoothness=4, name="y_ref")


def polynomials(n: int, values: dict) -> tuple[np.poly1d, np.poly1d]:
    """``(Z, D)``: numerator and denominator of ``G(s) = Y(s)/U(s)`` as numpy polynomials
    (``D = det P(s)``, ``Z`` as in the module doc), built from the parameter values."""
    n = _check_n(n)
    p = values
    Pm = [[np.poly1d([0.0]) for _ in range(n)] for _ in range(n)]
    for i in range(n):
        Pm[i][i] = np.poly1d([p["m"], 0.0, 0.0])
    Pm[0][0] = Pm[0][0] + np.poly1d([p["c0"], p["k0"]])
    e = np.poly1d([p["c"], p["k"]])
    for i in range(n - 1):
        Pm[i][i] = Pm[i][i] + e
        Pm[i + 1][i + 1] = Pm[i + 1][i + 1] + e
        Pm[i][i + 1] = Pm[i][i + 1] - e
        Pm[i + 1][i] = Pm[i + 1][i] - e
    D = _tridiagonal_det(Pm)
    Z = _tridiagonal_det([row[1:] for row in Pm[1:]]) - p["lam"] * e ** (n - 1)
    return Z, D


def _tridiagonal_det(T) -> np.poly1d:
    """Determinant of a tridiagonal polynomial matrix by the three-term recurrence."""
    d_prev, d = np.poly1d([1.0]), T[0][0]
    for i in range(1, len(T)):
        d_prev, d = d, T[i][i] * d - T[i][i - 1] * T[i - 1][i] * d_prev
    return d


def exact_zeros(model: Model, n: int | None = None) -> np.ndarray:
    """The zeros of ``G(s)``: roots of ``Z(s)`` (module doc), sorted by real part."""
    n = model.n if n is None else n
    Z, _ = polynomials(n, model.values)
    return np.sort_complex(Z.roots)


def initial_configuration(model: Model) -> np.ndarray:
    return np.zeros(model.n)


def drawing(model: Model):
    """The masses on a horizontal line (a vertical offset per mass makes the springs visible)."""
    from invctl.plot.animate import Drawing

    n = model.n
    gap = 0.3
    pts = {"wall": ca.vertcat(-gap, 0)}
    pts.update({f"m{i + 1}": ca.vertcat(i * gap + model.q[i], 0) for i in range(n)})
    links = [("wall", "m1")] + [(f"m{i}", f"m{i + 1}") for i in range(1, n)]
    return Drawing(points=pts, links=links, segments=[((-gap, -0.1), (-gap, 0.1))])


def _check(values: dict) -> None:
    from invctl.errors import ParameterError

    _check_n(values["n"])
    bad = {k: values[k] for k in ("k0", "c0", "k", "c") if values[k] < 0}
    if bad:
        raise ParameterError(f"mass_chain: springs and dampers must be >= 0, got {bad}")
    if values["k"] == 0 and values["c"] == 0:
        raise ParameterError("mass_chain: k = c = 0 decouples the masses (mass n is then not influenced by u)")


SCENE = Scene(
    "mass_chain", build, params={"n": DEFAULT_N, **PARAMS}, integer=("n",), positive=("n", "m"),
    validate=_check,
    tracking=Tracking(reference=reference, plant={"m": 1.2}, initial_configuration=initial_configuration),
    drawing=drawing,
    description="chain of n masses on spring-dampers, force on mass 1, output y = x1 - lam xn: a real zero in the "
                "right half plane for lam > 1 (non-minimum phase); the simulated plant's masses are 20 % heavier",
)
