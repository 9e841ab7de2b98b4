"""Grid axes, the result of :func:`invctl.studies.library.generate` and where it is written.

:class:`Axis`, :func:`parse_grid`, :func:`resolve_axes`: what a grid axis of a scene may be (a scene
parameter or a numeric keyword argument of the scene's reference, :func:`reference_arguments`).

:class:`Library` stacks the collocation data of every grid point (one transcription: the same
number of intervals everywhere), so any point is an :class:`~invctl.inversion.Inverse` again
(:meth:`Library.inverse`), and keeps, for every point, its status (``solved``, ``inaccurate``,
``failed``), the reason of a failure and the solver statistics.

:class:`LibraryStore` writes points as they are solved: ``lib.npz`` keeps them in ``lib.npz.parts/``
until the whole library is assembled; a folder holds one ``Inverse`` file per point
(``point_00012.npz``, loadable with ``Inverse.load`` and drawable with ``invctl animate``) and
``library.json``.  Files carry the key of the settings that produced them, so a resumed run reads
back exactly the points of the same library.
"""
from __future__ import annotations

import inspect
import json
import math
import os
import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import LibraryError, OutputPathError, ParameterError, ResultFileError
from ..io import load_npz, read_json, read_meta, save_npz
from ..plot import finish
from ..scenes import jsonable

if TYPE_CHECKING:
    from ..inversion import Inverse

_AXIS = re.compile(r"^(?:(param|ref):)?([A-Za-z_]\w*)(?:\[(\d+)\])?$")


@dataclass(frozen=True)
class Axis:
    """One grid axis: ``name`` as written (``m3``, ``rf[0]``), ``kind`` ``"param"`` or ``"reference"``,
    the parameter or argument ``key``, the component ``index`` of a sequence argument, the ``values``."""

    name: str
    kind: str
    key: str
    index: int | None
    values: tuple


def parse_grid(item: str) -> tuple[str, np.ndarray]:
    """``NAME=START:STOP:COUNT`` (inclusive, evenly spaced), ``NAME=V1,V2,...`` or ``NAME=V`` -> (name, values).
    Numbers are parsed with ``float`` (never evaluated)."""
    name, sep, spec = str(item).partition("=")
    name, spec = name.strip(), spec.strip()
    if not sep or not name or not spec:
        raise ParameterError(f"--grid {item!r}: expected NAME=START:STOP:COUNT or NAME=V1,V2,... (e.g. m3=0.4:0.6:3)")

    def num(text):
        try:
            v = float(text)
        except ValueError:
            raise ParameterError(f"--grid {item!r}: {text.strip()!r} is not a number") from None
        if not math.isfinite(v):
            raise ParameterError(f"--grid {item!r}: values must be finite, got {text.strip()!r}")
        return v

    if ":" in spec:
        parts = spec.split(":")
        if len(parts) != 3:
            raise ParameterError(f"--grid {item!r}: a range is START:STOP:COUNT (three fields), got {spec!r}")
        a, b = num(parts[0]), num(parts[1])
        try:
            count = int(parts[2])
        except ValueError:
            raise ParameterError(f"--grid {item!r}: COUNT {parts[2]!r} is not an integer") from None
        if count < 1 or (count == 1 and a != b) or (count > 1 and a == b):
            raise ParameterError(f"--grid {item!r}: COUNT must be >= 2 for START != STOP (1 only when equal), "
                                 f"got {count}")
        values = np.linspace(a, b, count)
    else:
        values = np.array([num(v) for v in spec.split(",")])
    if np.unique(values).size != values.size:
        raise ParameterError(f"--grid {item!r}: repeated values {values.tolist()}")
    return name, values


def grid_counts(grid) -> list[int]:
    """The number of values of every grid axis, read without building them (``COUNT`` of a range, the
    items of a list), so that a size check can come first; malformed items count 1 (:func:`parse_grid`
    then says what is wrong)."""
    if isinstance(grid, dict):
        return [int(np.size(v)) for v in grid.values()]
    out = []
    for item in grid:
        spec = str(item).partition("=")[2]
        parts = spec.split(":")
        try:
            out.append(max(1, int(parts[2])) if len(parts) == 3 else spec.count(",") + 1)
        except ValueError:
            out.append(1)
    return out


