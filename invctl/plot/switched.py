"""Figures of the switched position/force study (002 Figs. 2-4, 6, 7 and Lambda maps)."""
from __future__ import annotations

import math

import numpy as np


def _plt():
    import matplotlib.pyplot as plt

    return plt


def _shade(ax, intervals, color="0.85", label=None):
    for i, (a, b) in enumerate(intervals):
        ax.axvspan(a, b, color=color, lw=0, label=label if i == 0 else None, zorder=0)


def plot_simulation(sim, axes=None, *, title=None, overlay=None, overlay_label="reduced model"):
    """Position (top) and contact force against desired force (bottom); contact phases shaded grey.

    ``overlay`` (another simulation, e.g. the reduced model of Fig. 7) is drawn in blue.
    """
    plt = _plt()
    if axes is None:
        fig, axes = plt.subplots(2, 1, sharex=True, figsize=(7.5, 5.2))
    ax1, ax2 = axes
    for ax in axes:
        _shade(ax, sim.contact_intervals(), label="contact")
    ax1.plot(sim.t, 1e3 * sim.xd, "--", color="tab:orange", lw=1, label="$x_d$")
    ax1.plot(sim.t, 1e3 * sim.x, color="k", lw=1.2, label="$x$")
    if sim.xt.size:
        ax1.plot(sim.t, 1e3 * sim.xt, color="tab:green", lw=0.8, label="$x_t$ (tip)")
    ax1.axhline(0.0, color="0.4", lw=0.6)
    ax1.set_ylabel("position [mm]")
    ax2.plot(sim.t, sim.Fd_desired, "--", color="tab:orange", lw=1, label="$F_d$")
    ax2.plot(sim.t, sim.Fe, color="k", lw=1.2, label="$F_e$")
    if overlay is not None:
        ax1.plot(overlay.t, 1e3 * overlay.x, color="tab:blue", lw=1, label=f"$x$ {overlay_label}")
        ax2.plot(overlay.t, overlay.Fe, color="tab:blue", lw=1, label=f"$F_e$ {overlay_label}")
    ax2.set_ylabel("force [N]")
    ax2.set_xlabel("t [s]")
    ax1.legend(loc="best", fontsize=8)
    ax2.legend(loc="best", fontsize=8)
    ax1.set_title(title or f"{sim.label}: peak {sim.peak_force:.3g} N, {sim.bounces} bounces, "
                  f"force RMS error {sim.force_rms_error:.3g} N", fontsize=9)
    ax1.figure.tight_layout()
    return axes


def plot_phase_portrait(report, portrait, ax=None):
    """Switching lines of ``Sigma^w`` (Fig. 2), real eigenvectors, and one worst-case trajectory.

    ``portrait`` holds what :meth:`invctl.stability.conewise.StabilityReport.phase_portrait` computed:
    ``eigenvectors`` ({1: [(lambda, v)], 2: [...]}) and the worst-case trajectory ``z`` (N, 2)."""
    plt = _plt()
    if ax is None:
        _, ax = plt.subplots(figsize=(5.2, 5))
    s = report.system
    # normalise z2 by sqrt(K1) so both axes are comparable
    sc = math.sqrt(s.K1)
    ax.axhline(0, color="k", lw=0.8)
    if s.dB != 0:
        slope = -s.dK / s.dB
        d = np.array([1.0, slope / sc]) / math.hypot(1.0, slope / sc) * 1e3
        ax.plot([-d[0], d[0]], [-d[1], d[1]], color="k", lw=0.8, label="switching lines")
    else:
        ax.axvline(0, color="k", lw=0.8)
    for i, col in ((1, "tab:blue"), (2, "tab:red")):
        for lam, v in portrait["eigenvectors"][i]:
            v = np.array([v[0], v[1] / sc]) / np.hypot(v[0], v[1] / sc) * 1e3
            ax.plot([-v[0], v[0]], [-v[1], v[1]], ":", color=col, label=f"eigvec A{i} (lambda={lam:.3g})")
    zs = np.asarray(portrait["z"], float)
    # angle-preserving radial compression r -> log(1 + r) keeps lines through 0 straight
    w = np.column_stack([zs[:, 0], zs[:, 1] / sc])
    r = np.hypot(w[:, 0], w[:, 1])
    w = w * (np.log1p(r) / np.where(r > 0, r, 1))[:, None] / math.log(2.0)
    ax.plot(w[:, 0], w[:, 1], color="tab:purple", lw=1, label="worst-case trajectory (radius log-compressed)")
    lim = 1.05 * max(1.0, np.max(np.abs(w)))
    ax.set_xlim(-lim, lim)
    ax.set_ylim(-lim, lim)
    ax.set_xlabel("$z_1$")
    ax.set_ylabel(r"$z_2/\sqrt{K_1}$")
    lam = f"Lambda = {report.Lambda:.4g}" if report.Lambda is not None else "visible eigenvector"
    ax.set_title(f"Sigma^w: {lam}, GUAS {'yes' if report.guas else 'no'}", fontsize=9)
    ax.legend(fontsize=7, loc="best")
    return ax


def plot_lambda_curve(values, lam, visible=None, ax=None, *, xlabel="bf [Ns/m]", logx=True):
    """Lambda against one parameter, with the stability border Lambda = 1 and visible-eigenvector points."""
    plt = _plt()
    if ax is None:
        _, ax = plt.subplots(figsize=(6, 3.8))
    ax.plot(values, lam, color="k", lw=1.2, label="Lambda (closed form)")
    if visible is not None and np.any(visible):
        ax.plot(np.asarray(values)[visible], np.ones(int(np.sum(visible))), "g|", ms=12,
                label="visible eigenvector (Lambda undefined)")
    ax.axhline(1.0, color="tab:red", lw=0.8, ls="--", label="Lambda = 1")
    ax.set_yscale("log")
    if logx:
        ax.set_xscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("Lambda")
    ax.legend(fontsize=8)
    return ax


def plot_lambda_map(kt, bt, lam, visible, ax=None, *, design=None):
    """Lambda over (kt, bt) in log colours; the Lambda = 1 contour, the visible-eigenvector region hatched."""
    plt = _plt()
    from matplotlib.colors import LogNorm

    if ax is None:
        _, ax = plt.subplots(figsize=(6.4, 4.6))
    L = np.where(visible, np.nan, lam)
    pc = ax.pcolormesh(kt, bt, L.T, norm=LogNorm(vmin=np.nanmin(L) if np.isfinite(np.nanmin(L)) else 1e-2,
                                                  vmax=max(np.nanmax(L), 1.01)), shading="auto", cmap="viridis")
    ax.figure.colorbar(pc, ax=ax, label="Lambda")
    if np.any(np.isfinite(L)):
        ax.contour(kt, bt, np.where(np.isfinite(L), L, 0.0).T, levels=[1.0], colors="r", linewidths=1.2)
    if np.any(visible):
        ax.contourf(kt, bt, visible.T.astype(float), levels=[0.5, 1.5], colors="none", hatches=["//"])
    if design is not None:
        ax.plot(*design, "r*", ms=10, label="design point")
        ax.legend(fontsize=8)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("kt [N/m]")
    ax.set_ylabel("bt [Ns/m]")
    ax.set_title("Lambda of the reduced wrist model (red: Lambda = 1; hatched: visible eigenvector)", fontsize=9)
    return ax
