"""One result vocabulary: :class:`Trajectory`, :class:`Status` and :func:`load`.

Every run result -- the stable inverse (:class:`~invctl.inversion.Inverse`), a closed-loop run
(:class:`~invctl.simulate.closed_loop.ClosedLoopResult`), a contact run
(:class:`~invctl.simulate.contact_record.ContactTrajectory`) and a switched run
(:class:`~invctl.simulate.switched.SwitchedSimulation`) -- is a :class:`Trajectory`:

==========  ============================================================================
``t``       sample times, ``(K,)``
``q, v``    coordinates and velocities, ``(n, K)`` (time along the last axis)
``u``       inputs, ``(m, K)``
``y``       outputs, ``(p, K)``
``lam``     constraint or contact forces, ``(l, K)`` (empty rows when there are none)
``status``  a :class:`Status`; ``success`` is ``status is Status.OK``
==========  ============================================================================

and has ``sample(t)``, ``plot(ax=None)``, ``to_npz(path)``; :func:`load` reads any saved result
back as its class.  The subclasses add their own extras (funnel ratios, impacts, events, ...).
"""
from __future__ import annotations

from dataclasses import MISSING, fields
from enum import Enum
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from .errors import ResultFileError
from .io import FORMAT_VERSION, file_loader, load_npz_versioned, read_meta, require_finite, save_npz


class Status(str, Enum):
    """How a run ended (a ``str``: ``Status.OK == "ok"``, and JSON writes the value)."""

    OK = "ok"
    LEFT_REGION = "left_region"
    FUNNEL_VIOLATION = "funnel_violation"
    FAILED = "failed"
    INTERRUPTED = "interrupted"

    __str__ = str.__str__

    def __format__(self, spec: str) -> str:
        return str.__format__(self.value, spec)

    @property
    def message(self) -> str:
        """One line saying what the status means."""
        return _MESSAGES[self]

    @classmethod
    def of(cls, value: Any) -> "Status":
        """``value`` (a status or its string) as a :class:`Status`.

        Raises
        ------
        ValueError
            Not one of the statuses (their values are listed).
        """
        try:
            return value if isinstance(value, cls) else cls(str(value))
        except ValueError:
            raise ValueError(f"unknown status {value!r}; statuses: {[s.value for s in cls]}") from None


_MESSAGES = {
    Status.OK: "ran to the end inside its region (and funnels)",
    Status.LEFT_REGION: "ran to the end, but left the model's operating region",
    Status.FUNNEL_VIOLATION: "left a funnel; the run is truncated there",
    Status.FAILED: "the solver or integrator failed; the result holds what was computed before",
    Status.INTERRUPTED: "interrupted (Ctrl-C or a time limit); the result holds what was computed before",
}


class Curve(np.ndarray):
    """An array of samples on a trajectory's times that can also be called at any times:
    ``inv.u`` is the feedforward on the mesh, ``inv.u(t)`` evaluates its polynomial at ``t``."""

    def __new__(cls, values, evaluate):
        obj = np.asarray(values, float).view(cls)
        obj._evaluate = evaluate
        return obj

    def __array_finalize__(self, obj):
        self._evaluate = None  # slices and arithmetic give plain samples; only the whole curve is callable

    def __array_wrap__(self, arr, context=None, return_scalar=False):
        out = np.asarray(arr)
        return out[()] if return_scalar else out

    def __call__(self, t) -> np.ndarray:
        if self._evaluate is None:
            raise TypeError("only a whole trajectory curve (e.g. inv.u) can be evaluated at times; index the result "
                            "instead: inv.u(t)[0]")
        return self._evaluate(t)

    def __reduce__(self):  # pickles as a plain array
        return np.asarray(self).__reduce__()


_FIELDS = ("q", "v", "u", "y", "lam")


