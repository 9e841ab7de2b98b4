"""What the feedforward buys (invctl.studies.compare) and the figures a control engineer reads (issue 19):
measures against closed forms on synthetic runs, the headline, axis labels with units, the funnel figure's
ratios equal to the table's, runs that left their funnel kept off the axes, the contact figures' zoom."""
from types import SimpleNamespace

import numpy as np
import pytest

from invctl.simulate.closed_loop import ClosedLoopResult
from invctl.studies.compare import compare_runs, run_measures, steady_offsets
from invctl.studies.tracking import TrackingStudy


def _run(name, t, y, y_ref, u, ratios=None, status="ok", stats=None):
    """A ClosedLoopResult from given signals (two outputs, named with units in the tests)."""
    n = t.size
    ratios = np.zeros((0, n)) if ratios is None else np.atleast_2d(ratios)
    err = np.linalg.norm(y - y_ref, axis=0)
    return ClosedLoopResult(
        t=t, q=np.vstack([y, y]), v=np.zeros((4, n)), z=np.zeros((0, n)), u=u, u_ff=np.zeros_like(u),
        u_fb=u, y=y, y_ref=y_ref, ratios=ratios, e_bar=np.zeros((1, n)), phi_bar=np.ones(n),
        drift_g=np.zeros(n), drift_Gv=np.zeros(n), cumulative_errors={"output": float(np.trapezoid(err, t))},
        wall_s=0.0, controller=name, status=status, ratio_names=[f"level {k}" for k in range(ratios.shape[0])],
        q_names=["x", "y", "a", "b"], y_names=["x", "a"], u_names=["u1", "u2"], stats=dict(stats or {}))


T = np.linspace(0.0, 2.0, 2001)
REF = np.vstack([np.minimum(T, 1.0), np.zeros_like(T)])          # the move ends at t = 1


def test_measures_against_closed_forms():
    """RMS of sin(2 pi t) over whole periods is 1/sqrt(2); a ratio rising linearly from 0 to 1 over 2 s is
    above 0.9 for 0.2 s; the largest gain is kappa_bar / (1 - r_max^2); peaks and final error as given."""
    u = np.vstack([np.sin(2 * np.pi * T), np.zeros_like(T)])
    ratio = 0.5 * T * 0.99                     # up to 0.99 at t = 2: above 0.9 for t > 0.9/0.495
    y = REF + np.vstack([0.01 * np.exp(-T), np.zeros_like(T)])
    M = run_measures(_run("C2", T, y, REF, u, np.vstack([0.5 * ratio, ratio])), kappa_bar=20.0, move_end=1.0)
    assert M["rms_input"] == pytest.approx(1 / np.sqrt(2), rel=1e-6)
    assert M["peak_input"] == pytest.approx(1.0, rel=1e-6)
    assert M["time_near_boundary"] == pytest.approx(2.0 - 0.9 / 0.495, abs=2e-3)
    assert M["max_gain"] == pytest.approx(20.0 / (1 - 0.99 ** 2), rel=1e-9)
    assert M["final_output_error"] == pytest.approx(0.01 * np.exp(-2.0), rel=1e-9)
    assert M["inside"] and M["steady_offsets"] == []         # a decaying error is no steady offset


def test_steady_offset_is_named_and_a_transient_is_not():
    """A constant 4.7 cm error after the move is a steady offset of that output; a run that left its region
    is not comparable, and the headline says both."""
    u = np.ones((2, T.size))
    off = REF + np.vstack([np.where(T > 1, -0.047, 0.0), np.zeros_like(T)])
    good = _run("C1", T, off, REF, 0.5 * u)
    assert steady_offsets(good, 1.0) == [("x", pytest.approx(-0.047))]
    bad = _run("C2", T, REF + 0.001, REF, u, stats={"left_region": {"t": 1.5}}, status="left_region")
    cmp = compare_runs({"C1": good, "C2": bad}, move_end=1.0, units={"x": "m", "a": "rad", "u1": "N", "u2": "N"})
    line = cmp.headline()
    assert "peak input +50 %" in line and "RMS input +50 %" in line
    assert "NOT comparable: C2 left region at t = 1.5 s" in line
    assert "steady offset after the move: C1: x -0.047 m" in line
    assert "peak |u| [N]" in cmp.table()


def _study(runs, units):
    return TrackingStudy(runs, {"units": units, "figure_captions": {}})


