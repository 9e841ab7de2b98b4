"""Figures for results and studies. Import from the submodules."""


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
