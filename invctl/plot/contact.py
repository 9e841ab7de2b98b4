"""Figures of contact simulations: phase portrait, gaps, impulses, energy and V."""
from __future__ import annotations

import numpy as np

from . import save


def active_window(tr, rel: float = 1e-2, pad: float = 0.1):
    """``(t_start, t_stop)`` that holds everything that happens: the span where the velocities or the changes
    of the impulses from step to step exceed ``rel`` times their largest value (a persistent contact with a
    constant impulse is no event), padded by ``pad`` of its length; ``None`` if that is more than half of the
    run (nothing to zoom)."""
    t = np.asarray(tr.t, float)
    if t.size < 3:
        return None
    v = np.max(np.abs(np.atleast_2d(tr.v)), axis=0) if np.size(tr.v) else np.zeros_like(t)
    act = v > rel * max(float(v.max(initial=0.0)), 1e-300)
    P = np.atleast_2d(tr.P) if np.size(tr.P) else np.zeros((0, 0))
    if P.shape[-1] > 1:
        p = np.max(np.abs(np.diff(P, axis=1)), axis=0)
        act[1:p.size + 1] |= p > rel * max(float(p.max()), 1e-300)
    idx = np.flatnonzero(act)
    if idx.size == 0:
        return None
    a, b = float(t[idx[0]]), float(t[idx[-1]])
    width = max(b - a, t[1] - t[0])
    lo, hi = max(t[0], a - pad * width), min(t[-1], b + pad * width)
    return (lo, hi) if hi - lo < 0.5 * (t[-1] - t[0]) else None



def plot_contact_trajectory(tr, path=None, *, coords=None, title: str | None = None):
    """Four panels: phase portrait, gap history, impulses, energy and V(t) with its jumps.

    Returns the matplotlib figure (written to ``path`` when given).
    """
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(2, 2, figsize=(10, 7))
    coords = range(tr.q.shape[0]) if coords is None else coords  # q, v, gaps, P: time along the last axis
    qn = tr.names.get("q", [f"q{i + 1}" for i in range(tr.q.shape[0])])
    for i in coords:
        ax[0, 0].plot(tr.q[i], tr.v[i], lw=0.8, label=qn[i])
    ax[0, 0].set(title="phase portrait", xlabel="q", ylabel="v")
    ax[0, 0].legend(fontsize=8)
    gn = tr.names.get("gaps", [f"f{i + 1}" for i in range(tr.gaps.shape[0])])
    for i in range(tr.gaps.shape[0]):
        ax[0, 1].plot(tr.t, tr.gaps[i], lw=0.8, label=gn[i])
    ax[0, 1].axhline(0, color="k", lw=0.5)
    ax[0, 1].set(title=f"gaps (max violation {tr.max_gap_violation:.2e})", xlabel="t [s]",
                 ylabel="gap (units of the gap function)")
    ax[0, 1].legend(fontsize=8)
    for i in range(tr.P.shape[0]):
        ax[1, 0].plot(tr.t[:tr.P.shape[1]], tr.P[i], lw=0.8, label=f"P {gn[i]}")
    ax[1, 0].set(title="impulses per step", xlabel="t [s]", ylabel="impulse per step")
    ax[1, 0].legend(fontsize=8)
    ax[1, 1].plot(tr.t, tr.energy, lw=0.8, label="energy")
    ax[1, 1].plot(tr.t, tr.V, lw=0.8, ls="--", label="V")
    try:
        ti = tr.impact_times
        for t in ti[:200]:
            ax[1, 1].axvline(t, color="r", lw=0.3, alpha=0.4)
    except Exception:
        pass
    ax[1, 1].set(title=f"energy and V (max V increase {tr.max_V_increase:.2e})", xlabel="t [s]",
                 ylabel="energy, V [J]")
    ax[1, 1].legend(fontsize=8)
    win = active_window(tr)
    if win is not None:     # zoom the time axes to where things happen; say so
        for a in (ax[0, 1], ax[1, 0], ax[1, 1]):
            a.set_xlim(*win)
            a.set_xlabel(f"t [s] (zoomed to [{win[0]:.3g}, {win[1]:.3g}] of [{tr.t[0]:.3g}, {tr.t[-1]:.3g}]; "
                         "motion < 1 % of its peak outside)")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    save(fig, path)
    return fig
