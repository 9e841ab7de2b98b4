"""Saving and loading results (``.npz`` with a format tag and version), output-path checks.

Every result type writes its arrays plus one JSON entry ``__invctl__`` =
``{"kind": ..., "version": ..., "info": {...}}``; :func:`load_npz` checks the tag, the kind and
the version and raises :class:`~invctl.errors.ResultFileError` for missing, truncated, foreign or
newer files instead of returning wrong-sized data.
"""
from __future__ import annotations

import csv
import functools
import json
import os
import zipfile
from pathlib import Path

import numpy as np

from .errors import InvctlError, OutputPathError, ResultFileError

#: version of the files written by this invctl (raise when the layout changes incompatibly); a result
#: type whose layout changed on its own writes its own version (``save_npz(..., version=...)``) and
#: reads the older ones it can convert (``load_npz_versioned(..., older=...)``)
FORMAT_VERSION = 2
_TAG = "__invctl__"


def save_npz(path, kind: str, arrays: dict, info: dict | None = None, *, version: int = FORMAT_VERSION) -> Path:
    """Write ``arrays`` (name -> array-like) and ``info`` (JSON-able) to ``path`` (``.npz`` added
    when missing) with format ``version``; returns the path written."""
    from .scenes import jsonable

    path = Path(path)
    if path.suffix != ".npz":
        path = path.with_name(path.name + ".npz")
    data = {k: np.asarray(v) for k, v in arrays.items()}
    for k, v in data.items():
        if v.dtype == object:
            raise ResultFileError(f"save_npz: entry {k!r} is not a plain array")
    meta = {"kind": kind, "version": int(version), "info": jsonable(info or {})}
    data[_TAG] = np.asarray(json.dumps(meta))
    np.savez(path, **data)  # type: ignore[arg-type]  # numpy types the first keyword as allow_pickle
    return path


def read_meta(path) -> dict:
    """The ``{"kind", "version", "info"}`` entry of an invctl result file (checked)."""
    path = Path(path)
    if not path.is_file():
        raise ResultFileError(f"{path}: no such file" + (" (a folder)" if path.is_dir() else ""))
    if not zipfile.is_zipfile(path):
        raise ResultFileError(f"{path}: not an .npz result file (not a zip archive: another format, or truncated)")
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
    if (not isinstance(meta, dict) or not isinstance(meta.get("kind"), str) or isinstance(meta.get("version"), bool)
            or not isinstance(meta.get("version"), int) or not isinstance(meta.get("info", {}), dict)):
        raise ResultFileError(f"{path}: malformed {_TAG!r} entry (needs a kind, an integer version and an info "
                              "dict); the file was edited or not written by invctl")
    return meta


def load_npz(path, kind: str | tuple, *, version: int = FORMAT_VERSION) -> tuple[dict, dict]:
    """Arrays and info of a file written by :func:`save_npz`, after checking tag, kind and version
    (exactly ``version``).

    Raises
    ------
    ResultFileError
        Missing, truncated or foreign file, another result kind, a newer or older format version, or
        non-finite values in a float array.
    """
    arrays, info, _ = load_npz_versioned(path, kind, version=version)
    return arrays, info


def load_npz_versioned(path, kind: str | tuple, *, version: int = FORMAT_VERSION,
                       older: tuple = ()) -> tuple[dict, dict, int]:
    """``(arrays, info, file_version)`` of a file written by :func:`save_npz` whose format version is
    ``version`` or one of the ``older`` versions the caller converts itself.

    Raises
    ------
    ResultFileError
        Missing, truncated or foreign file, another result kind, a version newer than ``version``
        or older and not in ``older``.
    """
    path = Path(path)
    meta = read_meta(path)
    kinds = (kind,) if isinstance(kind, str) else tuple(kind)
    if meta["kind"] not in kinds:
        raise ResultFileError(f"{path}: holds a {meta['kind']}, expected {' or '.join(kinds)}")
    found = int(meta["version"])
    if found > version:
        raise ResultFileError(f"{path}: format version {found} is newer than this invctl's "
                              f"({version}); upgrade invctl")
    if found < version and found not in tuple(older):
        raise ResultFileError(f"{path}: format version {found} is older than this invctl's "
                              f"({version}); recompute the result")
    try:
        with np.load(path, allow_pickle=False) as d:
            arrays = {k: np.array(d[k]) for k in d.files if k != _TAG}
    except (zipfile.BadZipFile, EOFError, OSError, ValueError) as exc:
        raise ResultFileError(f"{path}: cannot read ({type(exc).__name__}: {exc}); the file is truncated") from None
    return arrays, dict(meta.get("info", {})), found


