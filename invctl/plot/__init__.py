"""Figures for results and studies. Import from the submodules."""
from __future__ import annotations

from pathlib import Path

#: dots per inch of the figures written to files (a 7-inch-wide figure: 700 pixels)
DPI = 100
#: fixed margins of :func:`grid` in inches: left (tick labels and axis label), right, bottom (tick labels and
#: axis label), top (a title), the suptitle's extra top, the gap between stacked axes without labels
MARGINS = {"left": 1.0, "right": 0.2, "bottom": 0.55, "top": 0.4, "suptitle": 0.3, "stack": 0.15}
#: at most this many tick intervals on a linear axis of :func:`grid` (matplotlib's own choice, a tick about every three
#: font sizes, puts 9 on a 7-inch time axis; each tick is artists and a text laid out at every draw)
NBINS = 5


def close(figures) -> None:
    """Close what a ``plot`` call returned (a figure, axes, or a list, dict or array of them)
    once it is written to disk, so that commands do not accumulate open pyplot figures."""
    import matplotlib.pyplot as plt
    import numpy as np

    if isinstance(figures, dict):
        figures = list(figures.values())
    for f in np.ravel(np.asarray(figures, dtype=object)):
        if f is not None:
            plt.close(getattr(f, "figure", f))


def grid(rows: int, cols: int, figsize, *, sharex: bool = False, labelled_rows: bool = True,
         suptitle: bool = False):
    """A pyplot figure of ``rows x cols`` axes (a 2-d array) at :data:`DPI` with fixed margins (:data:`MARGINS`)
    in place of a layout engine, which would lay it out at every draw: room for tick labels and an axis label left
    of and below every axes, a title above every row (``labelled_rows``; else above the first row only, the rows
    stacked, e.g. with ``sharex``) and a ``suptitle``; at most :data:`NBINS` tick intervals on a linear axis.
    :func:`save` checks the labels fit and lays out otherwise."""
    import matplotlib.pyplot as plt

    w, h = figsize
    m = MARGINS
    top = m["top"] + (m["suptitle"] if suptitle else 0.0)
    gap_h = m["bottom"] + m["top"] if labelled_rows else m["stack"]
    gap_w = m["left"] + m["right"]
    ax_w = (w - m["left"] - m["right"] - (cols - 1) * gap_w) / cols
    ax_h = (h - top - m["bottom"] - (rows - 1) * gap_h) / rows
    # titles at the top of their axes (matplotlib would place them above the y offset text of every axes at each draw,
    # computing the y ticks once more; save() checks the offset texts are clear of them)
    with plt.rc_context({"axes.titley": 1.0}):
        fig, axs = plt.subplots(rows, cols, figsize=figsize, dpi=DPI, sharex=sharex, squeeze=False, gridspec_kw=dict(
            left=m["left"] / w, right=1 - m["right"] / w, bottom=m["bottom"] / h, top=1 - top / h,
            wspace=gap_w / ax_w, hspace=gap_h / ax_h))
    for ax in axs.flat:
        ax.locator_params(nbins=NBINS)
    return fig, axs


def finish(fig, path=None, dpi: float = 120):
    """``fig`` laid out (``tight_layout``) and, with ``path``, written there at ``dpi``; returns ``fig``."""
    fig.tight_layout()
    if path:
        fig.savefig(path, dpi=dpi)
    return fig


def save(fig, path, dpi: float | None = None) -> Path | None:
    """Write ``fig`` to ``path`` (format by the suffix; nothing when ``path`` is None) with one draw. Matplotlib's ``savefig`` draws a figure
    with a layout engine (constrained layout, or the placeholder ``tight_layout`` leaves) twice, once to lay it out
    and once to render; a PNG here is rendered once, with the layout in the same draw, and written from the
    canvas. A figure without a layout engine (:func:`grid`) whose titles or axis labels leave the figure or run
    into an axes or another label after that draw is laid out by constrained layout and drawn again. PNGs are
    compressed at zlib level 1."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    if not path:
        return None
    path = Path(path)
    if dpi is not None:
        fig.set_dpi(dpi)
    canvas = fig.canvas
    if path.suffix.lower() != ".png" or not isinstance(canvas, FigureCanvasAgg):
        fig.savefig(path, dpi=fig.dpi)
        return path
    fixed = fig.get_layout_engine() is None
    canvas.draw()
    if fixed and crowded(fig):
        fig.set_layout_engine("constrained")
        canvas.draw()
    from matplotlib.image import imsave

    # zlib level 1: about twice as fast as Pillow's default 6, files about 10 % larger
    imsave(path, canvas.buffer_rgba(), format="png", origin="upper", dpi=fig.dpi, pil_kwargs={"compress_level": 1})
    return path


def crowded(fig) -> list[str]:
    """After a draw of ``fig``: the titles, axis labels, figure texts and offset texts (``1e-3`` above an axis) that
    leave the figure or overlap another of them (or, but for offset texts, an axes); empty: all fit. Each axis label
    lies beyond its tick labels, so these fit too."""
    renderer = fig.canvas.get_renderer()
    frame = fig.bbox
    shown = [ax for ax in fig.axes if ax.get_visible() and ax.axison]

    def boxes(texts):
        return [(t.get_text(), t.get_window_extent(renderer)) for t in texts if t.get_visible() and t.get_text()]

    labels = boxes([t for ax in shown for t in (ax.title, ax.xaxis.label, ax.yaxis.label)] + list(fig.texts))
    offsets = boxes([t for ax in shown for t in (ax.xaxis.offsetText, ax.yaxis.offsetText)])
    bad = []
    for i, (text, b) in enumerate(labels + offsets):
        out = b.x0 < frame.x0 - 0.5 or b.y0 < frame.y0 - 0.5 or b.x1 > frame.x1 + 0.5 or b.y1 > frame.y1 + 0.5
        others = [c for j, (_, c) in enumerate(labels) if j != i]
        if out or any(b.overlaps(c) for c in others) or (i < len(labels) and any(b.overlaps(ax.bbox) for ax in shown)):
            bad.append(text)
    return bad
