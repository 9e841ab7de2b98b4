"""Map of the C1-versus-C2 reductions of 003 Sect. 6 over the unknowns of its Table 2 (docs/reproduction.md).

Under the paper's rules (one funnel and one gain per level shared by both outputs, ``phi = phi_2``,
``kappa_bar = kappa_2``; ``Tracking(funnel_levels="shared")``) and with the identified parameters (the
defaults), Table 2's unknowns are the gains ``kappa_0, kappa_1, kappa_2`` and the funnels
``(p_j, q_j, r_j)``.  The map scales them around the automatic design (the stated rule, scale 1):

* ``kappa x``: the level gains kappa_0, kappa_1 (one factor),
* ``width x``: every funnel's p and r (initial and final widths, one factor),
* ``kappa_bar x``: kappa_2 (panels).

Per point it runs C1 and C2 on the plant m3 x 1.2 and records the reductions of C2's cumulative output and
end-effector errors and C2's largest funnel ratio.  Near the printed pair (40 %, 50 %) it then perturbs
each factor by +-1 % and reports the spread (fragility).  Writes a PNG and a Markdown table.

    python tools/reproduction_map.py --out docs/figures/manipulator_reduction_map.png --md map.md
    python tools/reproduction_map.py --smoke          # 2 x 2 points, one panel (a test runs this)
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import invctl_scenes.manipulator as scene  # noqa: E402
from invctl.control.funnel import Funnel  # noqa: E402
from invctl.control.funnel_nmp import NMPFunnelController  # noqa: E402
from invctl.errors import FunnelViolation, SimulationFailed  # noqa: E402
from invctl.studies.tracking import run_controller, setup_tracking  # noqa: E402

PRINTED = (0.40, 0.50)


def scaled_options(design, kappa: float, width: float, kappa_bar: float) -> dict:
    """The design's controller options with the level gains, all funnel widths and kappa_bar scaled."""
    opts = design.controller_options()

    def fun(f):
        p, q, r = (f.params[k] for k in "pqr")
        return Funnel.exponential(p * width, q, r * width, f.name)

    opts["funnels"] = [[fun(f) for f in row] for row in opts["funnels"]]
    opts["phi_bar"] = fun(opts["phi_bar"])
    opts["kappa"] = [[k * kappa for k in row] for row in opts["kappa"]]
    opts["kappa_bar"] = opts["kappa_bar"] * kappa_bar
    return opts


def point(setup, kappa, width, kappa_bar) -> dict:
    """C1 and C2 at one point: reductions (output, end effector) and C2's largest ratio (None: C2 left)."""
    ctrl = NMPFunnelController(setup.model, setup.lin, setup.reference, t_end=setup.t_end,
                               **scaled_options(setup.design, kappa, width, kappa_bar))
    s = dataclasses.replace(setup, controller=ctrl, _loops={}, _c1=None)
    runs = {}
    for name in ("C1", "C2"):
        try:
            runs[name] = run_controller(s, name)
        except (FunnelViolation, SimulationFailed):
            return {"kappa": kappa, "width": width, "kappa_bar": kappa_bar, "output": None, "end effector": None,
                    "c2_ratio": None, "left": name}
    red = {k: 1 - runs["C1"].cumulative_errors[k] / runs["C2"].cumulative_errors[k]
           for k in ("output", "end effector")}
    inside = all(r.departure is None for r in runs.values())
    return {"kappa": kappa, "width": width, "kappa_bar": kappa_bar, **red,
            "c2_ratio": runs["C2"].max_funnel_ratio, "left": None if inside else "region"}


def scan(setup, kappas, widths, kbars, progress=True) -> list:
    out = []
    for kb in kbars:
        for k in kappas:
            for w in widths:
                out.append(point(setup, k, w, kb))
                if progress:
                    r = out[-1]
                    print(f"kappa x{k:.3g} width x{w:.3g} kappa_bar x{kb:.3g}: "
                          + ("C2 or C1 left" if r["output"] is None else
                             f"{100 * r['output']:.1f} % / {100 * r['end effector']:.1f} %, C2 ratio "
                             f"{r['c2_ratio']:.3f}"), file=sys.stderr, flush=True)
    return out


def distance(r) -> float:
    """Largest distance (percentage points) of a point's pair from the printed pair."""
    if r["output"] is None:
        return np.inf
    return 100 * max(abs(r["output"] - PRINTED[0]), abs(r["end effector"] - PRINTED[1]))


def fragility(setup, r, step=0.01) -> dict:
    """Reductions with each factor changed by +-step around ``r``: the spread of both figures."""
    pts = []
    for key in ("kappa", "width", "kappa_bar"):
        for sgn in (-1, 1):
            f = {k: r[k] for k in ("kappa", "width", "kappa_bar")}
            f[key] *= 1 + sgn * step
            pts.append(point(setup, f["kappa"], f["width"], f["kappa_bar"]))
    ok = [p for p in pts if p["output"] is not None]
    spread = {k: (min(p[k] for p in ok), max(p[k] for p in ok)) if ok else None for k in ("output", "end effector")}
    return {"points": pts, "spread": spread, "left": sum(p["output"] is None for p in pts)}


