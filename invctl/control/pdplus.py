"""PD + gravity compensation (000 (36)) and PD+ tracking (000 (48), (57)).

Controllers are :class:`FeedbackLaw` objects: symbolic CasADi laws
``u(q, v, t; kappa)`` together with their Lyapunov function ``V(q, v, t;
kappa)``.  The gains and set points ``kappa`` are symbols, so the compiled
time-stepping loop takes new gains without being rebuilt.

The controllers act on the *actuated coordinates* ``q_1 = q[idx]`` of the
open system (000 Sect. 5): the input matrix must select them
(``B[:, j] = e_{idx_j}``).  ``V`` is (37)/(50): the closed-loop error energy
of the actuated part plus the mechanical energy of the rest,
``1/2 v2^T M22 v2 + U_2(q)`` with ``U_2`` the potential of the unactuated
bodies given by the scene.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import casadi as ca
import numpy as np

from ..errors import DimensionError, ModelError, ParameterError


@dataclass(frozen=True)
class FeedbackLaw:
    """A symbolic feedback law with gains carried as parameters.

    Parameters
    ----------
    name : str
    kappa_names : sequence of str
        Names of the law's parameters (gains, set points, preload ``beta``).
    kappa_values : sequence of float
        Their default values.
    build : callable
        ``build(model, t, kappa) -> (u, V)``: SX expressions in ``model.q``,
        ``model.v``, ``model.theta``, ``t`` and ``kappa``; ``V`` may be None.
    info : dict
        Extra data (actuated indices, ...).
    """

    name: str
    kappa_names: tuple
    kappa_values: tuple
    build: Callable
    info: dict = field(default_factory=dict)

    def symbolic(self, model, t):
        """``(u, V, kappa)`` SX for ``model`` and time symbol ``t``."""
        kappa = ca.SX.sym("kappa", len(self.kappa_names))
        u, V = self.build(model, t, kappa)
        u = ca.SX(u)
        if u.shape[0] != model.m:
            raise DimensionError(f"law {self.name!r} returns {u.shape[0]} inputs, model has m = {model.m}")
        return u, (ca.SX(0) if V is None else ca.SX(V)), kappa

    def values(self, **overrides) -> np.ndarray:
        """Gain vector with overrides by name."""
        vals = dict(zip(self.kappa_names, self.kappa_values))
        unknown = sorted(set(overrides) - set(vals))
        if unknown:
            raise ParameterError(f"law {self.name!r}: unknown gain(s) {unknown}; known: {list(vals)}")
        vals.update({k: float(v) for k, v in overrides.items()})
        return np.array([vals[k] for k in self.kappa_names], float)

    def function(self, model) -> ca.Function:
        """``(q, v, t, theta, kappa) -> (u, V)`` as a CasADi Function."""
        t = ca.SX.sym("t")
        u, V, kappa = self.symbolic(model, t)
        return ca.Function(self.name, [model.q, model.v, t, model.theta, kappa], [u, V],
                           ["q", "v", "t", "theta", "kappa"], ["u", "V"])


def selection_indices(model, idx: Sequence[int] | None = None) -> list[int]:
    """Actuated coordinate indices; checks that ``B`` selects them (collocation)."""
    B = ca.DM(ca.evalf(ca.substitute(model.B, model.theta, ca.DM(model.theta_values)))) if not ca.depends_on(
        model.B, model.q) else None
    if B is None:
        raise ModelError(f"model {model.name!r}: B depends on q; PD laws need a constant selection matrix")
    Bn = np.array(B)
    if idx is None:
        idx = [int(np.flatnonzero(Bn[:, j])[0]) for j in range(Bn.shape[1])]
    idx = [int(i) for i in idx]
    E = np.zeros((model.n, len(idx)))
    E[idx, range(len(idx))] = 1.0
    if Bn.shape[1] != len(idx) or not np.allclose(Bn, E):
        raise ModelError(
            f"model {model.name!r}: B does not select coordinates {idx} (collocated control needs "
            f"B[:, j] = e_idx[j]); got B = {Bn.tolist()}")
    return idx


def gravity_vector(model) -> ca.SX:
    """``G(q) = -f(q, 0)``: the potential (and any velocity-free) force."""
    return -ca.substitute(model.f, model.v, ca.SX.zeros(model.n))


def christoffel_C(model) -> ca.SX:
    """Coriolis matrix ``C(q, v)`` from the Christoffel symbols of ``M`` (so that
    ``dM/dt - 2C`` is skew-symmetric, 000 Sect. 5)."""
    M, q, v, n = model.M, model.q, model.v, model.n
    dM = [ca.jacobian(M[:, k], q) for k in range(n)]  # dM[k][i, j] = dM_ik/dq_j
    C = ca.SX.zeros(n, n)
    for i in range(n):
        for j in range(n):
            c = 0
            for k in range(n):
                c += 0.5 * (dM[j][i, k] + dM[k][i, j] - ca.jacobian(M[j, k], q[i])) * v[k]
            C[i, j] = c
    return C


def _rest(model, idx):
    return [i for i in range(model.n) if i not in idx]


def _energy_rest(model, idx, potential):
    r = _rest(model, idx)
    v2 = model.v[r] if r else ca.SX(0, 1)
    T2 = 0.5 * ca.mtimes([v2.T, model.M[r, r], v2]) if r else 0
    U2 = 0 if potential is None else potential
    return T2 + U2


def zero_input(potential=None) -> FeedbackLaw:
    """``u = 0``; ``V`` is the mechanical energy ``1/2 v^T M v + U(q)``."""

    def build(model, t, kappa):
        V = 0.5 * ca.mtimes([model.v.T, model.M, model.v]) + (0 if potential is None else potential)
        return ca.SX.zeros(model.m), V

    return FeedbackLaw("open_loop", (), (), build)


def pd_gravity(model, *, Kp, Kv, q_d, idx=None, potential=None) -> FeedbackLaw:
    """PD + gravity compensation (000 (36)) on the actuated coordinates.

    ``tau_1 = G_1(q) - Kp (q_1 - q_1d) - Kv v_1`` with diagonal gains, and
    ``V = 1/2 v^T M v + 1/2 (q_1 - q_1d)^T Kp (q_1 - q_1d) + U_2(q)`` (37)
    where ``potential`` is ``U_2`` (SX in ``model.q``/``model.theta``).
    """
    idx = selection_indices(model, idx)
    k = len(idx)
    Kp, Kv, q_d = (np.broadcast_to(np.asarray(x, float), (k,)) for x in (Kp, Kv, q_d))
    if np.any(Kp <= 0) or np.any(Kv <= 0):
        raise ModelError(f"pd_gravity: gains must be positive (000 (36)), got Kp={Kp.tolist()}, Kv={Kv.tolist()}")
    names = tuple([f"Kp{j + 1}" for j in range(k)] + [f"Kv{j + 1}" for j in range(k)] + [f"qd{j + 1}" for j in range(k)])

    def build(model, t, kappa):
        kp, kv, qd = kappa[0:k], kappa[k:2 * k], kappa[2 * k:3 * k]
        q1, v1 = model.q[idx], model.v[idx]
        G1 = gravity_vector(model)[idx]
        e = q1 - qd
        u = G1 - kp * e - kv * v1
        T1 = 0.5 * ca.mtimes([v1.T, model.M[idx, idx], v1])
        V = T1 + 0.5 * ca.sum1(kp * e**2) + _energy_rest(model, idx, potential)
        if k < model.n:  # coupling of kinetic energy between blocks (zero for block-diagonal M)
            r = _rest(model, idx)
            V = V + ca.mtimes([v1.T, model.M[idx, r], model.v[r]])
        return u, V

    return FeedbackLaw("pd_gravity", names, tuple(np.r_[Kp, Kv, q_d]), build, {"idx": idx})


def pd_plus_tracking(model, *, Kp, Kv, q_d: Callable, idx=None, potential=None) -> FeedbackLaw:
    """PD+ tracking (000 (48); (57) when only ``q_1 = q[idx]`` is actuated).

    ``tau_1 = M_11 qdd_1d + C_11(q, v) qd_1d + G_1(q) - Kv (v_1 - qd_1d) - Kp (q_1 - q_1d)``
    with ``C`` from Christoffel symbols; ``V = 1/2 e_v^T M_11 e_v + 1/2 e^T Kp e
    + 1/2 v_2^T M_22 v_2 + U_2`` ((50), and the candidate after (57)).

    Parameters
    ----------
    q_d : callable
        ``q_d(t) -> SX`` (length ``len(idx)``), smooth in the CasADi time
        symbol; its derivatives are taken by AD.
    """
    idx = selection_indices(model, idx)
    k = len(idx)
    Kp, Kv = (np.broadcast_to(np.asarray(x, float), (k,)) for x in (Kp, Kv))
    if np.any(Kp <= 0) or np.any(Kv <= 0):
        raise ModelError(f"pd_plus_tracking: gains must be positive (000 (48)), got Kp={Kp.tolist()}, Kv={Kv.tolist()}")
    names = tuple([f"Kp{j + 1}" for j in range(k)] + [f"Kv{j + 1}" for j in range(k)])
    C = christoffel_C(model)

    def build(model, t, kappa):
        kp, kv = kappa[0:k], kappa[k:2 * k]
        qd = ca.SX(q_d(t))
        if qd.shape[0] != k:
            raise DimensionError(f"pd_plus_tracking: q_d(t) has length {qd.shape[0]}, expected {k}")
        dqd = ca.jacobian(qd, t)
        ddqd = ca.jacobian(dqd, t)
        q1, v1 = model.q[idx], model.v[idx]
        M11 = model.M[idx, idx]
        e, ev = q1 - qd, v1 - dqd
        u = ca.mtimes(M11, ddqd) + ca.mtimes(C[idx, idx], dqd) + gravity_vector(model)[idx] - kv * ev - kp * e
        V = 0.5 * ca.mtimes([ev.T, M11, ev]) + 0.5 * ca.sum1(kp * e**2) + _energy_rest(model, idx, potential)
        return u, V

    return FeedbackLaw("pd_plus", names, tuple(np.r_[Kp, Kv]), build, {"idx": idx, "q_d": q_d})
