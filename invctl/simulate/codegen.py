"""Helpers of the compiled time loops: symbolic small solves, common-subexpression elimination,
named state layouts, and C code generation compiled with the system compiler (disk cache)."""
from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import casadi as ca


def c_compiler() -> str | None:
    """Path of a C compiler (``$CC``, gcc, cc, clang) or None."""
    for name in (os.environ.get("CC"), "gcc", "cc", "clang"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


def cache_dir() -> Path:
    """``$INVCTL_CACHE`` or ``~/.cache/invctl`` (a temporary folder if neither is writable)."""
    d = Path(os.environ.get("INVCTL_CACHE", Path.home() / ".cache" / "invctl"))
    try:
        d.mkdir(parents=True, exist_ok=True)
        if not os.access(d, os.W_OK):
            raise OSError(f"{d} is not writable")
    except OSError:
        d = Path(tempfile.gettempdir()) / f"invctl-cache-{os.getuid()}"
        d.mkdir(parents=True, exist_ok=True)
    return d


def small_solve(A, B):
    """``A^{-1} B`` for symbolic ``A``: one division per row for a structurally diagonal ``A``,
    adjugate formula for n <= 3 (few operations, exploits structural zeros), symbolic QR beyond."""
    n = A.shape[0]
    if all(A[i, j].is_zero() for i in range(n) for j in range(n) if i != j):
        return ca.vertcat(*[B[i, :] / A[i, i] for i in range(n)])
    if n == 2:
        det = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
        adj = ca.blockcat([[A[1, 1], -A[0, 1]], [-A[1, 0], A[0, 0]]])
        return ca.mtimes(adj, B) / det
    if n == 3:
        c = [[A[(i + 1) % 3, (j + 1) % 3] * A[(i + 2) % 3, (j + 2) % 3]
              - A[(i + 1) % 3, (j + 2) % 3] * A[(i + 2) % 3, (j + 1) % 3] for j in range(3)] for i in range(3)]
        det = A[0, 0] * c[0][0] + A[0, 1] * c[0][1] + A[0, 2] * c[0][2]
        adj = ca.blockcat([[c[j][i] for j in range(3)] for i in range(3)])
        return ca.mtimes(adj, B) / det
    return ca.solve(A, B)


def cse(*exprs):
    """Common-subexpression elimination (CasADi >= 3.6), if available."""
    if hasattr(ca, "cse"):
        out = ca.cse(list(exprs))
        return tuple(out)
    return exprs


class Layout:
    """Named slices of a stacked column vector."""

    def __init__(self, parts):
        self.parts = list(parts)
        self.sl, o = {}, 0
        for name, size in self.parts:
            self.sl[name] = slice(o, o + size)
            o += size
        self.size = o

    def __getitem__(self, name):
        return self.sl[name]


def generate_c(*fns: ca.Function) -> str:
    """C code of ``fns`` (CasADi code generation, no header)."""
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / f"{fns[0].name()}.c"
        cg = ca.CodeGenerator(src.name, {"with_header": False})
        for fn in fns:
            cg.add(fn)
        cg.generate(str(tmp) + os.sep)
        return src.read_text()


def compile_c(code: str, *, large: bool = False, verbose: bool = False) -> Path | None:
    """Shared library of the C ``code`` built with the system compiler, cached on disk under the hash
    of the code (None when no compiler works).  No ``-ffast-math``, and no contraction to fused
    multiply-adds: the compiled arithmetic is the VM's, to the last bit."""
    cc = c_compiler()
    if cc is None:
        return None
    # -O1 for very long straight-line code: -O3 takes minutes there and runs no faster (measured)
    opt = "-O1" if large else "-O3"
    # -fno-semantic-interposition: calls between the generated functions may be inlined; short code also
    # scheduled before register allocation, register pressure aware (fewer spills in the time loop)
    extra = ["-march=native", "-fno-semantic-interposition"]
    if not large:
        extra += ["-fschedule-insns", "-fsched-pressure"]
    flags = [opt, *extra, "-ffp-contract=off", "-fPIC", "-shared"]
    key = hashlib.sha256(code.encode() + " ".join(flags).encode()).hexdigest()[:20]
    lib = cache_dir() / f"mj_{key}.so"
    if not lib.exists():
        csrc = cache_dir() / f"mj_{key}.{os.getpid()}.c"
        csrc.write_text(code)
        tmp_lib = lib.with_suffix(f".{os.getpid()}.tmp.so")
        cmd = [cc, *flags, str(csrc), "-o", str(tmp_lib), "-lm"]
        if verbose:
            print("invctl: compiling time-stepping loop:", " ".join(cmd), file=sys.stderr)
        res = subprocess.run(cmd, capture_output=True, text=True)
        if res.returncode != 0:
            cmd = [a for a in cmd if a not in extra]
            res = subprocess.run(cmd, capture_output=True, text=True)
            if res.returncode != 0:
                print(f"invctl: C compilation failed, using the CasADi VM:\n{res.stderr[:500]}", file=sys.stderr)
                csrc.unlink(missing_ok=True)
                return None
        os.replace(tmp_lib, lib)
        csrc.unlink(missing_ok=True)
    return lib