def plot(results, kappas, widths, kbars, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = len(kbars)
    fig, axs = plt.subplots(3, cols, figsize=(4.2 * cols + 1.5, 10), constrained_layout=True, squeeze=False)
    what = (("output", "C1 vs C2, output: reduction [%]", "RdBu", (-60, 60)),
            ("end effector", "C1 vs C2, end effector: reduction [%]", "RdBu", (-60, 60)),
            ("c2_ratio", "C2: largest funnel ratio phi|e| [-]", "viridis", (0, 1)))
    for c, kb in enumerate(kbars):
        sel = [r for r in results if r["kappa_bar"] == kb]
        for row, (key, title, cmap, lim) in enumerate(what):
            Z = np.full((len(kappas), len(widths)), np.nan)
            for r in sel:
                if r[key] is not None:
                    Z[kappas.index(r["kappa"]), widths.index(r["width"])] = (100 if key != "c2_ratio" else 1) * r[key]
            ax = axs[row, c]
            im = ax.pcolormesh(np.arange(len(widths) + 1), np.arange(len(kappas) + 1), Z, cmap=cmap,
                               vmin=lim[0], vmax=lim[1])
            for i in range(len(kappas)):
                for j in range(len(widths)):
                    ax.text(j + 0.5, i + 0.5, "left" if np.isnan(Z[i, j]) else f"{Z[i, j]:.0f}" if key != "c2_ratio"
                            else f"{Z[i, j]:.2f}", ha="center", va="center", fontsize=7)
            near = [r for r in sel if distance(r) <= 10]
            for r in near:
                ax.add_patch(plt.Rectangle((widths.index(r["width"]), kappas.index(r["kappa"])), 1, 1, fill=False,
                                           ec="k", lw=2))
            if kb == 1.0 and 1.0 in kappas and 1.0 in widths:
                ax.plot(widths.index(1.0) + 0.5, kappas.index(1.0) + 0.5, marker="o", ms=16, mfc="none", mec="m",
                        mew=2)
            ax.set_xticks(np.arange(len(widths)) + 0.5, [f"{w:g}" for w in widths])
            ax.set_yticks(np.arange(len(kappas)) + 0.5, [f"{k:g}" for k in kappas])
            ax.set(xlabel="funnel widths x (p and r) [-]", ylabel="level gains kappa_0, kappa_1 x [-]",
                   title=f"{title}\nkappa_bar x {kb:g}")
            fig.colorbar(im, ax=ax, shrink=0.8)
    fig.suptitle("003 Sect. 6 under the paper's rules (shared funnels and gains), identified parameters, plant "
                 "m3 x 1.2\nboxed: within 10 points of the printed 40 % / 50 %; magenta circle: the automatic design")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def markdown(results, frag) -> str:
    lines = ["| kappa x | width x | kappa_bar x | C1 vs C2: y [%] | r_app [%] | C2 max phi|e| | distance to 40/50 [points] |",
             "|---|---|---|---|---|---|---|"]
    for r in results:
        if r["output"] is None:
            lines.append(f"| {r['kappa']:g} | {r['width']:g} | {r['kappa_bar']:g} | – | – | {r['left']} left | – |")
        else:
            lines.append(f"| {r['kappa']:g} | {r['width']:g} | {r['kappa_bar']:g} | {100 * r['output']:.1f} | "
                         f"{100 * r['end effector']:.1f} | {r['c2_ratio']:.3f} | {distance(r):.1f} |")
    for r, fr in frag:
        sp = fr["spread"]
        lines.append("")
        lines.append(f"Fragility at kappa x {r['kappa']:g}, width x {r['width']:g}, kappa_bar x {r['kappa_bar']:g} "
                     f"({100 * r['output']:.1f} % / {100 * r['end effector']:.1f} %, C2 ratio {r['c2_ratio']:.3f}): "
                     "each factor +-1 % gives "
                     + (f"output {100 * sp['output'][0]:.1f} … {100 * sp['output'][1]:.1f} %, end effector "
                        f"{100 * sp['end effector'][0]:.1f} … {100 * sp['end effector'][1]:.1f} %"
                        if sp["output"] else "no run inside")
                     + (f"; {fr['left']} of 6 perturbed points leave" if fr["left"] else ""))
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="reduction_map.png", help="figure (PNG)")
    ap.add_argument("--md", default=None, help="write the Markdown table here")
    ap.add_argument("--kappa", default="0.5,0.71,1,1.41,2", help="level-gain factors, comma separated")
    ap.add_argument("--width", default="0.5,0.71,1,1.41,2", help="funnel-width factors")
    ap.add_argument("--kappa-bar", default="0.5,1,2", help="kappa_bar factors (panels)")
    ap.add_argument("--fragile", type=int, default=2, help="perturb the N points nearest the printed pair")
    ap.add_argument("--smoke", action="store_true", help="2 x 2 points, one panel, no fragility")
    a = ap.parse_args(argv)
    parse = lambda s: [float(x) for x in s.split(",")]  # noqa: E731
    kappas, widths, kbars = parse(a.kappa), parse(a.width), parse(a.kappa_bar)
    if a.smoke:
        kappas, widths, kbars, a.fragile = [1.0, 2.0], [1.0, 2.0], [1.0], 0
    setup = setup_tracking(scene.SCENE, {}, invert=True)
    if setup.design.levels != "shared":
        raise SystemExit("the manipulator scene must declare funnel_levels='shared' (003 Sect. 6)")
    results = scan(setup, kappas, widths, kbars, progress=not a.smoke)
    near = sorted((r for r in results if r["output"] is not None), key=distance)[:a.fragile]
    frag = [(r, fragility(setup, r)) for r in near]
    plot(results, kappas, widths, kbars, a.out)
    text = markdown(results, frag)
    if a.md:
        Path(a.md).write_text(text + "\n")
    print(text)
    return results


if __name__ == "__main__":
    main()
