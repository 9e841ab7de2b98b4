"""Figures of the tracking study (content of 003 Figs. 5-9) and of a single closed-loop run."""
from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["plot_run", "plot_study"]

_COLORS = {"C1": "tab:blue", "C2": "tab:orange", "C3": "tab:green", "C1-42": "tab:purple"}


def _plt():
    import matplotlib.pyplot as plt

    return plt


def plot_run(res, path=None):
    """One run: outputs vs reference, errors, inputs, funnel ratios."""
    plt = _plt()
    fig, ax = plt.subplots(2, 2, figsize=(10, 6.5), constrained_layout=True)
    t = res.t
    for i in range(res.y.shape[0]):
        ax[0, 0].plot(t, res.y[i], label=f"y{i + 1}")
        ax[0, 0].plot(t, res.y_ref[i], "k--", lw=0.8)
    ax[0, 0].set(title=f"{res.controller}: outputs (dashed: reference)", xlabel="t [s]")
    ax[0, 0].legend()
    ax[0, 1].semilogy(t, np.maximum(res.output_error, 1e-12), label="||y - y_ref||")
    ax[0, 1].semilogy(t, np.maximum(res.endeffector_error, 1e-12), label="||r_app - r_ref||")
    ax[0, 1].set(title="tracking errors", xlabel="t [s]")
    ax[0, 1].legend()
    for i in range(res.u.shape[0]):
        ax[1, 0].plot(t, res.u[i], label=f"u{i + 1}")
    ax[1, 0].set(title="inputs", xlabel="t [s]")
    ax[1, 0].legend()
    if res.ratios.size:
        for k in range(res.ratios.shape[0]):
            ax[1, 1].plot(t, res.ratios[k], label=res.ratio_names[k] if res.ratio_names else f"level {k}")
        ax[1, 1].axhline(1.0, color="k", lw=1)
        ax[1, 1].set(title=f"funnel ratios (max {res.max_funnel_ratio:.3f})", xlabel="t [s]", ylim=(0, 1.05))
        ax[1, 1].legend(fontsize=7)
    else:
        ax[1, 1].axis("off")
        ax[1, 1].text(0.1, 0.5, "no feedback: no funnel", transform=ax[1, 1].transAxes)
    if path:
        fig.savefig(path, dpi=120)
    return fig


def plot_study(study, out_dir=None, fmt="png"):
    """Figures 5-9 of 003 in content: states (C1), end-effector path, errors, inputs, funnel."""
    plt = _plt()
    runs = study.runs
    figs = {}
    main = runs.get("C1") or next(iter(runs.values()))
    fig, ax = plt.subplots(2, 1, figsize=(7, 5.5), sharex=True, constrained_layout=True)
    for i, name in enumerate(main.q_names or [f"q{i}" for i in range(main.q.shape[0])]):
        (ax[0] if i < 2 else ax[1]).plot(main.t, main.q[i], label=name)
    ax[0].set(title=f"Fig. 5: states under {main.controller}", ylabel="[m]")
    ax[1].set(xlabel="t [s]", ylabel="[rad]")
    ax[0].legend()
    ax[1].legend()
    figs["fig5_states"] = fig

    fig, ax = plt.subplots(figsize=(6, 4.5), constrained_layout=True)
    ax.plot(main.r_ref[0], main.r_ref[1], "k--", lw=1.2, label="reference")
    for name, r in runs.items():
        ax.plot(r.r[0], r.r[1], color=_COLORS.get(name), label=name)
    ax.set(title="Fig. 6: end-effector position r_app", xlabel="e1 [m]", ylabel="e2 [m]", aspect="equal")
    ax.legend()
    figs["fig6_endeffector"] = fig

    fig, ax = plt.subplots(1, 2, figsize=(11, 4), constrained_layout=True)
    for name, r in runs.items():
        ax[0].plot(r.t, r.output_error, color=_COLORS.get(name), label=f"{name} ({r.cumulative_output_error:.3g})")
        ax[1].plot(r.t, r.endeffector_error, color=_COLORS.get(name),
                   label=f"{name} ({r.cumulative_endeffector_error:.3g})")
    ax[0].set(title="Fig. 7a: ||y - y_ref|| (cumulative in legend)", xlabel="t [s]")
    ax[1].set(title="Fig. 7b: ||r_app - r_app,ref||", xlabel="t [s]")
    ax[0].legend()
    ax[1].legend()
    figs["fig7_errors"] = fig

    fig, ax = plt.subplots(2, 1, figsize=(7, 5.5), sharex=True, constrained_layout=True)
    for name, r in runs.items():
        for i in range(r.u.shape[0]):
            ax[i].plot(r.t, r.u[i], color=_COLORS.get(name), label=name)
    ax[0].set(title="Fig. 8: inputs", ylabel="u1 [N]")
    ax[1].set(xlabel="t [s]", ylabel="u2 [N]")
    ax[0].legend()
    figs["fig8_inputs"] = fig

    fig, ax = plt.subplots(figsize=(7, 4), constrained_layout=True)
    drawn = False
    for name, r in runs.items():
        if r.ratios.size:
            ax.semilogy(r.t, np.maximum(np.abs(r.e_bar), 1e-12), color=_COLORS.get(name), label=f"||e_bar|| {name}")
            if not drawn:
                ax.semilogy(r.t, 1.0 / r.phi_bar, "k", lw=1.2, label="funnel boundary 1/phi")
                drawn = True
    ax.set(title="Fig. 9: error norm and funnel boundary", xlabel="t [s]")
    ax.legend()
    figs["fig9_funnel"] = fig

    if out_dir is not None:
        d = Path(out_dir)
        d.mkdir(parents=True, exist_ok=True)
        for key, f in figs.items():
            f.savefig(d / f"{key}.{fmt}", dpi=120)
    return figs
