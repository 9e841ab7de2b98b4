"""Figures of contact simulations: phase portrait, gaps, impulses, energy and V."""
from __future__ import annotations



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
    ax[0, 0].set_xlabel("q")
    ax[0, 0].set_ylabel("v")
    ax[0, 0].set_title("phase portrait")
    ax[0, 0].legend(fontsize=8)
    gn = tr.names.get("gaps", [f"f{i + 1}" for i in range(tr.gaps.shape[0])])
    for i in range(tr.gaps.shape[0]):
        ax[0, 1].plot(tr.t, tr.gaps[i], lw=0.8, label=gn[i])
    ax[0, 1].axhline(0, color="k", lw=0.5)
    ax[0, 1].set_title(f"gaps (max violation {tr.max_gap_violation:.2e})")
    ax[0, 1].set_xlabel("t [s]")
    ax[0, 1].legend(fontsize=8)
    for i in range(tr.P.shape[0]):
        ax[1, 0].plot(tr.t[:tr.P.shape[1]], tr.P[i], lw=0.8, label=f"P {gn[i]}")
    ax[1, 0].set_title("impulses per step")
    ax[1, 0].set_xlabel("t [s]")
    ax[1, 0].legend(fontsize=8)
    ax[1, 1].plot(tr.t, tr.energy, lw=0.8, label="energy")
    ax[1, 1].plot(tr.t, tr.V, lw=0.8, ls="--", label="V")
    try:
        ti = tr.impact_times
        for t in ti[:200]:
            ax[1, 1].axvline(t, color="r", lw=0.3, alpha=0.4)
    except Exception:
        pass
    ax[1, 1].set_title(f"energy and V (max V increase {tr.max_V_increase:.2e})")
    ax[1, 1].set_xlabel("t [s]")
    ax[1, 1].legend(fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    if path:
        fig.savefig(path, dpi=120)
    return fig


def plot_convergence(hs, errors: dict, slopes: dict | None = None, path=None, title="time-step convergence"):
    """Log-log errors versus h with fitted slopes."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4.5))
    for name, err in errors.items():
        lab = name if not slopes else f"{name} (slope {slopes[name]:.2f})"
        ax.loglog(hs, err, "o-", label=lab)
    ax.set_xlabel("h [s]")
    ax.set_ylabel("error")
    ax.set_title(title)
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    if path:
        fig.savefig(path, dpi=120)
    return fig