def reference_arguments(scene) -> dict[str, Any]:
    """The grid-able arguments of the scene's reference function: keyword arguments (after
    ``model``) whose default is a number or a sequence of numbers, with their defaults."""
    ref = scene.tracking.reference if scene.tracking is not None else None
    if ref is None:
        return {}
    out: dict[str, Any] = {}
    for i, p in enumerate(inspect.signature(ref).parameters.values()):
        if i == 0 or p.kind not in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY) or p.default is p.empty:
            continue
        d = p.default
        if isinstance(d, (int, float)) and not isinstance(d, bool):
            out[p.name] = float(d)
        elif (isinstance(d, (tuple, list)) and d
              and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in d)):
            out[p.name] = tuple(float(v) for v in d)
    return out


def resolve_axes(scene, grid) -> list[Axis]:
    """Check grid axes against the scene (``grid``: dict name -> values, or ``NAME=...`` strings).

    Raises
    ------
    ParameterError
        Unknown or ambiguous names, a component index out of range, repeated axes.
    """
    items = [parse_grid(g) for g in grid] if not isinstance(grid, dict) else list(grid.items())
    if not items:
        raise ParameterError("a library needs at least one grid axis, e.g. --grid m3=0.4:0.6:3")
    refargs = reference_arguments(scene)
    params = set(scene.params)
    able = sorted(params) + [f"{k}[i]" if isinstance(v, tuple) else k for k, v in refargs.items()]
    axes, seen = [], set()
    for name, values in items:
        mt = _AXIS.match(str(name).strip())
        if not mt:
            raise ParameterError(f"grid axis {name!r}: expected NAME, NAME[INDEX], param:NAME or ref:NAME")
        prefix, key, idx = mt.group(1), mt.group(2), mt.group(3)
        in_p, in_r = key in params, key in refargs
        if prefix is None and in_p and in_r:
            raise ParameterError(f"grid axis {name!r} is both a scene parameter and an argument of the reference; "
                                 f"write param:{key} or ref:{key}")
        kind = "param" if (prefix == "param" or (prefix is None and in_p)) else "reference"
        if (kind == "param" and not in_p) or (kind == "reference" and not in_r):
            raise ParameterError(f"grid axis {name!r}: not a parameter of scene {scene.name!r} nor a numeric "
                                 f"keyword argument of its reference; grid-able: {', '.join(able) or 'none'} "
                                 "(docs/trajectories.md: how a scene declares reference arguments)")
        index = None
        if kind == "reference" and isinstance(refargs[key], tuple):
            if idx is None:
                raise ParameterError(f"grid axis {name!r}: reference argument {key} is a sequence "
                                     f"{refargs[key]}; grid one component, e.g. {key}[0]")
            index = int(idx)
            if index >= len(refargs[key]):
                raise ParameterError(f"grid axis {name!r}: {key} has {len(refargs[key])} components")
        elif idx is not None:
            raise ParameterError(f"grid axis {name!r}: {key} is a number, not a sequence (no [index])")
        label = key if index is None else f"{key}[{index}]"
        if (kind, label) in seen:
            raise ParameterError(f"grid axis {label!r} given twice")
        seen.add((kind, label))
        vals = np.atleast_1d(np.asarray(values, float))
        if vals.size == 0 or not np.all(np.isfinite(vals)):
            raise ParameterError(f"grid axis {label!r}: values must be finite numbers, got {vals.tolist()}")
        axes.append(Axis(label, kind, key, index, tuple(float(v) for v in vals)))
    return axes


_STATS = ("iterations", "factorizations", "wall_s", "cpu_s", "residual", "error", "source")