class Trajectory:
    """Base class of every run result (see the module docstring for the common fields).

    Subclasses set ``t``, ``q``, ``v`` (and usually ``u``, ``y``, ``lam``) as attributes or
    properties; what a subclass does not have is an array with no rows.
    """

    #: axis labels of the generic plot, per field
    _AXES: ClassVar[dict] = {"q": "coordinates q", "v": "velocities v", "u": "inputs u", "y": "outputs y",
                             "lam": "forces lam"}

    t: Any
    q: Any
    v: Any

    def __post_init__(self):  # (dataclass subclasses) a status given as its string
        if hasattr(self, "status"):
            self.status = Status.of(self.status)

    def field(self, name: str) -> np.ndarray:
        """``q``, ``v``, ``u``, ``y`` or ``lam`` as a 2-D array ``(rows, len(t))`` (no rows when this result
        has no such signal)."""
        if name not in _FIELDS:
            raise ValueError(f"unknown trajectory field {name!r}; fields: {list(_FIELDS)}")
        a = getattr(self, name, None)
        if a is None:
            return np.zeros((0, np.size(self.t)))
        return np.atleast_2d(np.asarray(a, float))

    @property
    def success(self) -> bool:
        return Status.of(getattr(self, "status", Status.OK)) is Status.OK

    def row_names(self, field: str) -> list[str]:
        """Row names of ``field`` (``"q"``, ``"u"``, ...) for legends and CSV headers: the result's own
        (``names[field]`` or ``<field>_names``) when it has them, else ``q1, q2, ...``."""
        rows = self.field(field).shape[0]
        names = getattr(self, "names", None)
        given = names.get(field) if isinstance(names, dict) else getattr(self, f"{field}_names", None)
        if given is not None and len(given) == rows:
            return [str(x) for x in given]
        return [f"{field}{i + 1}" for i in range(rows)]

    # ---------------------------------------------------------------- common methods
    def sample(self, t) -> dict:
        """``q, v, u, y, lam`` at times ``t``, each ``(rows, len(t))`` (linear interpolation between the samples;
        subclasses with exact interpolants use those)."""
        t = np.atleast_1d(np.asarray(t, float))
        tt = np.asarray(self.t, float)
        out = {}
        for k in _FIELDS:
            a = self.field(k)
            if a.shape[-1] != tt.size:
                a = np.zeros((0, tt.size))
            out[k] = np.array([np.interp(t, tt, row) for row in a]).reshape(a.shape[0], t.size)
        return out

    def _generic_plot(self, ax=None, *, path=None, fields=("q", "u")):
        """The trajectory's ``fields`` against time, one axis each, labelled (``ax``: a list of axes to draw in;
        ``path``: also save the figure there). Returns the figure."""
        import matplotlib.pyplot as plt

        ax, path = plot_target(ax, path)

        fields = [f for f in fields if self.field(f).shape[0]]
        if ax is None:
            _, ax = plt.subplots(len(fields), 1, figsize=(7, 2.4 * len(fields) + 0.6), sharex=True, squeeze=False)
            ax = list(ax[:, 0])
        axes = list(np.atleast_1d(ax))
        t = np.asarray(self.t, float)
        for a, f in zip(axes, fields):
            for row, name in zip(self.field(f), self.row_names(f)):
                a.plot(t, row, label=name)
            a.set_ylabel(self._AXES.get(f, f))
            a.grid(alpha=0.3)
            a.legend(fontsize=7, loc="best")
        axes[-1].set_xlabel("time t [s]")
        axes[0].set_title(f"{type(self).__name__}: {Status.of(getattr(self, 'status', 'ok')).value}")
        from .plot import save

        save(axes[0].figure, path)
        return axes[0].figure

    def plot(self, ax=None, *, path=None, **options):
        """The result's figure (subclasses draw their own kind's panels); ``ax``: axes to draw in, ``path``: save
        the figure there too; ``fields``: which signals the generic panels show. Returns the figure."""
        return self._generic_plot(ax, path=path, fields=options.get("fields", ("q", "u")))

    # ---------------------------------------------------------------- files
    #: the ``.npz`` kind (its entry in :data:`KINDS`), the format version written and the older ones read
    _KIND: ClassVar[str] = ""
    _VERSION: ClassVar[int] = FORMAT_VERSION
    _OLDER: ClassVar[tuple] = ()
    #: dataclass fields written as arrays; the others go into the file's JSON info, ``meta`` merged into it
    _ARRAYS: ClassVar[tuple] = ()
    #: dict fields whose arrays are written as entries ``<prefix><key>`` (their other values into the info)
    _PREFIXED: ClassVar[dict] = {}
    #: info entries a file must have although their fields have defaults (written even when empty)
    _REQUIRED: ClassVar[tuple] = ()
    #: arrays besides the fields that a file must have (a subclass's samples), handed to :meth:`_read`
    _SAMPLES: ClassVar[tuple] = ()
    #: fields not written (:meth:`_read` rebuilds them) and the entries that must be finite
    _UNSAVED: ClassVar[tuple] = ()
    _FINITE: ClassVar[tuple] = ("t", "q", "v")

    def to_npz(self, path, *, meta: dict | None = None) -> Path:
        """Write to ``.npz`` (read back with :func:`load`); ``meta`` (JSON-able) records where the run came from
        (scene, parameters) for ``invctl animate``. Returns the path written."""
        return self._write(path, {}, meta)

    def _write(self, path, arrays: dict, meta: dict | None) -> Path:
        """:meth:`to_npz` with a subclass's ``arrays`` (its samples) written besides the fields."""
        arrays, info = dict(arrays), {}
        for name in (f.name for f in fields(self)):  # type: ignore[arg-type]  # subclasses are dataclasses
            value = getattr(self, name)
            if name in self._ARRAYS:
                arrays[name] = value
            elif name in self._PREFIXED:
                plain = {k: v for k, v in value.items() if isinstance(v, np.ndarray) and v.dtype != object}
                arrays.update({self._PREFIXED[name] + k: v for k, v in plain.items()})
                if len(plain) < len(value) or name in self._REQUIRED:
                    info[name] = {k: v for k, v in value.items() if k not in plain}
            elif name not in ("meta", *self._UNSAVED):
                info[name] = value
        return save_npz(path, self._KIND, arrays, {**info, **self.meta, **(meta or {})},  # type: ignore[attr-defined]
                        version=self._VERSION)

    @classmethod
    @file_loader
    def load(cls, path):
        """Read a file written by :meth:`to_npz` (format, version, completeness and finite values checked).

        Raises
        ------
        ResultFileError
            Missing, truncated, foreign, incomplete or newer files, and older ones this class cannot convert.
        """
        d, info, version = load_npz_versioned(path, cls._KIND, version=cls._VERSION, older=cls._OLDER)
        missing = [k for k in cls._SAMPLES if k not in d] + [k for k in cls._REQUIRED if k not in info]
        kw: dict[str, Any] = {k: d[k] for k in cls._SAMPLES if k in d}
        for name, prefix in cls._PREFIXED.items():
            kw[name] = {**info.pop(name, {}), **{k[len(prefix):]: v for k, v in d.items() if k.startswith(prefix)}}
        for f in fields(cls):
            src = d if f.name in cls._ARRAYS else info
            if f.name in kw or f.name in ("meta", *cls._UNSAVED):
                continue
            if f.name in src:
                kw[f.name] = _typed(str(f.type), src.pop(f.name))
            elif f.name in cls._ARRAYS or f.default is MISSING and f.default_factory is MISSING:
                missing.append(f.name)
        if missing:
            raise ResultFileError(f"{path}: incomplete {cls.__name__} file (missing {missing})")
        require_finite(path, kw, cls._FINITE)
        kw["meta"] = {**info.pop("meta", {}), **info}  # the rest of the info (switched runs nested it)
        return cls(**cls._read(path, kw, version))

    @classmethod
    def _read(cls, path, kw: dict, version: int) -> dict:
        """The constructor's arguments of a file of format ``version`` (subclasses check and convert, and take
        their :attr:`_SAMPLES` out)."""
        return kw


