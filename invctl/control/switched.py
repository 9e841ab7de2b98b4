"""The switched motion/force controller 002 (3) in closed loop with the 1-DOF plants.

Plants (each a small frozen dataclass):

* :class:`RigidWallPlant` -- 002 (1)-(2): ``M x'' + b x' = F_c - F_e``,
  ``F_e = ke x + be x'`` for ``x > 0``;
* :class:`CompliantWristPlant` -- 002 (24)-(25): arm ``x`` and tip ``x_t``
  joined by ``F_t = kt (x - x_t) + bt (x' - x_t')``; the wall acts on the tip.

The controller (3) switches between (3a) (motion control, ``x <= 0``) and (3b)
(force control, ``x > 0``).  Everything is linear in the plant state, the
reference state ``(x_d, x_d', y_1, y_1')`` and the inputs ``(x~_d, F~_d)``,
so each combination of contact bits yields one matrix of the closed loop;
:class:`ClosedLoop` assembles them for exact propagation.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import ParameterError
from ..reference.gluing import DEG, GluedReference, input_selector, nilpotent_block


def _positive(obj, names, allow_zero=()):
    for n in names:
        v = getattr(obj, n)
        if not math.isfinite(v):
            raise ParameterError(f"{type(obj).__name__}.{n} = {v} is not finite")
        if v < 0 or (v == 0 and n not in allow_zero):
            raise ParameterError(f"{type(obj).__name__}.{n} must be {'>= 0' if n in allow_zero else '> 0'}, got {v}")


@dataclass(frozen=True)
class SwitchedForceController:
    """002 (3): ``F_c = Ma x_d'' + kd (x_d' - x') + kp (x_d - x)`` for ``x <= 0``,
    ``F_c = F_d + kf (F_d - F_e) - bf x'`` for ``x > 0``."""

    Ma: float
    kp: float
    kd: float
    kf: float
    bf: float

    def __post_init__(self):
        _positive(self, ("Ma", "kp", "kd"), allow_zero=("Ma",))
        for n in ("kf", "bf"):
            if not math.isfinite(getattr(self, n)):
                raise ParameterError(f"controller gain {n} is not finite")

    def force(self, contact, x, v, xd, xd_dot, xd_ddot, Fd, Fe):
        """``F_c`` (vectorized)."""
        free = self.Ma * xd_ddot + self.kd * (xd_dot - v) + self.kp * (xd - x)
        cont = (1 + self.kf) * Fd - self.kf * Fe - self.bf * v
        return np.where(contact, cont, free)


@dataclass(frozen=True)
class RigidWallPlant:
    """002 (1)-(2). State ``(x, x')``; one switching surface ``x = 0`` for wall and controller."""

    M: float
    b: float
    ke: float
    be: float
    n = 2
    names = ("x", "v")
    #: surfaces: (name, position index, velocity index, switches wall, switches controller)
    surfaces = (("x", 0, 1, True, True),)

    def __post_init__(self):
        _positive(self, ("M", "b", "ke", "be"), allow_zero=("b", "be"))

    def rows(self, wall: bool):
        """``(A_plant, f_c, fe_row)``: ``s' = A s + f_c F_c``, ``F_e = fe_row . s``."""
        fe = np.array([self.ke, self.be]) if wall else np.zeros(2)
        A = np.array([[0.0, 1.0], [0.0, -self.b / self.M]])
        A[1] -= fe / self.M
        fc = np.array([0.0, 1.0 / self.M])
        return A, fc, fe

    def initial_state(self, x0, v0):
        return np.array([x0, v0])


@dataclass(frozen=True)
class CompliantWristPlant:
    """002 (24)-(25). State ``(x, x', x_t, x_t')``; wall at ``x_t = 0``.

    ``controller_on`` chooses the surface that switches the controller (3):
    ``"arm"`` (``x = 0``, as printed in (3)) or ``"tip"`` (``x_t = 0``, i.e. the
    contact itself, equivalent to switching on the measured force).
    """

    M: float
    b: float
    Mt: float
    kt: float
    bt: float
    ke: float
    be: float
    controller_on: str = "arm"
    n = 4
    names = ("x", "v", "xt", "vt")

    def __post_init__(self):
        _positive(self, ("M", "b", "Mt", "kt", "bt", "ke", "be"), allow_zero=("b", "bt", "be"))
        if self.controller_on not in ("arm", "tip"):
            raise ParameterError(f"controller_on must be 'arm' or 'tip', got {self.controller_on!r}")

    @property
    def surfaces(self):
        if self.controller_on == "tip":
            return (("xt", 2, 3, True, True),)
        return (("xt", 2, 3, True, False), ("x", 0, 1, False, True))

    def rows(self, wall: bool):
        M, Mt, kt, bt = self.M, self.Mt, self.kt, self.bt
        fe = np.array([0.0, 0.0, self.ke, self.be]) if wall else np.zeros(4)
        ft = np.array([kt, bt, -kt, -bt])
        A = np.zeros((4, 4))
        A[0, 1] = 1.0
        A[2, 3] = 1.0
        A[1] = (-ft - np.array([0.0, self.b, 0.0, 0.0])) / M
        A[3] = (ft - fe) / Mt
        fc = np.array([0.0, 1.0 / M, 0.0, 0.0])
        return A, fc, fe

    def initial_state(self, x0, v0):
        return np.array([x0, v0, x0, v0])


