"""Shared pieces of the collocation NLPs: sparse assembly of dense per-interval blocks (mapped SX outputs)
into global CSC matrices, compiled-function helpers."""
from __future__ import annotations

import casadi as ca
import numpy as np


def _assembly(rows, cols, shape, *, summed: bool = False):
    """Sparsity of the triplets ``(rows, cols)`` and the sparse 0/1 matrix mapping values in
    triplet order to its nonzeros in CSC order (duplicates are added when ``summed``)."""
    rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
    key = cols * shape[0] + rows
    uniq = np.unique(key)
    if not summed and uniq.size != key.size:
        raise RuntimeError("duplicate entries in a Jacobian pattern")
    pos = np.searchsorted(uniq, key)
    ucols, urows = uniq // shape[0], uniq % shape[0]
    indptr = np.concatenate([[0], np.cumsum(np.bincount(ucols, minlength=shape[1]))])
    sparsity = ca.Sparsity(int(shape[0]), int(shape[1]), indptr.astype(np.int64).tolist(),
                           urows.astype(np.int64).tolist())
    S = ca.DM(ca.Sparsity.triplet(int(uniq.size), int(key.size), pos.tolist(), list(range(key.size))), 1.0)
    return sparsity, S


def _block_triplets(nrow: int, index: np.ndarray, row0: int):
    """Global (row, col) of the vec of a mapped dense block output ``(nrow x nz)`` per repetition
    (``index``: ``(count, nz)`` global columns; rows ``row0 + k nrow + i``), in vec order."""
    count, nz = index.shape
    k = np.repeat(np.arange(count), nz * nrow)
    j = np.tile(np.repeat(np.arange(nz), nrow), count)
    i = np.tile(np.arange(nrow), count * nz)
    return row0 + k * nrow + i, index[k, j]


def _all_cached(functions) -> bool:
    from .compiled import is_cached

    return all(is_cached(f) for f in functions)


def _compile(fn):
    from .compiled import compile_cached

    return compile_cached(fn)
