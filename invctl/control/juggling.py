"""Input/output linearization of juggling structures, 000 (23)-(27).

With the outputs ``y = f'(q)`` (selected gaps) the dynamics give

    y'' = Dcal(q) tau + Mcal(q) lam - Fcal(q, v)                       (24)

with ``Dcal = W^T M^{-1} B`` (decoupling matrix), ``Mcal = W^T M^{-1} W``
(the Delassus matrix) and ``Fcal = -(W^T M^{-1} f + d/dt(W^T) v)`` (``f =
-C v - G`` in the model's convention, so ``Fcal`` is (24)'s bracket).  If
``rank Dcal = dim y``, the input

    tau = Dcal^+ (tau_bar + Fcal) + (I - Dcal^+ Dcal) tau_tilde

gives ``y'' = tau_bar + Mcal lam`` (linear in free flight).  000 (25) prints
``Dcal^+ [tau_bar - Fcal]``, which with (24) as printed would leave
``-2 Fcal``; the sign used here is the one that linearizes (checked in the
tests; see docs/reproduction.md).
"""
from __future__ import annotations

from typing import Sequence

import casadi as ca
import numpy as np

from ..contact.mechanics import ContactSystem
from ..errors import RelativeDegreeError
from .pdplus import FeedbackLaw


def io_terms(model, outputs: Sequence[int]):
    """Symbolic ``(Dcal, Mcal, Fcal, y, y_dot)`` of (24) for the gap indices ``outputs``."""
    cs = ContactSystem(model)
    idx = [int(i) for i in outputs]
    W = cs.W[:, idx]
    MiW = ca.solve(model.M, W)
    Dcal = ca.mtimes(MiW.T, model.B)
    Mcal = ca.mtimes(W.T, MiW)
    Fcal = -(ca.mtimes(MiW.T, model.f) + cs.Wdot_v[idx])
    return Dcal, Mcal, Fcal, cs.gap[idx], ca.mtimes(W.T, model.v)


def io_decoupling_check(model, q, outputs: Sequence[int], *, rtol: float = 1e-9) -> np.ndarray:
    """``Dcal(q)``; raises :class:`RelativeDegreeError` when its rank is below ``dim y``
    (no uniform relative degree (2, ..., 2))."""
    Dcal = io_terms(model, outputs)[0]
    D = np.array(ca.Function("D", [model.q, model.theta], [Dcal])(np.asarray(q, float), model.theta_values))
    s = np.linalg.svd(D, compute_uv=False)
    if s.size < len(outputs) or s.min() <= rtol * max(1.0, s.max()):
        raise RelativeDegreeError(
            f"decoupling matrix W^T M^-1 B of outputs {list(outputs)} has rank < {len(outputs)} at q = "
            f"{np.round(q, 6).tolist()} (singular values {s.tolist()}); the I/O linearization (25) does not exist")
    return D


def juggling_law(model, outputs: Sequence[int], *, Ky, Dy, y_d, tau_tilde=None) -> FeedbackLaw:
    """I/O-linearizing law with ``tau_bar = -Ky (y - y_d) - Dy y'``.

    In free flight (``lam = 0``) the gaps then obey the linear dynamics
    ``y'' + Dy y' + Ky (y - y_d) = 0``; ``tau_tilde(model, t, kappa)`` (optional)
    acts in ``ker Dcal`` (zero dynamics, 000 (26)(c)).
    """
    k = len(outputs)
    Ky, Dy, y_d = (np.broadcast_to(np.asarray(x, float), (k,)) for x in (Ky, Dy, y_d))
    names = tuple([f"Ky{i + 1}" for i in range(k)] + [f"Dy{i + 1}" for i in range(k)] + [f"yd{i + 1}" for i in range(k)])

    def build(model, t, kappa):
        Dcal, Mcal, Fcal, y, yd = io_terms(model, outputs)
        ky, dy, ydes = kappa[0:k], kappa[k:2 * k], kappa[2 * k:3 * k]
        tb = -ky * (y - ydes) - dy * yd
        Dp = ca.mtimes(Dcal.T, ca.inv(ca.mtimes(Dcal, Dcal.T)))
        u = ca.mtimes(Dp, tb + Fcal)
        if tau_tilde is not None:
            tt = ca.SX(tau_tilde(model, t, kappa))
            u = u + tt - ca.mtimes(Dp, ca.mtimes(Dcal, tt))
        return u, None

    return FeedbackLaw("juggling_io", names, tuple(np.r_[Ky, Dy, y_d]), build, {"outputs": list(outputs),
                                                                              "lyapunov": False})
