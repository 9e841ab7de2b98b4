"""Helpers for users' own tests.

``assert_inverts(model, inverse, reference, tol)`` forward-simulates ``model``
under the feedforward of ``inverse`` from the inverse's state at ``t0`` and
checks ``max |y - y_ref| <= tol`` (see :func:`invctl.inversion.forward_check`
for the integrator -- CasADi CVODES (or scipy DOP853 with ``method="DOP853"``)
on the index-1 ODE of ``model.accel_and_multipliers``, no code shared with the
collocation -- and for
the windowed restarts used when the open-loop model is unstable).
"""
from __future__ import annotations

from .inversion.verify import forward_check


def assert_inverts(model, inverse, reference, tol: float = 1e-6, **options) -> dict:
    """Assert that ``inverse.u`` reproduces ``reference`` on ``model``.

    Parameters
    ----------
    model : Model
        The model to simulate (the reference model of the inversion, or a plant).
    inverse : Inverse
        The result of :func:`invctl.inversion.invert`.
    reference : Reference
        ``y_ref``.
    tol : float
        Largest accepted ``max_t |y(t) - y_ref(t)|_inf`` on ``[t0, tf + 10 %]``.
    **options
        Passed to :func:`invctl.inversion.forward_check` (``t_start``, ``t_end``,
        ``window``, ``max_gain``, ``rtol``, ``atol``, ``method``).

    Returns
    -------
    dict
        The forward-check report (``error``, ``t_worst``, ``window``, ...).

    Raises
    ------
    AssertionError
        With the error, where it occurs, and the inverse's diagnostics.
    """
    rep = forward_check(model, inverse, reference, **options)
    if not rep["error"] <= tol:
        d = inverse.diagnostics
        raise AssertionError(
            f"the feedforward does not invert {getattr(model, 'name', 'the model')}: max |y - y_ref| = "
            f"{rep['error']:.3e} > tol = {tol:.1e} at t = {rep['t_worst']:.4g} s "
            f"(forward simulation from the inverse state at t0, {rep['windows']} window(s) of {rep['window']:.3g} s; "
            f"inverse: {d.get('scheme')} N={d.get('N')}, status {d.get('status')}, position residual "
            f"{d.get('residuals', {}).get('position', float('nan')):.2g}). Refine the mesh (N or tol=...) "
            "or check that model and inverse use the same parameters")
    return rep