class ClosedLoop:
    """Plant + controller (3) + glued reference as one piecewise-linear system.

    Augmented state ``S = (plant state, r = (x_d, x_d', y_1, y_1'), Taylor states of x~_d and F~_d)``.
    A *mode* is ``(bits, contact_phase, sliding)``: one bit per switching surface
    (True = ``position > 0``), the reference phase, and the index of a surface the
    state slides on (or -1).
    """

    def __init__(self, plant, controller: SwitchedForceController, reference: GluedReference):
        self.plant = plant
        self.controller = controller
        self.reference = reference
        self.np = plant.n
        self.nr = reference.n
        self.nu = reference.n_inputs * (DEG + 1)
        self.n = self.np + self.nr + self.nu
        self._sel = input_selector(reference.n_inputs)
        self._cache: dict = {}

    # -- mode bookkeeping ---------------------------------------------------------------
    @property
    def surfaces(self):
        return self.plant.surfaces

    def wall_on(self, bits) -> bool:
        return any(b for b, s in zip(bits, self.surfaces) if s[3])

    def ctrl_on(self, bits) -> bool:
        return any(b for b, s in zip(bits, self.surfaces) if s[4])

    # -- rows on the augmented state -------------------------------------------------------
    def ref_rows(self, phase: bool) -> dict[str, np.ndarray]:
        """Reference outputs as rows on ``S``."""
        out = {}
        for k, row in self.reference.output_rows(phase).items():
            full = np.zeros(self.n)
            full[self.np:self.np + self.nr] = row[:4]
            full[self.np + self.nr:] = row[4:] @ self._sel
            out[k] = full
        return out

    def fe_row(self, bits) -> np.ndarray:
        _, _, fe = self.plant.rows(self.wall_on(bits))
        full = np.zeros(self.n)
        full[:self.np] = fe
        return full

    def fc_row(self, bits, phase) -> np.ndarray:
        c = self.controller
        rr = self.ref_rows(phase)
        full = np.zeros(self.n)
        if self.ctrl_on(bits):
            full += (1 + c.kf) * rr["Fd"] - c.kf * self.fe_row(bits)
            full[1] -= c.bf
        else:
            full += c.Ma * rr["xd_ddot"] + c.kd * rr["xd_dot"] + c.kp * rr["xd"]
            full[1] -= c.kd
            full[0] -= c.kp
        return full

    def matrix(self, bits: tuple, phase: bool, sliding: int = -1) -> np.ndarray:
        """The augmented matrix of one mode (cached)."""
        key = (tuple(bits), bool(phase), int(sliding))
        if key in self._cache:
            return self._cache[key]
        A = np.zeros((self.n, self.n))
        Ap, fc, _ = self.plant.rows(self.wall_on(bits))
        A[:self.np, :self.np] = Ap
        A[:self.np] += np.outer(fc, self.fc_row(bits, phase))
        Ar, Br = self.reference.matrices(phase)
        i0 = self.np
        A[i0:i0 + self.nr, i0:i0 + self.nr] = Ar
        A[i0:i0 + self.nr, i0 + self.nr:] = Br @ self._sel
        A[i0 + self.nr:, i0 + self.nr:] = nilpotent_block(self.reference.n_inputs)
        if sliding >= 0:
            _, ip, iv, _, _ = self.surfaces[sliding]
            A[ip] = 0.0
            A[iv] = 0.0
        self._cache[key] = A
        return A

    def plant_eigenvalues(self, bits, phase) -> np.ndarray:
        A = self.matrix(bits, phase)
        return np.linalg.eigvals(A[:self.np, :self.np])

    def initial_state(self, t0: float) -> np.ndarray:
        r = self.reference.initial_state()
        S = np.zeros(self.n)
        S[:self.np] = self.plant.initial_state(r[0], r[1])
        S[self.np:self.np + self.nr] = r
        S[self.np + self.nr:] = self.reference.taylor_inputs(t0)
        return S

    def contact_reset(self, S: np.ndarray) -> np.ndarray:
        """Reference reset at the start of a contact phase (App. A), on the augmented state."""
        R = self.reference.contact_reset()
        i0 = self.np
        ru = np.concatenate([S[i0:i0 + self.nr], self._sel @ S[i0 + self.nr:]])
        S = S.copy()
        S[i0:i0 + self.nr] = R @ ru
        return S
