"""Figures of the tracking study (content of 003 Figs. 5-9) and of a single closed-loop run."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from . import grid, save

_COLORS = {"C1": "tab:blue", "C2": "tab:orange", "C3": "tab:green", "C1-inv": "tab:purple"}
#: a curve larger than this many times every other curve of its axis does not set the axis (drawn clipped, marked)
OFF_SCALE = 10.0


def plot_run(res, path=None, units=None):
    """One run: outputs vs reference, errors, inputs, funnel ratios (``units``: name -> unit; default the
    scene's, recorded in the run's ``meta``)."""
    units = dict(units or (res.meta or {}).get("units") or {})
    fig, ax = grid(2, 2, (10, 6.5))
    t = res.t
    ynames, unames = res.row_names("y"), res.row_names("u")
    curves = []
    for i in range(res.y.shape[0]):
        line, = ax[0, 0].plot(t, res.y[i], label=ynames[i])
        ax[0, 0].plot(t, res.y_ref[i], "k--", lw=0.8)
        curves += [(res, t, res.y[i], line.get_color()), (None, t, res.y_ref[i], "k")]
    _clip_departed(ax[0, 0], curves)
    ax[0, 0].set(title=f"{_label(res.controller, res)}: outputs (dashed: reference)", xlabel="t [s]",
                 ylabel=_unit_label(ynames, units, "outputs"))
    ax[0, 0].legend()
    curves = []
    for name in ["output", *res.signals]:
        err = np.maximum(res.signal_error(name), 1e-12)
        line, = ax[0, 1].semilogy(t, err, label=f"{name} error")
        curves.append((res, t, err, line.get_color()))
    _clip_departed(ax[0, 1], curves, log=True)
    ax[0, 1].set(title="tracking errors", xlabel="t [s]", ylabel="error norm")
    ax[0, 1].legend()
    for i in range(res.u.shape[0]):
        ax[1, 0].plot(t, res.u[i], label=unames[i])
    ax[1, 0].set(title="inputs", xlabel="t [s]", ylabel=_unit_label(unames, units, "inputs"))
    ax[1, 0].legend()
    if res.ratios.size:
        for k in range(res.ratios.shape[0]):
            ax[1, 1].plot(t, res.ratios[k], label=res.ratio_names[k] if res.ratio_names else f"level {k}")
        ax[1, 1].axhline(1.0, color="k", lw=1)
        ax[1, 1].set(title=f"funnel ratios (max {res.max_funnel_ratio:.3f})", xlabel="t [s]", ylim=(0, 1.05),
                     ylabel="phi|e| [-] (boundary 1)")
        ax[1, 1].legend(fontsize=7)
    else:
        ax[1, 1].axis("off")
        ax[1, 1].text(0.1, 0.5, "no feedback: no funnel", transform=ax[1, 1].transAxes)
    save(fig, path)
    return fig


def _label(name: str, r, extra: str = "") -> str:
    """``name`` with ``extra`` and, for a run that left its region or funnel, where it did."""
    dep = r.departure
    return name + extra + (f" ({dep[1]} at t = {dep[0]:.3g} s)" if dep is not None else "")


def _clip_departed(ax, curves, log=False, both=False):
    """Keep the axis limits to the runs that stayed inside (and to the others up to their exit; a curve larger
    than ``OFF_SCALE`` times every other one up to where it passes them) and mark every exit with a cross: ``curves`` are ``(run, x, y, color)`` over ``run.t`` (run ``None``: a curve that always
    counts, e.g. the reference); ``both`` limits x as well as y."""
    keep, marks, beyond = [], [], False
    scale = [float(np.nanmax(np.abs(y))) if np.size(y) else 0.0 for _, _, y, _ in curves]
    for c, (r, x, y, color) in enumerate(curves):
        dep = r.departure if r is not None else None
        k = len(x) if dep is None else int(np.searchsorted(r.t, dep[0], side="right"))
        # a run far off the others' scale (diverging without leaving a funnel or region) counts up to where it
        # passes the largest of the others
        others = max((s for i, s in enumerate(scale) if i != c), default=0.0)
        if r is not None and not both and others > 0 and scale[c] > OFF_SCALE * others:
            k = min(k, int(np.argmax(np.abs(np.asarray(y)) > others)) or 1)
            dep = dep or (float(x[k - 1]), "off scale")
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


def _by_unit(names, units: dict) -> list:
    """Indices of ``names`` grouped by their unit (undeclared units: one group per name), in order."""
    groups: dict = {}
    for i, n in enumerate(names):
        unit = (units or {}).get(n)
        groups.setdefault(unit if unit else f"\0{n}", []).append(i)
    return list(groups.values())


def _unit_label(names, units, what: str = "") -> str:
    """An axis label of the curves ``names``: ``q1, q2 [m]`` (the unit of the first; ``name [unit]`` for one curve,
    without a unit when none is declared); ``<what> (mixed units)`` when ``what`` is given and the units differ."""
    if what and len(_by_unit(names, units)) > 1:
        return f"{what} (mixed units)"
    unit = (units or {}).get(names[0])
    return (", ".join(names) + (f" [{unit}]" if unit else "")) if len(names) <= 3 else (
        f"[{unit}]" if unit else ", ".join(names))


def plot_study(study, out_dir=None, fmt="png", captions=None, units=None):
    """The comparison figures of a tracking study (the content of 003 Figs. 5-9 for any scene):
    ``states`` (states of the first run, one axis per unit), ``path_<signal>`` (planar signals such as an end
    effector), ``errors`` (each output's error and each signal's error norm), ``inputs`` and ``funnel``
    (every level's ratio ``phi |e|``, boundary at 1: the numbers of the table).  ``captions`` maps these keys
    to a prefix (e.g. the paper's figure numbers); ``units`` maps quantity names to units (default: the
    study's ``info["units"]``, declared by the scene).  A run that left its region or funnel is marked with
    a cross and does not set the axes."""
    captions = dict(captions or {})
    units = dict(units if units is not None else (study.info.get("units") or {}))
    runs = study.runs
    figs = {}
    main = runs.get("C1") or next(iter(runs.values()))
    qn = main.row_names("q")
    groups = _by_unit(qn, units)
    fig, axs = grid(len(groups), 1, (7, 1.2 + 2.2 * len(groups)), sharex=True, labelled_rows=False)
    for ax, idx in zip(axs[:, 0], groups):
        curves = []
        for i in idx:
            line, = ax.plot(main.t, main.q[i], label=qn[i])
            curves.append((main, main.t, main.q[i], line.get_color()))
        _clip_departed(ax, curves)
        ax.set(ylabel=_unit_label([qn[i] for i in idx], units))
        ax.legend(ncol=3, fontsize=8)
    axs[0, 0].set(title=_title(captions, "states", f"states under {_label(main.controller, main)}"))
    axs[-1, 0].set(xlabel="t [s]")
    figs["states"] = fig

    for sname, ref in main.signals_ref.items():
        if ref.shape[0] != 2:
            continue
        key = f"path_{sname.replace(' ', '_')}"
        fig, axs = grid(1, 1, (6, 4.5))
        ax = axs[0, 0]
        ax.plot(ref[0], ref[1], "k--", lw=1.2, label="reference")
        curves = [(None, ref[0], ref[1], "k")]
        for name, r in runs.items():
            ax.plot(r.signals[sname][0], r.signals[sname][1], color=_COLORS.get(name), label=_label(name, r))
            curves.append((r, r.signals[sname][0], r.signals[sname][1], _COLORS.get(name)))
        _clip_departed(ax, curves, both=True)
        unit = f" [{units[sname]}]" if sname in units else ""
        ax.set(title=_title(captions, key, f"{sname}: path"), aspect="equal", xlabel=f"{sname}, x{unit}",
               ylabel=f"{sname}, y{unit}")
        ax.legend()
        figs[key] = fig

    yn = main.row_names("y")
    panels = [(f"output {n}: y - y_ref", (lambda r, i=i: r.y[i] - r.y_ref[i]), units.get(n)) for i, n in enumerate(yn)]
    panels += [(f"{s}: ||error||", (lambda r, s=s: r.signal_error(s)), units.get(s)) for s in main.signals]
    cols = min(len(panels), 3)
    rows = -(-len(panels) // cols)
    fig, axs = grid(rows, cols, (4.8 * cols, 3.4 * rows + 0.4), suptitle=True)
    for k, (label, err, unit) in enumerate(panels):
        ax = axs[k // cols, k % cols]
        for name, r in runs.items():
            extra = f" (cum. ||e_y|| {r.cumulative_errors['output']:.3g})" if k == 0 else ""
            ax.plot(r.t, err(r), color=_COLORS.get(name), label=_label(name, r, extra))
        ax.axhline(0.0, color="k", lw=0.5)
        _clip_departed(ax, [(r, r.t, err(r), _COLORS.get(name)) for name, r in runs.items()])
        ax.set(title=label, xlabel="t [s]", ylabel="error" + (f" [{unit}]" if unit else " (no unit declared)"))
        ax.legend(fontsize=8)
    for k in range(len(panels), rows * cols):
        axs[k // cols, k % cols].axis("off")
    fig.suptitle(_title(captions, "errors", "tracking errors"))
    figs["errors"] = fig

    m = main.u.shape[0]
    fig, axs = grid(m, 1, (7, 2.6 * m + 0.6), sharex=True, labelled_rows=False)
    unames = main.row_names("u")
    for name, r in runs.items():
        for i in range(m):
            axs[i, 0].plot(r.t, r.u[i], color=_COLORS.get(name), label=_label(name, r))
    for i in range(m):
        _clip_departed(axs[i, 0], [(r, r.t, r.u[i], _COLORS.get(name)) for name, r in runs.items()])
        axs[i, 0].set(ylabel=_unit_label([unames[i]], units))
    axs[0, 0].set(title=_title(captions, "inputs", "inputs"))
    axs[-1, 0].set(xlabel="t [s]")
    axs[0, 0].legend()
    figs["inputs"] = fig

    figs["funnel"] = _plot_ratios(runs, _title(captions, "funnel", "funnel ratios phi|e| (boundary at 1)"))

    if out_dir is not None:
        d = Path(out_dir)
        d.mkdir(parents=True, exist_ok=True)
        for key, f in figs.items():
            save(f, d / f"{key}.{fmt}")
    return figs


def _plot_ratios(runs, title):
    """One axis per funnel level (the ratio names of the first feedback run): ``phi |e|`` of every run with
    feedback, the boundary at 1; the legend gives each run's largest ratio over all levels (the table's
    ``max phi|e|``)."""
    fb = {n: r for n, r in runs.items() if r.ratios.size}
    if not fb:
        fig, axs = grid(1, 1, (7, 2))
        ax = axs[0, 0]
        ax.axis("off")
        ax.text(0.05, 0.5, "no run with feedback: no funnel", transform=ax.transAxes)
        return fig
    first = next(iter(fb.values()))
    names = first.ratio_names or [f"level {k}" for k in range(first.ratios.shape[0])]
    fig, axs = grid(len(names), 1, (7, 1.0 + 1.6 * len(names)), sharex=True, labelled_rows=False)
    for k, (ax, level) in enumerate(zip(axs[:, 0], names)):
        for name, r in fb.items():
            if k < r.ratios.shape[0]:
                extra = f" (max over levels {r.max_funnel_ratio:.3g})" if k == 0 else ""
                ax.plot(r.t, r.ratios[k], color=_COLORS.get(name), label=_label(name, r, extra), gid=f"ratio:{name}:{k}")
                dep = r.departure
                if dep is not None:
                    ax.plot([r.t[-1] if dep[1] == "left its funnel" else dep[0]],
                            [min(float(np.interp(dep[0], r.t, r.ratios[k])), 1.05)],
                            marker="X", ms=9, color=_COLORS.get(name), mec="k", ls="none", zorder=5)
        ax.axhline(1.0, color="k", lw=1.2)
        ax.axhline(0.9, color="0.5", lw=0.6, ls=":")
        ax.set(ylim=(0, 1.08), ylabel=level + " [-]")
    axs[0, 0].set(title=title)
    axs[0, 0].legend(fontsize=7)
    axs[-1, 0].set(xlabel="t [s]")
    return fig


def plot_funnels(controller, t_end: float, path=None):
    """The funnel boundaries ``1/phi_i,j(t)`` of every level and ``1/phi(t)`` of ``e_bar`` (log scale)."""
    t = np.linspace(0.0, t_end, 400)
    fig, axs = grid(1, 1, (7, 4))
    ax = axs[0, 0]
    for i, row in enumerate(controller.levels.phi):
        for j, f in enumerate(row):
            ax.semilogy(t, np.ravel(f.boundary(t)), label=f"level {i + 1},{j}")
    ax.semilogy(t, np.ravel(controller.phi_bar.boundary(t)), "k", lw=1.5, label="e_bar")
    ax.set(title="funnel boundaries 1/phi(t)", xlabel="t [s]", ylabel="1/phi (units of the error level)")
    ax.legend(fontsize=8, ncol=2)
    save(fig, path)
    return fig
