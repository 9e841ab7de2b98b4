"""Figures of the tracking study (content of 003 Figs. 5-9) and of a single closed-loop run."""
from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["plot_run", "plot_study", "plot_funnels"]

_COLORS = {"C1": "tab:blue", "C2": "tab:orange", "C3": "tab:green", "C1-inv": "tab:purple"}


def _plt():
    import matplotlib.pyplot as plt

    return plt


def plot_run(res, path=None):
    """One run: outputs vs reference, errors, inputs, funnel ratios."""
    plt = _plt()
    fig, ax = plt.subplots(2, 2, figsize=(10, 6.5), constrained_layout=True)
    t = res.t
    ynames = res.y_names or [f"y{i + 1}" for i in range(res.y.shape[0])]
    curves = []
    for i in range(res.y.shape[0]):
        line, = ax[0, 0].plot(t, res.y[i], label=ynames[i])
        ax[0, 0].plot(t, res.y_ref[i], "k--", lw=0.8)
        curves += [(res, t, res.y[i], line.get_color()), (None, t, res.y_ref[i], "k")]
    _clip_departed(ax[0, 0], curves)
    ax[0, 0].set(title=f"{_label(res.controller, res)}: outputs (dashed: reference)", xlabel="t [s]")
    ax[0, 0].legend()
    curves = []
    for name in ["output", *res.signals]:
        err = np.maximum(res.signal_error(name), 1e-12)
        line, = ax[0, 1].semilogy(t, err, label=f"{name} error")
        curves.append((res, t, err, line.get_color()))
    _clip_departed(ax[0, 1], curves, log=True)
    ax[0, 1].set(title="tracking errors", xlabel="t [s]")
    ax[0, 1].legend()
    unames = res.u_names or [f"u{i + 1}" for i in range(res.u.shape[0])]
    for i in range(res.u.shape[0]):
        ax[1, 0].plot(t, res.u[i], label=unames[i])
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


def _label(name: str, r, extra: str = "") -> str:
    """``name`` with ``extra`` and, for a run that left its region or funnel, where it did."""
    dep = r.departure
    return name + extra + (f" ({dep[1]} at t = {dep[0]:.3g} s)" if dep is not None else "")


def _clip_departed(ax, curves, log=False, both=False):
    """Keep the axis limits to the runs that stayed inside (and to the others up to their exit) and mark
    every exit: ``curves`` are ``(run, x, y, color)`` over ``run.t`` (run ``None``: a curve that always
    counts, e.g. the reference); ``both`` limits x as well as y."""
    keep, marks, beyond = [], [], False
    for r, x, y, color in curves:
        dep = r.departure if r is not None else None
        k = len(x) if dep is None else int(np.searchsorted(r.t, dep[0], side="right"))
        keep.append((np.asarray(x)[:k], np.asarray(y)[:k]))
        beyond |= k < len(x)
        if dep is not None and k:
            marks.append((x[k - 1], y[k - 1], color))
    lims = {}
    for i, setter in ((1, ax.set_ylim), (0, ax.set_xlim))[:2 if both else 1]:
        vals = np.concatenate([c[i] for c in keep]) if keep else np.zeros(0)
        vals = vals[np.isfinite(vals) & ((vals > 0) if log else True)]
        if not (beyond and vals.size):
            continue
        lo, hi = float(vals.min()), float(vals.max())
        if log:
            lo, hi = lo / 1.5, hi * 1.5
        else:
            pad = 0.05 * (hi - lo) or 0.05 * max(abs(hi), 1.0)
            lo, hi = lo - pad, hi + pad
        setter(lo, hi)
        lims[i] = (lo, hi)
    for x, y, color in marks:
        x = float(np.clip(x, *lims[0])) if 0 in lims else x
        y = float(np.clip(y, *lims[1])) if 1 in lims else y
        ax.plot([x], [y], marker="X", ms=10, color=color, mec="k", ls="none", zorder=5)


def _title(captions: dict, key: str, text: str) -> str:
    return f"{captions[key]}: {text}" if key in captions else text


