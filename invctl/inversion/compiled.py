"""Compiled evaluation of small CasADi functions, cached on disk across runs.

``compile_cached(fn)`` generates C code for an SX function, compiles it with the
system C compiler into ``$INVCTL_CACHE`` (default ``~/.cache/invctl``) under a
name derived from the function's serialization, and loads it with
``casadi.external``.  A second run (or another process) loads the shared
object without compiling.  Compiled functions have no derivatives: the
transcription uses them only where it supplies its own Jacobian (square
systems).  Whether this pays is measured in ``benchmarks/bench_inversion.py``.
"""
from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import casadi as ca


def cache_dir() -> Path:
    d = Path(os.environ.get("INVCTL_CACHE", Path.home() / ".cache" / "invctl"))
    d.mkdir(parents=True, exist_ok=True)
    return d


def compiler() -> str | None:
    return shutil.which(os.environ.get("CC", "gcc")) or shutil.which("cc")


_NAMES: dict = {}


def _name(fn: ca.Function, flags, key: str | None = None) -> str:
    """Cache name: from ``key`` (a structural key of what built ``fn``, e.g. the model's
    serialized functions and the source of the code that derives ``fn`` from them) when
    given, else from the serialization of ``fn`` (memoized per function object:
    serializing the right-hand-side Jacobian costs ~10 ms)."""
    if key is not None:
        text = "|".join([key, fn.name(), " ".join(flags), ca.__version__])
        return f"{fn.name()}_{hashlib.sha1(text.encode()).hexdigest()[:16]}"
    hit = _NAMES.get((id(fn), tuple(flags)))
    if hit is not None and hit[0] is fn:
        return hit[1]
    key = hashlib.sha1((fn.serialize() + " ".join(flags)).encode()).hexdigest()[:16]
    name = f"{fn.name()}_{key}"
    if len(_NAMES) > 256:
        _NAMES.clear()
    _NAMES[(id(fn), tuple(flags))] = (fn, name)
    return name


def is_cached(fn: ca.Function, flags: tuple[str, ...] = ("-O2",), key: str | None = None) -> bool:
    """Whether the compiled form of ``fn`` is already in the disk cache (and a compiler exists)."""
    return compiler() is not None and (cache_dir() / f"{_name(fn, flags, key)}.so").exists()


def compile_cached(fn: ca.Function, flags: tuple[str, ...] = ("-O2",), key: str | None = None) -> ca.Function:
    """The compiled (and disk-cached) equivalent of the SX function ``fn`` (cache name from
    ``key`` if given, see :func:`_name`).

    Raises
    ------
    RuntimeError
        No C compiler, or compilation failed (the message has the compiler output).
    """
    cc = compiler()
    if cc is None:
        raise RuntimeError("compiled evaluation needs a C compiler (gcc/cc on PATH or $CC)")
    name = _name(fn, flags, key)
    so = cache_dir() / f"{name}.so"
    if not so.exists():
        sx_in = [fn.sx_in(i) for i in range(fn.n_in())]
        out = fn(*sx_in)
        out = list(out) if isinstance(out, (list, tuple)) else [out]
        renamed = ca.Function(name, sx_in, out, fn.name_in(), fn.name_out())
        with tempfile.TemporaryDirectory() as tmp:
            cg = ca.CodeGenerator(f"{name}.c", {"with_header": False})
            cg.add(renamed)
            cg.generate(tmp + os.sep)
            tmp_so = Path(tmp) / f"{name}.so"
            r = subprocess.run([cc, *flags, "-shared", "-fPIC", "-o", str(tmp_so), str(Path(tmp) / f"{name}.c"), "-lm"],
                               capture_output=True, text=True)
            if r.returncode != 0:
                raise RuntimeError(f"compiling {name} failed:\n{r.stderr[-2000:]}")
            part = so.with_suffix(f".{os.getpid()}.part")
            shutil.copy(tmp_so, part)
            os.replace(part, so)
    return ca.external(name, str(so))