def _typed(kind: str, value):
    """A value read from a file as its field's annotated type (scalars, names; arrays as they are)."""
    if kind == "list":
        return [str(x) for x in np.atleast_1d(value)] if np.size(value) else []
    convert = {"float": float, "int": int, "str": str, "dict": dict}.get(kind)
    return value if convert is None else convert(value)


class Animated(Trajectory):
    """A run of a scene's mechanism (an inverse, a closed-loop or a contact run), drawn by :meth:`animate`."""

    def animate(self, path, **options):
        """Draw the mechanism along the run (GIF/MP4) from the scene's drawing (an inverse: along its state
        trajectory, pre-actuation included); see :func:`invctl.plot.animate.animate_result` (the scene defaults
        to ``meta["scene"]``)."""
        from .plot.animate import animate_result

        return animate_result(self, path, **options)


def plot_target(ax, path):
    """``(ax, path)`` of a ``plot(ax=None, *, path=None)`` call; a path given in place of the axes (the older
    ``result.plot("fig.png")``) is taken as the path."""
    import os

    if isinstance(ax, (str, os.PathLike)):
        return None, ax
    return ax, path


#: ``.npz`` kind -> the class that reads it (imported on use, so loading one kind imports only its module)
KINDS = {
    "Inverse": ("invctl.inversion.result", "Inverse"),
    "ClosedLoopResult": ("invctl.simulate.closed_loop", "ClosedLoopResult"),
    "ContactTrajectory": ("invctl.simulate.contact_record", "ContactTrajectory"),
    "SwitchedSimulation": ("invctl.simulate.switched", "SwitchedSimulation"),
    "TrajectoryLibrary": ("invctl.studies.library_data", "Library"),
}


def load(path):
    """Read any result invctl saved: an ``.npz`` run (inverse, closed-loop, contact, switched run, trajectory
    library) or a tracking study's folder (``study.json`` with its runs), as its own class.

    Raises
    ------
    ResultFileError
        Missing, truncated or foreign file, or a kind this invctl does not know.
    """
    import importlib

    p = Path(path)
    if p.is_dir():
        if not (p / "study.json").is_file():
            raise ResultFileError(f"{p}: a folder without study.json; invctl.load reads .npz files and the folders "
                                  "`invctl pipeline` writes for tracking scenes")
        from .studies.tracking import TrackingStudy

        return TrackingStudy.load(p)
    kind = read_meta(p)["kind"]
    if kind not in KINDS:
        raise ResultFileError(f"{p}: holds a {kind!r}, which invctl.load cannot read; it reads {sorted(KINDS)}")
    module, name = KINDS[kind]
    return getattr(importlib.import_module(module), name).load(p)