def plot_study(study, out_dir=None, fmt="png", captions=None):
    """The comparison figures of a tracking study (the content of 003 Figs. 5-9 for any scene):
    ``states`` (states of the first run), ``path_<signal>`` (planar signals such as an end effector),
    ``errors`` (output and signal errors), ``inputs`` and ``funnel`` (error norm and funnel boundary).
    ``captions`` maps these keys to a prefix (e.g. the paper's figure numbers)."""
    plt = _plt()
    captions = dict(captions or {})
    runs = study.runs
    figs = {}
    main = runs.get("C1") or next(iter(runs.values()))
    fig, ax = plt.subplots(figsize=(7, 4.5), constrained_layout=True)
    curves = []
    for i, name in enumerate(main.q_names or [f"q{i + 1}" for i in range(main.q.shape[0])]):
        line, = ax.plot(main.t, main.q[i], label=name)
        curves.append((main, main.t, main.q[i], line.get_color()))
    _clip_departed(ax, curves)
    ax.set(title=_title(captions, "states", f"states under {_label(main.controller, main)}"), xlabel="t [s]")
    ax.legend(ncol=2, fontsize=8)
    figs["states"] = fig

    for sname, ref in main.signals_ref.items():
        if ref.shape[0] != 2:
            continue
        key = f"path_{sname.replace(' ', '_')}"
        fig, ax = plt.subplots(figsize=(6, 4.5), constrained_layout=True)
        ax.plot(ref[0], ref[1], "k--", lw=1.2, label="reference")
        curves = [(None, ref[0], ref[1], "k")]
        for name, r in runs.items():
            ax.plot(r.signals[sname][0], r.signals[sname][1], color=_COLORS.get(name), label=_label(name, r))
            curves.append((r, r.signals[sname][0], r.signals[sname][1], _COLORS.get(name)))
        _clip_departed(ax, curves, both=True)
        ax.set(title=_title(captions, key, f"{sname}: path"), aspect="equal")
        ax.legend()
        figs[key] = fig

    kinds = ["output", *main.signals]
    fig, axs = plt.subplots(1, len(kinds), figsize=(5.5 * len(kinds), 4), constrained_layout=True, squeeze=False)
    for ax, kind in zip(axs[0], kinds):
        for name, r in runs.items():
            ax.plot(r.t, r.signal_error(kind), color=_COLORS.get(name),
                    label=_label(name, r, f" ({r.cumulative_errors[kind]:.3g})"))
        _clip_departed(ax, [(r, r.t, r.signal_error(kind), _COLORS.get(name)) for name, r in runs.items()])
        ax.set(title=_title(captions, "errors", f"{kind} error (cumulative in legend)"), xlabel="t [s]")
        ax.legend()
    figs["errors"] = fig

    m = main.u.shape[0]
    fig, axs = plt.subplots(m, 1, figsize=(7, 2.6 * m + 0.6), sharex=True, constrained_layout=True, squeeze=False)
    unames = main.u_names or [f"u{i + 1}" for i in range(m)]
    for name, r in runs.items():
        for i in range(m):
            axs[i, 0].plot(r.t, r.u[i], color=_COLORS.get(name), label=_label(name, r))
    for i in range(m):
        _clip_departed(axs[i, 0], [(r, r.t, r.u[i], _COLORS.get(name)) for name, r in runs.items()])
        axs[i, 0].set(ylabel=unames[i])
    axs[0, 0].set(title=_title(captions, "inputs", "inputs"))
    axs[-1, 0].set(xlabel="t [s]")
    axs[0, 0].legend()
    figs["inputs"] = fig

    fig, ax = plt.subplots(figsize=(7, 4), constrained_layout=True)
    drawn, curves = False, []
    for name, r in runs.items():
        if r.ratios.size:
            err = np.maximum(np.abs(r.e_bar), 1e-12)
            ax.semilogy(r.t, err, color=_COLORS.get(name), label=_label(f"||e_bar|| {name}", r))
            curves.append((r, r.t, err, _COLORS.get(name)))
            if not drawn:
                ax.semilogy(r.t, 1.0 / r.phi_bar, "k", lw=1.2, label="funnel boundary 1/phi")
                curves.append((None, r.t, 1.0 / r.phi_bar, "k"))
                drawn = True
    _clip_departed(ax, curves, log=True)
    ax.set(title=_title(captions, "funnel", "error norm and funnel boundary"), xlabel="t [s]")
    ax.legend()
    figs["funnel"] = fig

    if out_dir is not None:
        d = Path(out_dir)
        d.mkdir(parents=True, exist_ok=True)
        for key, f in figs.items():
            f.savefig(d / f"{key}.{fmt}", dpi=120)
    return figs


def plot_funnels(controller, t_end: float, path=None):
    """The funnel boundaries ``1/phi_i,j(t)`` of every level and ``1/phi(t)`` of ``e_bar`` (log scale)."""
    plt = _plt()
    t = np.linspace(0.0, t_end, 400)
    fig, ax = plt.subplots(figsize=(7, 4), constrained_layout=True)
    for i, row in enumerate(controller.levels.phi):
        for j, f in enumerate(row):
            ax.semilogy(t, np.ravel(f.boundary(t)), label=f"level {i + 1},{j}")
    ax.semilogy(t, np.ravel(controller.phi_bar.boundary(t)), "k", lw=1.5, label="e_bar")
    ax.set(title="funnel boundaries 1/phi(t)", xlabel="t [s]")
    ax.legend(fontsize=8, ncol=2)
    if path:
        fig.savefig(path, dpi=120)
    return fig
