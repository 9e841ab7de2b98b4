"""Compiled evaluation of small CasADi functions, cached on disk across runs.

``compile_cached(fn)`` generates C code for an SX function, compiles it with the
system C compiler into ``$INVCTL_CACHE`` (default ``~/.cache/invctl``) under a
name derived from the function's serialization, and loads it with
``casadi.external``.  A second run (or another process) loads the shared
object without compiling.  Compiled functions have no derivatives: the
transcription uses them only where it supplies its own Jacobian (square
systems).  Whether this pays is measured in ``benchmarks/bench_inversion.py``.

``compile_in_background(fns, key)`` compiles what is missing in a separate process (a
forked child of the caller that it does not wait for; ``python -m invctl.inversion.compiled`` where there is no fork),
smallest function first, which outlives the caller: the first run on a new machine solves in CasADi's virtual machine and the
pieces switch to C as they land in the cache (a held solver picks them up between
solves; the next run finds them).  ``INVCTL_BACKGROUND_COMPILE=0`` turns it off.
"""
from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import casadi as ca


def cache_dir() -> Path:
    d = Path(os.environ.get("INVCTL_CACHE", Path.home() / ".cache" / "invctl"))
    d.mkdir(parents=True, exist_ok=True)
    return d


_COMPILERS: dict = {}


def compiler() -> str | None:
    cc = os.environ.get("CC", "gcc")
    if cc not in _COMPILERS:
        _COMPILERS[cc] = shutil.which(cc) or shutil.which("cc")
    return _COMPILERS[cc]


def _name(fn: ca.Function, flags, key: str | None = None) -> str:
    """Cache name: from ``key`` (a structural key of what built ``fn``, e.g. the model's
    serialized functions and the source of the code that derives ``fn`` from them) when
    given, else from the serialization of ``fn`` (kept on the function object:
    serializing the right-hand-side Jacobian costs ~10 ms)."""
    if key is not None:
        return keyed_name(fn.name(), flags, key)
    names = fn.__dict__.setdefault("_invctl_cache_names", {})
    name = names.get(tuple(flags))
    if name is None:
        digest = hashlib.sha1((fn.serialize() + " ".join(flags)).encode()).hexdigest()[:16]
        name = names[tuple(flags)] = f"{fn.name()}_{digest}"
    return name


def keyed_name(name: str, flags, key: str) -> str:
    """Cache name of the function called ``name`` built from what ``key`` describes (:func:`_name`)."""
    text = "|".join([key, name, " ".join(flags), str(getattr(ca, "__version__", ""))])
    return f"{name}_{hashlib.sha1(text.encode()).hexdigest()[:16]}"


def load_cached(name: str, key: str, flags: tuple[str, ...] = ("-O2",)) -> ca.Function | None:
    """The compiled function called ``name`` with cache key ``key`` from the disk cache, without building
    its SX function (``None`` when it is not there or there is no compiler)."""
    _reap()
    full = keyed_name(name, flags, key)
    so = cache_dir() / f"{full}.so"
    return ca.external(full, str(so)) if compiler() is not None and so.exists() else None


def is_cached(fn: ca.Function, flags: tuple[str, ...] = ("-O2",), key: str | None = None) -> bool:
    """Whether the compiled form of ``fn`` is already in the disk cache (and a compiler exists)."""
    _reap()
    return compiler() is not None and (cache_dir() / f"{_name(fn, flags, key)}.so").exists()


def compile_cached(fn: ca.Function, flags: tuple[str, ...] = ("-O2",), key: str | None = None) -> ca.Function:
    """The compiled (and disk-cached) equivalent of the SX function ``fn`` (cache name from
    ``key`` if given, see :func:`_name`).

    Raises
    ------
    RuntimeError
        No C compiler, or compilation failed (the message has the compiler output).
    """
    name = _name(fn, flags, key)
    so = cache_dir() / f"{name}.so"
    if not so.exists():
        _build(fn, name, flags)
    return ca.external(name, str(so))


def _build(fn: ca.Function, name: str, flags) -> None:
    """Generate, compile and atomically install ``$INVCTL_CACHE/<name>.so``."""
    cc = compiler()
    if cc is None:
        raise RuntimeError("compiled evaluation needs a C compiler (gcc/cc on PATH or $CC)")
    so = cache_dir() / f"{name}.so"
    sx_in = [fn.sx_in(i) for i in range(fn.n_in())]
    out = fn(*sx_in)
    outs = list(out) if isinstance(out, (list, tuple)) else [out]
    renamed = ca.Function(name, sx_in, outs, fn.name_in(), fn.name_out())
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


