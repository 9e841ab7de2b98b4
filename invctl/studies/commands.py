"""``invctl study <kind> <scene>``: studies any scene offering them."""
from __future__ import annotations

import os
from pathlib import Path

from ..errors import SceneError
from ..scenes import CommandResult, scene_name
from .tradeoff import run_tradeoff

KINDS = ("tradeoff",)


def study_command(scene_module, kind: str, params: dict, *, out_dir: str = "invctl-out", **options) -> CommandResult:
    """Run a study of a scene and write its table (CSV, JSON) and figure (PNG)."""
    name = scene_name(scene_module)
    if kind not in KINDS:
        raise SceneError(f"unknown study {kind!r}; available: {', '.join(KINDS)}")
    spec_fn = getattr(scene_module, "tradeoff_spec", None)
    if spec_fn is None:
        raise SceneError(f"scene {name!r} offers no speed-versus-accuracy study (no tradeoff_spec)")
    smoke = os.environ.get("INVCTL_SMOKE") == "1"
    spec = spec_fn(params, smoke=smoke)
    spec.scene = spec.scene or name
    result = run_tradeoff(spec)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    result.to_csv(out / f"tradeoff_{name}.csv")
    result.to_json(out / f"tradeoff_{name}.json")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ax = result.plot()
    ax.figure.tight_layout()
    ax.figure.savefig(out / f"tradeoff_{name}.png", dpi=120)
    plt.close(ax.figure)
    text = result.table() + f"\nwritten: {out / f'tradeoff_{name}.csv'}, .json, .png"
    data = result.to_dict()
    return CommandResult(text, data)
