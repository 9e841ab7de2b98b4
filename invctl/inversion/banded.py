"""Banded LU factorization of the collocation Jacobian (Newton backend).

The Jacobian of a collocation transcription is almost block diagonal: ordered by time,
every defect couples only the unknowns of one interval.  Permuted to that order it is a
band matrix, and LAPACK's banded LU with partial pivoting (``dgbtrf``/``dgbtrs``)
factorizes it in ``O(n kl (kl + ku))`` -- about four times faster than SuperLU on the
manipulator's HS N = 100 system (``benchmarks/bench_inversion.py``).  The pattern is
analysed once per transcription; each factorization scatters the values into band
storage with one precomputed index array.
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import lapack


class BandedPattern:
    """Row/column permutations of a fixed square sparsity pattern (CSC ``indices``,
    ``indptr``) that make it banded, and the scatter into LAPACK band storage.

    Parameters
    ----------
    indices, indptr : CSC pattern of the ``n x n`` matrix.
    col_order : permutation of the columns (new position -> old column), e.g. the
        unknowns in time order; rows are then sorted by their last and first column.
    """

    def __init__(self, indices, indptr, n: int, col_order=None):
        indices = np.asarray(indices, np.int64)
        indptr = np.asarray(indptr, np.int64)
        self.n = n
        cols = np.repeat(np.arange(n), np.diff(indptr))
        corder = np.arange(n) if col_order is None else np.asarray(col_order, np.int64)
        cpos = np.empty(n, np.int64)
        cpos[corder] = np.arange(n)
        pc = cpos[cols]
        cmax = np.full(n, -1, np.int64)
        cmin = np.full(n, n, np.int64)
        np.maximum.at(cmax, indices, pc)
        np.minimum.at(cmin, indices, pc)
        rorder = np.lexsort((cmin, cmax))  # new row position -> old row
        rpos = np.empty(n, np.int64)
        rpos[rorder] = np.arange(n)
        pr = rpos[indices]
        self.kl = int(max(0, np.max(pr - pc)))
        self.ku = int(max(0, np.max(pc - pr)))
        self.ldab = 2 * self.kl + self.ku + 1
        # band storage, Fortran order: ab[kl + ku + i - j, j] = A[i, j]
        self._flat = (self.kl + self.ku + pr - pc) + self.ldab * pc
        self._rpos, self._corder = rpos, corder

    @property
    def worthwhile(self) -> bool:
        """Whether the band is narrow enough for the banded LU to beat a general sparse LU in
        time and memory (band storage is ``(2 kl + ku + 1) n`` doubles: HS on the manipulator
        has 69 rows, Legendre/Radau of degree 3 have 181, where SuperLU needs less memory)."""
        return self.n >= 64 and self.ldab <= 100 and self.ldab * self.n * 8 <= 64e6

    def factor(self, data) -> "BandedLU":
        """Factorize the matrix with these nonzeros (CSC order of the pattern).

        Raises
        ------
        RuntimeError
            The matrix is exactly singular (a zero pivot), as ``scipy.sparse.linalg.splu`` does.
        """
        ab = np.zeros(self.ldab * self.n)
        ab[self._flat] = data
        lu, piv, info = lapack.dgbtrf(ab.reshape(self.ldab, self.n, order="F"), self.kl, self.ku,
                                      overwrite_ab=1)
        if info > 0:
            raise RuntimeError(f"Factor is exactly singular (zero pivot in column {info - 1} of the band order)")
        if info < 0:
            raise ValueError(f"dgbtrf: illegal argument {-info}")
        return BandedLU(self, lu, piv)


class BandedLU:
    """A banded LU factorization; ``solve(b)`` solves ``A x = b`` in the original ordering."""

    def __init__(self, pattern: BandedPattern, lu, piv):
        self.pattern, self._lu, self._piv = pattern, lu, piv

    def solve(self, b) -> np.ndarray:
        pat = self.pattern
        bp = np.empty(pat.n)
        bp[pat._rpos] = np.asarray(b, float).ravel()
        y, info = lapack.dgbtrs(self._lu, pat.kl, pat.ku, bp, self._piv)
        if info != 0:
            raise ValueError(f"dgbtrs: illegal argument {-info}")
        x = np.empty(pat.n)
        x[pat._corder] = y
        return x