@dataclass
class Library:
    """Stable inverses over a grid (see the module doc).

    Attributes
    ----------
    axes : list of Axis
    shape : tuple, the grid shape (first axis slowest)
    values : (P, d) array, the axis values of every point (flat order)
    status, messages : lists of str per point
    t_mesh, X_mesh, dX_mesh, X_col : stacked collocation data, NaN for failed points
    t0, tf : (P,) transition of every point's reference
    stats : dict name -> (P,) array: ``iterations``, ``factorizations``, ``wall_s``, ``cpu_s`` (CPU time of
        the process that solved the point), ``residual``,
        ``error`` (forward check; NaN where not verified), ``source`` (the point whose solution
        started this one: -1 the base, -2 none) and ``initial_guess`` (list of str)
    info : dict, settings and timings
    """

    axes: list
    shape: tuple
    values: np.ndarray
    status: list
    messages: list
    t_mesh: np.ndarray
    X_mesh: np.ndarray
    dX_mesh: np.ndarray
    X_col: np.ndarray
    t0: np.ndarray
    tf: np.ndarray
    stats: dict
    info: dict = field(default_factory=dict)

    # ------------------------------------------------------------ construction
    @classmethod
    def assemble(cls, axes, shape, points, records: dict, info: dict) -> "Library":
        P = len(points)
        ok = [r for r in records.values() if r["status"] != "failed"]
        if ok:
            nx, n1, nc = ok[0]["X_mesh"].shape[0], ok[0]["X_mesh"].shape[1], ok[0]["X_col"].shape[1]
        else:
            s = info.get("sizes", {})
            nx, n1, nc = sum(s.get(k, 0) for k in ("n", "n", "l", "p", "m")), info["base"]["N"] + 1, 0
        lib = cls(list(axes), tuple(shape), np.asarray(points, float), ["failed"] * P, ["not solved"] * P,
                  np.full((P, n1), np.nan), np.full((P, nx, n1), np.nan), np.full((P, nx, n1), np.nan),
                  np.full((P, nx, nc), np.nan), np.full(P, np.nan), np.full(P, np.nan),
                  {k: np.full(P, np.nan) for k in _STATS} | {"initial_guess": [""] * P}, dict(info))
        for i, r in records.items():
            lib.status[i], lib.messages[i] = r["status"], r.get("message", "")
            for k in _STATS:
                v = r.get(k)
                lib.stats[k][i] = np.nan if v is None else float(v)
            lib.stats["initial_guess"][i] = r.get("initial_guess", "")
            if r["status"] != "failed":
                lib.t_mesh[i], lib.X_mesh[i], lib.dX_mesh[i], lib.X_col[i] = (r["t_mesh"], r["X_mesh"], r["dX_mesh"],
                                                                              r["X_col"])
                lib.t0[i], lib.tf[i] = r["t0"], r["tf"]
        return lib

    # ------------------------------------------------------------ access
    @property
    def points(self) -> list[dict]:
        """The axis values of every point, as dicts (flat order)."""
        return [{a.name: float(v) for a, v in zip(self.axes, row)} for row in self.values]

    @property
    def solved(self) -> np.ndarray:
        """True where the point has a trajectory (``solved`` or ``inaccurate``)."""
        return np.array([s != "failed" for s in self.status])

    @property
    def failures(self) -> list[dict]:
        """The points without an accepted trajectory: index, values, status and why."""
        return [{"index": i, "values": self.points[i], "status": s, "message": self.messages[i]}
                for i, s in enumerate(self.status) if s != "solved"]

    def index(self, values: dict) -> int:
        """Flat index of the grid point nearest to ``values`` (axis name -> value; missing axes: any)."""
        unknown = sorted(set(values) - {a.name for a in self.axes})
        if unknown:
            raise LibraryError(f"unknown axes {unknown}; the library's axes are {[a.name for a in self.axes]}")
        d = np.zeros(len(self.values))
        for j, a in enumerate(self.axes):
            if a.name in values:
                span = (max(a.values) - min(a.values)) or 1.0
                d += ((self.values[:, j] - float(values[a.name])) / span) ** 2
        return int(np.argmin(d))

    def inverse(self, i) -> Inverse:
        """Point ``i`` (flat index or dict of axis values) as an :class:`~invctl.inversion.Inverse`."""
        from ..inversion import Inverse

        i = self.index(i) if isinstance(i, dict) else int(i)
        if not 0 <= i < len(self.status):
            raise LibraryError(f"point {i} is not in the library (0..{len(self.status) - 1})")
        if self.status[i] == "failed":
            raise LibraryError(f"point {i} ({self.points[i]}) has no trajectory: {self.messages[i]}")
        info = self.info
        inv = Inverse(info["base"]["scheme"], self.t_mesh[i], self.X_mesh[i], self.dX_mesh[i], self.X_col[i],
                      info["sizes"], float(self.t0[i]), float(self.tf[i]), info.get("names", {}),
                      {"status": self.status[i], **{k: self.stats[k][i] for k in _STATS}})
        inv.meta = {"scene": info.get("scene_ref", info.get("scene")), "params": dict(info.get("params", {})),
                    "library_point": self.points[i]}
        return inv

    def u(self, t) -> np.ndarray:
        """The feedforward of every point at times ``t``: ``(P, m, len(t))``, NaN for failed points."""
        t = np.atleast_1d(np.asarray(t, float))
        m = self.info["sizes"]["m"]
        out = np.full((len(self.status), m, t.size), np.nan)
        for i in np.flatnonzero(self.solved):
            out[i] = self.inverse(int(i)).u(t)
        return out

    def peak_inputs(self, samples: int = 1001) -> np.ndarray:
        """``max_t |u_ff,j(t)|`` over each point's horizon: ``(P, m)``, NaN for failed points."""
        m = self.info["sizes"]["m"]
        out = np.full((len(self.status), m), np.nan)
        for i in np.flatnonzero(self.solved):
            inv = self.inverse(int(i))
            out[i] = np.max(np.abs(inv.u(np.linspace(inv.T0, inv.Tf, samples))), axis=1)
        return out

    def array(self, key: str) -> np.ndarray:
        """A per-point statistic (``stats`` key) in the grid's shape."""
        if key not in self.stats or key == "initial_guess":
            raise LibraryError(f"no statistic {key!r}; available: {sorted(set(self.stats) - {'initial_guess'})}")
        return np.asarray(self.stats[key], float).reshape(self.shape)

    # ------------------------------------------------------------ reports
    def counts(self) -> dict:
        return {s: int(sum(x == s for x in self.status)) for s in ("solved", "inaccurate", "failed")}

    def table(self, max_failures: int = 20) -> str:
        """A readable summary: grid, counts, rates, accuracy, and every failure with its reason."""
        info, c = self.info, self.counts()
        axes = ", ".join(f"{a.name} ({a.kind}) {min(a.values):.6g}..{max(a.values):.6g} x {len(a.values)}"
                         for a in self.axes)
        lines = [f"trajectory library of {info.get('scene')}: {len(self.status)} points over {axes}",
                 f"  base: {info['base']['scheme']} N = {info['base']['N']}, horizon [T0, Tf] = "
                 f"[{info['base']['T0']:.4g}, {info['base']['Tf']:.4g}] around [{info['base']['t0']:.4g}, "
                 f"{info['base']['tf']:.4g}]; backend {info.get('backend')}, "
                 f"{'continuation' if info.get('continuation') else 'cold starts'}",
                 f"  solved {c['solved']}, inaccurate {c['inaccurate']}, failed {c['failed']}"
                 + (f"  ({info['resumed']} read back from an earlier run)" if info.get("resumed") else "")]
        rate = info.get("points_per_s")
        if rate:
            lines.append(f"  {info.get('solved_now', 0)} solved now in {info['solve_wall_s']:.2f} s "
                         f"({rate:.1f} points/s; base solve {info['base_s']:.2f} s"
                         + (f"; compiled Newton, C compile {info['compile_s']:.2f} s" if info.get("compiled") == "yes"
                            else f"; Newton {info['compiled']}" if str(info.get("compiled", "")).startswith("not")
                            else "") + ")")
        ok = self.solved
        if ok.any():
            it = self.stats["iterations"][ok]
            lines.append(f"  solver iterations per point: median {np.nanmedian(it):.0f}, max {np.nanmax(it):.0f}; "
                         f"largest position residual {np.nanmax(self.stats['residual'][ok]):.2g}")
        err = self.stats["error"]
        if np.isfinite(err).any():
            k = int(np.nanargmax(err))
            lines.append(f"  forward-check error (verify={info.get('verify')}, {int(np.isfinite(err).sum())} points): "
                         f"max {err[k]:.3g} at {self.points[k]}"
                         + (f", tol {info['tol']:.2g}" if info.get("tol") else ""))
        fails = self.failures
        if fails:
            lines.append(f"  points without an accepted trajectory ({len(fails)}):")
            for f in fails[:max_failures]:
                vals = ", ".join(f"{k}={v:.6g}" for k, v in f["values"].items())
                lines.append(f"    #{f['index']} ({vals}): {f['status']}: {f['message']}")
            if len(fails) > max_failures:
                lines.append(f"    ... and {len(fails) - max_failures} more (Library.failures)")
        if info.get("out"):
            lines.append(f"  written: {info['out']}")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """JSON-able summary (``invctl generate --json``)."""
        err = self.stats["error"]
        return jsonable({
            "scene": self.info.get("scene"), "shape": list(self.shape), "points": len(self.status),
            "axes": [{"name": a.name, "kind": a.kind, "values": list(a.values)} for a in self.axes],
            "counts": self.counts(), "failures": self.failures,
            "max_forward_error": float(np.nanmax(err)) if np.isfinite(err).any() else None,
            "info": {k: v for k, v in self.info.items() if k not in ("names",)}})

    def plot(self, path=None, *, samples: int = 400):
        """The feedforward of every solved point (one panel per input, coloured by the first axis) and
        the peak of the first input over the grid (line or heat map)."""
        import matplotlib.pyplot as plt

        m = self.info["sizes"]["m"]
        fig, axes = plt.subplots(1, m + 1, figsize=(4.6 * (m + 1), 3.8))
        first = np.array([v[0] for v in self.values])
        lo, hi = first.min(), first.max()
        cmap = plt.get_cmap("viridis")
        for i in np.flatnonzero(self.solved):
            inv = self.inverse(int(i))
            t = np.linspace(inv.T0, inv.Tf, samples)
            u = inv.u(t)
            c = cmap(0.5 if hi == lo else (first[i] - lo) / (hi - lo))
            for j in range(m):
                axes[j].plot(t, u[j], color=c, lw=0.8)
        for j in range(m):
            axes[j].set_xlabel("t [s]")
            axes[j].set_ylabel(self.info.get("names", {}).get("u", [f"u{k + 1}" for k in range(m)])[j] + " (u_ff)")
            axes[j].grid(alpha=0.3)
        axes[0].set_title(f"colour: {self.axes[0].name} {lo:.3g} .. {hi:.3g}")
        peak = self.peak_inputs()[:, 0].reshape(self.shape)
        ax = axes[m]
        if len(self.shape) == 2:
            im = ax.pcolormesh(np.array(self.axes[1].values), np.array(self.axes[0].values), peak, shading="nearest")
            fig.colorbar(im, ax=ax, label="max |u1|")
            ax.set_xlabel(self.axes[1].name)
            ax.set_ylabel(self.axes[0].name)
        else:
            ax.plot(np.array(self.axes[0].values), peak.reshape(len(self.axes[0].values), -1), "o-")
            ax.set_xlabel(self.axes[0].name)
            ax.set_ylabel("max |u1|")
        bad = ~self.solved
        if bad.any() and len(self.shape) <= 2:
            v = self.values[bad]
            ax.plot(v[:, 1] if len(self.shape) == 2 else v[:, 0], v[:, 0] if len(self.shape) == 2 else
                    np.zeros(v.shape[0]), "rx", ms=9, mew=2, label="failed")
            ax.legend(fontsize=8)
        ax.set_title(f"{self.counts()['solved']} of {len(self.status)} solved")
        return finish(fig, path)

    # ------------------------------------------------------------ files
    def save(self, path) -> Path:
        """Write one ``.npz`` file (kind ``TrajectoryLibrary``); returns the path."""
        arrays = {"values": self.values, "status": np.array(self.status), "messages": np.array(self.messages),
                  "t_mesh": self.t_mesh, "X_mesh": self.X_mesh, "dX_mesh": self.dX_mesh, "X_col": self.X_col,
                  "t0": self.t0, "tf": self.tf, "initial_guess": np.array(self.stats["initial_guess"])}
        arrays.update({f"stat_{k}": self.stats[k] for k in _STATS})
        info = {**self.info, "shape": list(self.shape),
                "axes": [[a.name, a.kind, a.key, a.index, list(a.values)] for a in self.axes]}
        return save_npz(path, "TrajectoryLibrary", arrays, info)

    @classmethod
    def load(cls, path) -> "Library":
        """Read a library written by :meth:`save` (a ``.npz`` file) or by ``generate(out=folder)``.

        Raises
        ------
        ResultFileError
            Missing, truncated or foreign files; arrays whose sizes do not match the grid.
        LibraryError
            A point file of a folder that another library's run wrote (its settings key is not the one in
            ``library.json``).
        """
        p = Path(path)
        if p.is_dir():
            store = LibraryStore(p, None)
            meta = store.index()
            records = store.existing(expect=meta.get("key"))
            axes = [Axis(*a) for a in meta["axes"]]
            shape = tuple(meta["shape"])
            pts = np.array(meta["values"], float)
            recs = dict(records)
            for f in meta.get("failures", []):
                recs.setdefault(f["index"], {"status": "failed", "message": f["message"]})
            return cls.assemble(axes, shape, pts, recs, meta["info"])
        z, info = load_npz(p, "TrajectoryLibrary")
        try:
            axes = [Axis(a[0], a[1], a[2], a[3], tuple(a[4])) for a in info["axes"]]
            shape = tuple(info["shape"])
            P = int(np.prod(shape))
            if z["values"].shape != (P, len(axes)) or z["X_mesh"].shape[0] != P or len(z["status"]) != P:
                raise ValueError(f"grid {shape} does not match the stored arrays {z['X_mesh'].shape}")
            stats = {k: z[f"stat_{k}"] for k in _STATS} | {"initial_guess": [str(s) for s in z["initial_guess"]]}
            return cls(axes, shape, z["values"], [str(s) for s in z["status"]], [str(s) for s in z["messages"]],
                       z["t_mesh"], z["X_mesh"], z["dX_mesh"], z["X_col"], z["t0"], z["tf"], stats, info)
        except (KeyError, IndexError, ValueError, TypeError) as exc:
            raise ResultFileError(f"{p}: not a complete trajectory library ({type(exc).__name__}: {exc})") from None


