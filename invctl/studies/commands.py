"""``invctl study <kind> <scene>``: studies any scene offering them."""
from __future__ import annotations

import os
from pathlib import Path

from ..errors import SceneError
from ..scenes import CommandResult, scene_name
from .tradeoff import run_tradeoff

KINDS = ("tradeoff",)


def study_command(scene_module, kind: str, params: dict, *, out_dir: str = "invctl-out", job: str | None = None,
                  quiet: bool = False, **options) -> CommandResult:
    """Run a study of a scene and write its table (CSV, JSON) and figure (PNG).

    The spec comes from the scene's own ``tradeoff_spec`` or from
    :data:`invctl.studies.tradeoff_specs.REGISTRY`; ``job`` picks one of several
    (e.g. ``invert`` or ``simulate`` for the manipulator).  ``INVCTL_SMOKE=1``
    selects the coarse settings.
    """
    from .tradeoff_specs import spec_for

    name = scene_name(scene_module)
    if kind not in KINDS:
        raise SceneError(f"unknown study {kind!r}; available: {', '.join(KINDS)}")
    if options:
        raise SceneError(f"study {kind} does not take option(s) {sorted(options)}")
    smoke = os.environ.get("INVCTL_SMOKE") == "1"
    spec = spec_for(scene_module, name, params, smoke=smoke, job=job)
    spec.scene = spec.scene or name
    result = run_tradeoff(spec, progress=not quiet)
    stem = f"tradeoff_{spec.scene}"
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    result.to_csv(out / f"{stem}.csv")
    result.to_json(out / f"{stem}.json")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ax = result.plot()
    ax.figure.tight_layout()
    ax.figure.savefig(out / f"{stem}.png", dpi=120)
    plt.close(ax.figure)
    text = result.table() + f"\nwritten: {out / f'{stem}.csv'}, .json, .png"
    data = result.to_dict()
    data["files"] = {ext: str(out / f"{stem}.{ext}") for ext in ("csv", "json", "png")}
    return CommandResult(text, data)