def file_loader(load):
    """Decorator of a ``load(cls, path)`` classmethod body: a file whose entries have the wrong type,
    shape or content (a schema error raising ``KeyError``, ``TypeError``, ``ValueError``,
    ``AttributeError``, ``IndexError`` or ``OSError`` while the object is rebuilt) becomes a
    :class:`ResultFileError` naming the file, never a traceback or a wrong object."""
    @functools.wraps(load)
    def wrapper(cls, path, *args, **kwargs):
        try:
            return load(cls, path, *args, **kwargs)
        except InvctlError:
            raise
        except FileNotFoundError as exc:
            raise ResultFileError(f"{path}: no such file ({exc.filename})") from None
        except (KeyError, TypeError, ValueError, AttributeError, IndexError, OSError, zipfile.BadZipFile) as exc:
            raise ResultFileError(f"{path}: malformed {cls.__name__} file ({type(exc).__name__}: {exc}); it was "
                                  "edited, truncated or not written by this invctl") from None
    return wrapper


def read_json(path, what: str) -> dict:
    """A JSON object from ``path`` (``what`` names the file in errors).

    Raises
    ------
    ResultFileError
        Missing, unreadable or truncated file, or JSON that is not an object.
    """
    path = Path(path)
    try:
        d = json.loads(path.read_text())
    except FileNotFoundError:
        raise ResultFileError(f"{path}: no such file ({what})") from None
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise ResultFileError(f"{path}: not a readable {what} ({type(exc).__name__}: {exc}); the file is truncated "
                              "or was not written by invctl") from None
    if not isinstance(d, dict):
        raise ResultFileError(f"{path}: a {what} holds a JSON object, got {type(d).__name__}")
    return d


def write_rows(path, rows, first: tuple = ()) -> None:
    """``rows`` (dicts) as CSV with a header: the columns ``first``, then in the order they first appear."""
    keys = list(dict.fromkeys([*first, *(k for r in rows for k in r)]))
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=keys)
        writer.writeheader()
        writer.writerows(rows)


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
    _check_name(path, option)
    p = Path(path)
    if not p.name:
        raise OutputPathError(f"{option} {str(path)!r}: give a file name")
    if suffix and p.suffix.lower() != suffix:
        p = p.with_name(p.name + suffix)
    _check_name(p, option)
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise OutputPathError(f"{option} {path}: directory {str(parent)!r} does not exist; create it first")
    _probe_write(parent, f"{option} {path}: directory {str(parent)!r}")
    if p.is_dir():
        raise OutputPathError(f"{option} {path}: is a directory; give a file name")
    if p.exists() and not force:
        raise OutputPathError(f"{option} {p}: file exists; pass --force to replace it or choose another name")
    return p


def _check_name(path, option) -> None:
    text = str(path)
    if "\x00" in text:
        raise OutputPathError(f"{option} {text!r}: a path cannot contain a NUL character")
    try:
        max_name = os.pathconf(".", "PC_NAME_MAX")
    except (OSError, ValueError, AttributeError):
        max_name = 255
    long = [part for part in Path(text).parts if len(part.encode(errors="surrogateescape")) > max_name]
    if long:
        raise OutputPathError(f"{option} {text[:60]!r}...: the name {long[0][:40]!r}... is longer than the "
                              f"{max_name} bytes the file system allows")


def check_output_dir(path, *, option: str = "--out-dir") -> Path:
    """Check, before any computation, that a results folder can be written: it is created (with its
    parents) if missing and a file is written to it and removed."""
    _check_name(path, option)
    p = Path(path)
    probe = p
    while not probe.exists():
        probe = probe.parent if str(probe.parent) != str(probe) else Path(".")
    if not probe.is_dir():
        raise OutputPathError(f"{option} {path}: {str(probe)!r} is a file, not a folder")
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputPathError(f"{option} {path}: cannot create the folder ({exc.strerror or exc})") from None
    _probe_write(p, f"{option} {path}: folder")
    return p


def _probe_write(folder: Path, what: str) -> None:
    """Write and remove a file in ``folder`` (permission bits do not tell everything: read-only or
    virtual file systems, quotas)."""
    import tempfile

    if not os.access(folder, os.W_OK):
        raise OutputPathError(f"{what} is not writable")
    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".invctl-probe-"):
            pass
    except OSError as exc:
        raise OutputPathError(f"{what} is not writable ({exc.strerror or exc})") from None