# ---------------------------------------------------------------------- storage
class LibraryStore:
    """Where a library is written while it is generated (module doc); ``key`` identifies the settings."""

    def __init__(self, out, key: str | None, *, force: bool = False):
        self.path, self.key, self.force = Path(out), key, force
        self.layout: dict = {}  # scheme, sizes, names of the points' Inverse files (set by generate)
        self.file = self.path.suffix.lower() == ".npz"
        self.parts = Path(str(self.path) + ".parts") if self.file else self.path
        parent = self.path.parent if str(self.path.parent) else Path(".")
        if not parent.is_dir():
            raise OutputPathError(f"--out {out}: directory {str(parent)!r} does not exist; create it first")
        if not os.access(parent, os.W_OK):
            raise OutputPathError(f"--out {out}: directory {str(parent)!r} is not writable")
        if self.file and self.path.is_dir():
            raise OutputPathError(f"--out {out}: is a directory; a single-file library needs a .npz file name")
        if not self.file and self.path.exists() and not self.path.is_dir():
            raise OutputPathError(f"--out {out}: is a file; give a folder or a .npz file name")

    @property
    def lock_path(self) -> Path:
        """The lock of this output: ``<folder>/.lock``, or ``.<name>.lock`` next to a ``.npz`` file."""
        return self.path.with_name(f".{self.path.name}.lock") if self.file else self.path / ".lock"

    def acquire(self) -> None:
        """Own this output for the run (before anything is read or written); :meth:`release` at the end.

        An exclusive ``flock`` on the lock file: the system drops it when the owning process ends, killed
        or not, so a stale lock never blocks; the file records the owner's pid, host and settings key for
        the message of a refused run.

        Raises
        ------
        LibraryError
            Another run (of any settings) is writing this output now.
        """
        import fcntl
        import socket
        import time

        try:
            if not self.file:
                self.path.mkdir(exist_ok=True)
            fd = os.open(self.lock_path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise OutputPathError(f"--out {self.path}: cannot create {self.lock_path} ({exc.strerror or exc}); "
                                  "choose another --out") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                owner = json.loads(os.pread(fd, 4096, 0).decode() or "{}")
            except ValueError:
                owner = {}
            os.close(fd)
            raise LibraryError(
                f"--out {self.path}: another invctl generate (pid {owner.get('pid', '?')} on "
                f"{owner.get('host', '?')}, settings key {owner.get('key', '?')}"
                + (", the same settings" if owner.get("key") == self.key else f", this run {self.key}")
                + ") is writing this library now; wait for it to finish (the same command then resumes or reads "
                "it back) or choose another --out", diagnostics={"out": str(self.path), "owner": owner}) from None
        except OSError as exc:  # a file system without locks
            os.close(fd)
            raise OutputPathError(f"--out {self.path}: cannot lock {self.lock_path} ({exc.strerror or exc}), so "
                                  "concurrent runs could not be kept apart; choose an --out on a local disk") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps({"key": self.key, "pid": os.getpid(), "host": socket.gethostname(),
                                  "started": time.strftime("%Y-%m-%dT%H:%M:%S%z")}).encode(), 0)
        self._lock: int | None = fd

    def release(self) -> None:
        fd: int | None = getattr(self, "_lock", None)
        self._lock = None
        if fd is not None:
            os.close(fd)  # drops the flock; the file stays (removing it would race with a run opening it)

    def _point_files(self):
        return sorted(self.parts.glob("point_*.npz")) if self.parts.is_dir() else []

    def index(self) -> dict:
        f = self.path / "library.json"
        if not f.is_file():
            raise ResultFileError(f"{self.path}: no library.json (an unfinished library: run generate again "
                                  "with the same settings to finish it)")
        return read_json(f, "library index")

    def _mismatch(self, what: str, found) -> None:
        raise OutputPathError(f"--out {self.path}: {what} holds a library of other settings (key {found}, this run "
                              f"{self.key}); pass --force to replace it or choose another --out")

    def clear(self) -> None:
        """Remove what an earlier library left here (only the library's own files)."""
        for f in self._point_files():
            f.unlink()
        if self.file:
            if self.parts.is_dir():
                shutil.rmtree(self.parts)
            if self.path.exists():
                self.path.unlink()
        elif (self.path / "library.json").exists():
            (self.path / "library.json").unlink()

    def existing(self, expect: str | None = None) -> dict:
        """Records of the points solved by an earlier run of the same settings (resume); with ``expect``
        (the key in ``library.json``, when loading) a point file of another key is a :class:`LibraryError`."""
        out: dict = {}
        if self.force and self.key is not None:  # start over
            self.clear()
            return out
        if self.file and self.path.exists():
            meta = read_meta(self.path)
            if meta["kind"] != "TrajectoryLibrary":
                raise OutputPathError(f"--out {self.path}: holds a {meta['kind']}, not a trajectory library")
            found = meta["info"].get("key")
            if self.key is not None and found != self.key:
                self._mismatch("the file", found)
            else:
                lib = Library.load(self.path)
                for i in np.flatnonzero(lib.solved):
                    out[int(i)] = _record(lib, int(i))
        elif not self.file and (self.path / "library.json").exists() and self.key is not None:
            found = self.index().get("key")
            if found != self.key:
                self._mismatch("the folder", found)
        for f in self._point_files():
            try:
                meta = read_meta(f)["info"]
                lib_meta = meta.get("library", {})
                if self.key is not None and lib_meta.get("key") != self.key:
                    self._mismatch(f"{f.name}", lib_meta.get("key"))
                if expect is not None and lib_meta.get("key") != expect:
                    raise LibraryError(
                        f"{f}: point {lib_meta.get('index')} ({lib_meta.get('values')}) belongs to another library "
                        f"(settings key {lib_meta.get('key')}; library.json of {self.path} has {expect}): runs of "
                        "different settings wrote into this folder; generate the library again into an empty "
                        "--out (or with --force)", diagnostics={"file": str(f), "key": lib_meta.get("key"),
                                                              "library_key": expect})
                z, _ = load_npz(f, ("Inverse", "LibraryPoint"))
            except ResultFileError:
                continue  # a file cut off by the interruption: solve that point again
            stats = lib_meta.get("stats", {})
            rec = {"index": int(lib_meta["index"]), "status": lib_meta.get("status", "solved"),
                   "t_mesh": z["t_mesh"], "X_mesh": z["X_mesh"], "dX_mesh": z["dX_mesh"], "X_col": z["X_col"],
                   "t0": float(meta["t0"]), "tf": float(meta["tf"]), **{k: stats.get(k) for k in stats}}
            rec["message"] = stats.get("message") or ""
            out[rec["index"]] = rec
        return out

    def write(self, rec: dict, meta: dict) -> Path:
        """Write one solved point (atomically: a cut-off write never looks like a solved point)."""
        from ..inversion import Inverse

        self.parts.mkdir(parents=True, exist_ok=True)
        i = int(rec["index"])
        final = self.parts / f"point_{i:05d}.npz"
        tmp = self.parts / f".point_{i:05d}.{os.getpid()}.tmp.npz"
        if self.file:
            save_npz(tmp, "LibraryPoint", {k: rec[k] for k in ("t_mesh", "X_mesh", "dX_mesh", "X_col")},
                     {**meta, "t0": rec["t0"], "tf": rec["tf"]})
        else:
            lay = self.layout
            inv = Inverse(lay["scheme"], rec["t_mesh"], rec["X_mesh"], rec["dX_mesh"], rec["X_col"], lay["sizes"],
                          rec["t0"], rec["tf"], lay.get("names", {}), {"status": rec["status"]})
            inv.to_npz(tmp, meta=meta)
        os.replace(tmp, final)
        return final

    def finish(self, lib: Library) -> Path:
        """Write the assembled library (file: replaces the parts; folder: ``library.json``)."""
        if self.file:
            tmp = self.path.with_name(f".{self.path.stem}.{os.getpid()}.tmp.npz")
            lib.save(tmp)
            os.replace(tmp, self.path)
            if self.parts.is_dir():
                shutil.rmtree(self.parts)
            return self.path
        d = lib.to_dict()
        index = {"key": self.key, "shape": list(lib.shape), "values": lib.values.tolist(),
                 "axes": [[a.name, a.kind, a.key, a.index, list(a.values)] for a in lib.axes],
                 "failures": d["failures"], "counts": d["counts"], "info": lib.info,
                 "files": {str(i): f"point_{i:05d}.npz" for i in np.flatnonzero(lib.solved)}}
        (self.path / "library.json").write_text(json.dumps(jsonable(index), indent=1))
        return self.path


def _record(lib: Library, i: int) -> dict:
    return {"index": i, "status": lib.status[i], "message": lib.messages[i], "t_mesh": lib.t_mesh[i],
            "X_mesh": lib.X_mesh[i], "dX_mesh": lib.dX_mesh[i], "X_col": lib.X_col[i], "t0": float(lib.t0[i]),
            "tf": float(lib.tf[i]), "initial_guess": lib.stats["initial_guess"][i],
            **{k: float(lib.stats[k][i]) for k in _STATS}}