#: a lock file older than this is from a worker that died
_LOCK_STALE_S = 600.0


def background_enabled() -> bool:
    return os.environ.get("INVCTL_BACKGROUND_COMPILE", "1") != "0" and compiler() is not None


def compile_in_background(fns, flags: tuple[str, ...] = ("-O2",), key: str | None = None) -> Path | None:
    """Start one detached worker process compiling the functions of ``fns`` missing from the
    disk cache (smallest first); returns its lock file (removed when the worker is done), or
    ``None`` when nothing is missing, another worker holds the lock or background compilation is
    off (``INVCTL_BACKGROUND_COMPILE=0``, no compiler)."""
    if not background_enabled():
        return None
    todo = [(f, _name(f, flags, key)) for f in fns]
    todo = [(f, nm) for f, nm in todo if not (cache_dir() / f"{nm}.so").exists()]
    if not todo:
        return None
    d = cache_dir()
    tag = key if key is not None else todo[0][1]  # one worker per structural key
    lock = d / f"compile_{hashlib.sha1((tag + ' '.join(flags)).encode()).hexdigest()[:16]}.lock"
    try:
        if lock.exists() and time.time() - lock.stat().st_mtime < _LOCK_STALE_S:
            return None
        lock.write_text(str(os.getpid()))
    except OSError:
        return None
    todo.sort(key=lambda item: item[0].n_instructions())
    if hasattr(os, "fork"):
        _fork_worker(todo, flags, lock)
        return lock
    # no fork: the functions go to a new interpreter serialized (~0.15 s for the manipulator's largest)
    job = Path(tempfile.mkdtemp(prefix="invctl-compile-"))
    for i, (f, nm) in enumerate(todo):
        (job / f"{i:02d}_{nm}.casadi").write_text(f.serialize())
    (job / "flags").write_text(" ".join(flags))
    subprocess.Popen([sys.executable, "-m", "invctl.inversion.compiled", str(job), str(lock)],
                     stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                     start_new_session=True, env={**os.environ, "INVCTL_CACHE": str(d)})
    return lock


#: background workers forked by this process and not yet reaped (:func:`_reap`)
_WORKERS: list = []


def _reap() -> None:
    """Collect the exit status of finished background workers (no zombies left behind; never waits)."""
    for pid in list(_WORKERS):
        try:
            done = os.waitpid(pid, os.WNOHANG)[0] == pid
        except ChildProcessError:  # reaped by someone else
            done = True
        if done:
            _WORKERS.remove(pid)


def _fork_worker(todo, flags, lock: Path) -> None:
    """Compile ``todo`` in a forked child of this process: it has the functions in memory, so nothing
    is serialized on the caller's path, and the caller does not wait for it (a double fork that
    detaches the worker made the caller wait for the intermediate child: 30-70 ms of a first call on a
    loaded machine); lowest CPU priority, its own session, standard streams to ``/dev/null`` and no
    other inherited descriptors (nobody waits on a pipe it holds); it removes ``lock`` when done and is
    reaped by the next :func:`compile_in_background` or :func:`is_cached` of the caller (or by init
    after the caller exits)."""
    _reap()
    pid = os.fork()
    if pid:
        _WORKERS.append(pid)
        return
    try:
        os.setsid()
        os.nice(19)
        null = os.open(os.devnull, os.O_RDWR)
        for fd in (0, 1, 2):
            os.dup2(null, fd)
        os.closerange(3, 4096)
        for f, nm in todo:
            if not (cache_dir() / f"{nm}.so").exists():
                _build(f, nm, flags)
    finally:
        try:
            lock.unlink(missing_ok=True)
        finally:
            os._exit(0)


def _worker(job: Path, lock: Path) -> None:
    """Compile the serialized functions of ``job`` into the cache (the background process, at the
    lowest CPU priority: the caller's solves go first)."""
    try:
        os.nice(19)
        flags = tuple((job / "flags").read_text().split())
        for path in sorted(job.glob("*.casadi")):
            name = path.stem.split("_", 1)[1]
            if not (cache_dir() / f"{name}.so").exists():
                _build(ca.Function.deserialize(path.read_text()), name, flags)
    finally:
        shutil.rmtree(job, ignore_errors=True)
        lock.unlink(missing_ok=True)


if __name__ == "__main__":
    _worker(Path(sys.argv[1]), Path(sys.argv[2]))