def test_figures_label_every_axis_and_plot_the_tables_ratios():
    """Every axis has an x label (or shares x with one that has) and a y label; the units of the scene appear; states in m and rad get separate
    axes; the funnel figure's curves are the runs' ratios (their maximum is the table's max phi|e|)."""
    u = np.vstack([np.sin(T), np.cos(T)])
    r1 = np.vstack([0.3 * np.sin(T) ** 2, 0.2 * T / 2, 0.05 * np.ones_like(T)])
    runs = {"C1": _run("C1", T, REF + 0.01, REF, u, r1), "C2": _run("C2", T, REF + 0.02, REF, 2 * u, 2 * r1),
            "C3": _run("C3", T, REF + 0.1, REF, u)}
    units = {"x": "m", "y": "m", "a": "rad", "b": "rad", "u1": "N", "u2": "N"}
    figs = _study(runs, units).plot()
    for key, fig in figs.items():
        for ax in fig.axes:
            if ax.get_visible() and ax.axison and ax.get_label() != "<colorbar>":
                xlabel = ax.get_xlabel() or any(o.get_xlabel() for o in ax.get_shared_x_axes().get_siblings(ax))
                assert xlabel and ax.get_ylabel(), (key, ax.get_title())
    assert len(figs["states"].axes) == 2                              # m and rad apart
    assert {ax.get_ylabel() for ax in figs["inputs"].axes} == {"u1 [N]", "u2 [N]"}
    assert any("[rad]" in ax.get_ylabel() for ax in figs["errors"].axes)
    fun = figs["funnel"].axes
    assert len(fun) == 3
    for name in ("C1", "C2"):
        plotted = [ln.get_ydata() for ax in fun for ln in ax.get_lines() if ln.get_gid() and
                   ln.get_gid().startswith(f"ratio:{name}:")]
        assert len(plotted) == 3
        assert max(np.max(p) for p in plotted) == runs[name].max_funnel_ratio
        for k, p in enumerate(plotted):
            np.testing.assert_array_equal(p, runs[name].ratios[k])
    import matplotlib.pyplot as plt

    plt.close("all")


def test_a_run_that_left_its_funnel_or_diverged_does_not_set_the_axes():
    """A run cut at a funnel violation keeps its curve up to the exit (marked); a feedforward-only run diverging
    to 20.8 (crane) is drawn clipped and marked, and the others keep their scale."""
    u = np.ones((2, T.size))
    grow = REF + np.vstack([np.where(T > 0.5, 20.8 * (T - 0.5) / 1.5, 0.0), np.zeros_like(T)])
    cut = T <= 1.2
    c2 = _run("C2", T[cut], REF[:, cut] + 0.03 * T[cut], REF[:, cut], u[:, cut], np.vstack([T[cut] / 1.2]),
              status="funnel_violation")
    runs = {"C1": _run("C1", T, REF + 0.01 * np.sin(T), REF, u, np.vstack([0.1 * np.ones_like(T)])), "C2": c2,
            "C3": _run("C3", T, grow, REF, u)}
    figs = _study(runs, {"x": "m", "a": "rad"}).plot()
    ax = figs["errors"].axes[0]
    assert 0.03 < ax.get_ylim()[1] < 0.1                 # C2 up to its exit sets the scale, C3's 20.8 does not
    assert sum(ln.get_marker() == "X" for ln in ax.get_lines()) == 2
    assert "left its funnel at t = 1.2 s" in " ".join(t.get_text() for t in ax.get_legend().get_texts())
    import matplotlib.pyplot as plt

    plt.close("all")


def test_contact_figure_zooms_to_where_things_happen():
    """Motion in the first 0.1 s of 3 s: the time axes zoom to it (and say so); motion throughout: no zoom."""
    from invctl.plot.contact import active_window, plot_contact_trajectory

    t = np.linspace(0.0, 3.0, 3001)
    v = np.where(t < 0.1, np.sin(np.pi * t / 0.1), 0.0)[None, :]
    tr = SimpleNamespace(t=t, v=v, q=np.cumsum(v, axis=1) * 1e-3, P=np.zeros((1, t.size - 1)), names={},
                         gaps=np.ones((1, t.size)), max_gap_violation=0.0, energy=v[0] ** 2, V=v[0] ** 2,
                         impact_times=[], max_V_increase=0.0)
    lo, hi = active_window(tr)
    assert lo == 0.0 and 0.1 <= hi <= 0.12
    fig = plot_contact_trajectory(tr)
    assert fig.axes[1].get_xlim() == pytest.approx((lo, hi)) and "zoomed" in fig.axes[1].get_xlabel()
    tr.v = np.sin(t)[None, :]
    assert active_window(tr) is None
    import matplotlib.pyplot as plt

    plt.close("all")


