"""Saving and loading results (``.npz`` with a format tag and version), output-path checks.

Every result type writes its arrays plus one JSON entry ``__invctl__`` =
``{"kind": ..., "version": ..., "info": {...}}``; :func:`load_npz` checks the tag, the kind and
the version and raises :class:`~invctl.errors.ResultFileError` for missing, truncated, foreign or
newer files instead of returning wrong-sized data.
"""
from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path

import numpy as np

from .errors import OutputPathError, ResultFileError

__all__ = ["FORMAT_VERSION", "save_npz", "load_npz", "check_output_path", "read_meta"]

#: version of the files written by this invctl (raise when the layout changes incompatibly)
FORMAT_VERSION = 2
_TAG = "__invctl__"


def save_npz(path, kind: str, arrays: dict, info: dict | None = None) -> Path:
    """Write ``arrays`` (name -> array-like) and ``info`` (JSON-able) to ``path`` (``.npz`` added
    when missing); returns the path written."""
    from .scenes import jsonable

    path = Path(path)
    if path.suffix != ".npz":
        path = path.with_name(path.name + ".npz")
    data = {k: np.asarray(v) for k, v in arrays.items()}
    for k, v in data.items():
        if v.dtype == object:
            raise ResultFileError(f"save_npz: entry {k!r} is not a plain array")
    meta = {"kind": kind, "version": FORMAT_VERSION, "info": jsonable(info or {})}
    data[_TAG] = np.asarray(json.dumps(meta))
    np.savez(path, **data)
    return path


def read_meta(path) -> dict:
    """The ``{"kind", "version", "info"}`` entry of an invctl result file (checked)."""
    path = Path(path)
    if not path.is_file():
        raise ResultFileError(f"{path}: no such file")
    try:
        with np.load(path, allow_pickle=False) as d:
            if _TAG not in d.files:
                raise ResultFileError(f"{path}: not an invctl result file (no {_TAG!r} entry); it was written "
                                      "by another program or an older invctl: recompute it")
            meta = json.loads(str(d[_TAG]))
    except ResultFileError:
        raise
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError) as exc:
        raise ResultFileError(f"{path}: cannot read ({type(exc).__name__}: {exc}); the file is truncated or "
                              "not an .npz file") from None
    if not isinstance(meta, dict) or "kind" not in meta or "version" not in meta:
        raise ResultFileError(f"{path}: malformed {_TAG!r} entry")
    return meta


def load_npz(path, kind: str | tuple) -> tuple[dict, dict]:
    """Arrays and info of a file written by :func:`save_npz`, after checking tag, kind and version.

    Raises
    ------
    ResultFileError
        Missing, truncated or foreign file, another result kind, a newer format version, or
        non-finite values in a float array.
    """
    path = Path(path)
    meta = read_meta(path)
    kinds = (kind,) if isinstance(kind, str) else tuple(kind)
    if meta["kind"] not in kinds:
        raise ResultFileError(f"{path}: holds a {meta['kind']}, expected {' or '.join(kinds)}")
    if int(meta["version"]) > FORMAT_VERSION:
        raise ResultFileError(f"{path}: format version {meta['version']} is newer than this invctl's "
                              f"({FORMAT_VERSION}); upgrade invctl")
    if int(meta["version"]) < FORMAT_VERSION:
        raise ResultFileError(f"{path}: format version {meta['version']} is older than this invctl's "
                              f"({FORMAT_VERSION}); recompute the result")
    try:
        with np.load(path, allow_pickle=False) as d:
            arrays = {k: np.array(d[k]) for k in d.files if k != _TAG}
    except (zipfile.BadZipFile, EOFError, OSError, ValueError) as exc:
        raise ResultFileError(f"{path}: cannot read ({type(exc).__name__}: {exc}); the file is truncated") from None
    return arrays, dict(meta.get("info", {}))


def require_finite(path, arrays: dict, names) -> None:
    """Raise :class:`ResultFileError` when one of ``names`` holds NaN or infinity."""
    for k in names:
        a = arrays.get(k)
        if a is not None and a.dtype.kind == "f" and not np.all(np.isfinite(a)):
            raise ResultFileError(f"{path}: entry {k!r} holds non-finite values")


def check_output_path(path, *, suffix: str | None = None, force: bool = False, option: str = "--out") -> Path:
    """Check, before any computation, that ``path`` can be written: its directory exists and is
    writable, and an existing file is replaced only with ``force``. Returns the final path (``suffix``
    appended when missing, as the writer will do).

    Raises
    ------
    OutputPathError
        What is wrong and what to do.
    """
    p = Path(path)
    if suffix and p.suffix.lower() != suffix:
        p = p.with_name(p.name + suffix)
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise OutputPathError(f"{option} {path}: directory {str(parent)!r} does not exist; create it first")
    if not os.access(parent, os.W_OK):
        raise OutputPathError(f"{option} {path}: directory {str(parent)!r} is not writable")
    if p.is_dir():
        raise OutputPathError(f"{option} {path}: is a directory; give a file name")
    if p.exists() and not force:
        raise OutputPathError(f"{option} {p}: file exists; pass --force to replace it or choose another name")
    return p


def check_output_dir(path, *, option: str = "--out-dir") -> Path:
    """Check that a results folder can be created or written (before any computation)."""
    p = Path(path)
    probe = p
    while not probe.exists():
        probe = probe.parent if str(probe.parent) != str(probe) else Path(".")
    if not probe.is_dir():
        raise OutputPathError(f"{option} {path}: {str(probe)!r} is a file, not a folder")
    if not os.access(probe, os.W_OK):
        raise OutputPathError(f"{option} {path}: {str(probe)!r} is not writable")
    return p