def test_single_run_figure_takes_the_units_recorded_in_the_run():
    """``invctl simulate --plot``: the run's meta carries the scene's units; mixed output units are said so."""
    from invctl.plot.tracking import plot_run

    u = np.vstack([np.sin(T), np.cos(T)])
    r = _run("C1", T, REF + 0.01, REF, u, np.vstack([0.2 * np.ones_like(T)]))
    r.meta = {"units": {"x": "m", "a": "rad", "u1": "N", "u2": "N"}}
    fig = plot_run(r)
    labels = [ax.get_ylabel() for ax in fig.axes]
    assert "u1, u2 [N]" in labels and "outputs (mixed units)" in labels and "phi|e| [-] (boundary 1)" in labels
    assert all(ax.get_xlabel() == "t [s]" for ax in fig.axes)
    import matplotlib.pyplot as plt

    plt.close("all")


def _fits(fig):
    """Independently of invctl.plot.crowded: every shown axes with its tick labels, axis labels and title (its tight
    box) lies inside the figure, and no two of them overlap."""
    r = fig.canvas.get_renderer()
    boxes = [ax.get_tightbbox(r) for ax in fig.axes if ax.get_visible() and ax.axison]
    frame = fig.bbox
    inside = all(b.x0 >= frame.x0 and b.y0 >= frame.y0 and b.x1 <= frame.x1 and b.y1 <= frame.y1 for b in boxes)
    apart = not any(a.overlaps(b) for i, a in enumerate(boxes) for b in boxes[i + 1:])
    return inside and apart


def test_study_figures_are_drawn_once_and_nothing_is_clipped(tmp_path):
    """Each comparison figure is written with one draw (matplotlib's savefig draws a laid-out figure twice) at the
    fixed margins (no fallback layout), and its axes with their labels and ticks lie inside it, apart."""
    import matplotlib.pyplot as plt
    from PIL import Image

    from invctl.plot import DPI, NBINS

    u = np.vstack([40 * np.sin(T), -60 * np.cos(T)])
    r1 = np.vstack([0.3 * np.sin(T) ** 2, 0.2 * T / 2])
    runs = {"C1": _run("C1", T, REF + 0.01, REF, u, r1), "C2": _run("C2", T, REF - 0.2 * T, REF, 2 * u, 2 * r1),
            "C3": _run("C3", T, REF + 0.1, REF, u)}
    units = {"x": "m", "y": "m", "a": "rad", "b": "rad", "u1": "N", "u2": "N"}
    draws = []
    real_subplots = plt.subplots

    def counting(*a, **k):
        fig, axs = real_subplots(*a, **k)
        fig.canvas.mpl_connect("draw_event", lambda ev: draws.append(ev.canvas.figure))
        return fig, axs

    plt.subplots = counting
    try:
        figs = _study(runs, units).plot(tmp_path)
    finally:
        plt.subplots = real_subplots
    assert set(figs) == {"states", "errors", "inputs", "funnel"}
    for key, fig in figs.items():
        assert draws.count(fig) == 1, key
        assert fig.get_layout_engine() is None, key
        assert _fits(fig), key
        for ax in fig.axes:  # at most NBINS tick intervals in view on a linear axis
            for axis, (lo, hi) in ((ax.xaxis, ax.get_xlim()), (ax.yaxis, ax.get_ylim())):
                ticks = [t for t in axis.get_majorticklocs() if min(lo, hi) <= t <= max(lo, hi)]
                assert axis.get_scale() != "linear" or len(ticks) <= NBINS + 1, (key, ticks)
        with Image.open(tmp_path / f"{key}.png") as im:
            assert im.size == (round(fig.get_figwidth() * DPI), round(fig.get_figheight() * DPI))
    plt.close("all")


def test_save_lays_out_a_figure_whose_labels_do_not_fit(tmp_path):
    """A label too long for the fixed margins is found after the draw (it leaves the figure) and the figure is laid
    out by constrained layout and drawn again: then everything fits. A figure that fits keeps its margins."""
    import matplotlib.pyplot as plt

    from invctl.plot import crowded, grid, save

    fig, axs = grid(1, 2, (6, 3))
    for ax in axs[0]:
        ax.plot(T, 1e3 * T)
        ax.set(xlabel="t [s]", ylabel="y [m]", title="fits")
    save(fig, tmp_path / "fits.png")
    assert fig.get_layout_engine() is None and crowded(fig) == [] and _fits(fig)
    axs[0, 1].set_ylabel("a label\nover three\nlines [m]", fontsize=20)  # runs into the left axes
    fig.canvas.draw()
    assert crowded(fig) == ["a label\nover three\nlines [m]"] and not _fits(fig)
    save(fig, tmp_path / "laid_out.png")
    assert fig.get_layout_engine() is not None and crowded(fig) == [] and _fits(fig)
    plt.close("all")
