"""Banded Cholesky factorisation of sparse symmetric positive definite matrices (the solid's
Newton and PD matrices, the pressure recovery's Poisson matrix).

The fish is long and thin, so after a reverse Cuthill-McKee reordering its FEM matrices are
narrow bands: the default mesh's 2362 x 2362 Newton matrix has half-bandwidth w = 39. A banded
Cholesky K = L L^T then costs n w^2 to factor and 4 n w to solve, against SuperLU's general
sparse LU (default mesh, one thread: factor 0.84 vs 8.6 ms, solve 0.12 vs 0.57 ms).

The factor and the triangular solves are compiled (band_factor, band_solve) on a
row-major band L[j, i] = L_{j+i, j} (column j of L, from its diagonal down; LAPACK's lower band
storage transposed), so the solid's batched kernels (solid/kernels.py's newton_factors,
solve_samples) call them for many samples in parallel over numba's threads; LAPACK's
banded routines called from Python hold the GIL and cannot be. A matrix that is not positive
definite falls back to SuperLU (`spd_factor`).
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import reverse_cuthill_mckee

from fishsim.compiled import jit


@jit
def band_factor(L: np.ndarray) -> bool:
    """In place K -> its Cholesky factor, both as bands [n, w + 1] (L[j, i] = K_{j+i, j}, the
    lower triangle). Right-looking: column j is scaled by 1 / sqrt(pivot) and its outer product
    subtracted from the next w columns. Returns False (L then garbage) on a pivot <= 0, i.e. K is
    not positive definite."""
    n, w = L.shape[0], L.shape[1] - 1
    for j in range(n):
        pivot = L[j, 0]
        if not pivot > 0.0:
            return False
        d = np.sqrt(pivot)
        L[j, 0] = d
        m = min(w, n - 1 - j)
        for i in range(1, m + 1):
            L[j, i] /= d
        for k in range(1, m + 1):                   # column j + k -= L[j+k:, j] L[j+k, j]
            lk = L[j, k]
            for i in range(m - k + 1):
                L[j + k, i] -= L[j, k + i] * lk
    return True


@jit(fastmath={"reassoc", "contract"})
def band_solve(L: np.ndarray, x: np.ndarray) -> None:
    """In place x -> (L L^T)^-1 x for a factor band L [n, w + 1] and x [n]: forward substitution
    by columns, back substitution by (vectorised) dots."""
    n, w = L.shape[0], L.shape[1] - 1
    for j in range(n):
        xj = x[j] / L[j, 0]
        x[j] = xj
        for i in range(1, min(w, n - 1 - j) + 1):
            x[j + i] -= L[j, i] * xj
    for j in range(n - 1, -1, -1):
        s = x[j]
        for i in range(1, min(w, n - 1 - j) + 1):
            s -= L[j, i] * x[j + i]
        x[j] = s / L[j, 0]

class BandLayout:
    """Where a symmetric sparsity pattern's lower-triangle entries go in the band after the RCM
    permutation perm (row k of the band matrix is row perm[k] of K); computed once per pattern
    (the solid's matrices share a few patterns)."""

    _cache: ClassVar[dict] = {}

    def __init__(self, indptr: np.ndarray, indices: np.ndarray):
        n = len(indptr) - 1
        pattern = sp.csr_matrix((np.ones(len(indices)), indices, indptr), shape=(n, n))
        self.perm = reverse_cuthill_mckee(pattern, symmetric_mode=True)
        self.inverse = np.argsort(self.perm)
        rows = np.repeat(np.arange(n), np.diff(indptr))
        r, c = self.inverse[rows], self.inverse[indices]
        self.lower = r >= c
        self.column, self.offset = c[self.lower], (r - c)[self.lower]      # L[column, offset]
        self.width = int(self.offset.max())

    @classmethod
    def of(cls, indptr: np.ndarray, indices: np.ndarray) -> BandLayout:
        """The layout of a canonical CSR (or, symmetric, CSC) pattern (cached)."""
        key = (indptr.tobytes(), indices.tobytes())
        if key not in cls._cache:
            if len(cls._cache) >= 16:
                cls._cache.pop(next(iter(cls._cache)))
            cls._cache[key] = cls(indptr, indices)
        return cls._cache[key]

    def band(self, data: np.ndarray) -> np.ndarray:
        """The band [n, w + 1] of the matrix with the values ``data`` (in its CSR/CSC order)."""
        L = np.zeros((len(self.perm), self.width + 1))
        L[self.column, self.offset] = data[self.lower]
        return L


class BandedCholesky:
    """K = P^T L L^T P for a sparse SPD K (P: RCM permutation); ``solve(b)`` for b [n] or [n, k]."""

    def __init__(self, layout: BandLayout, factor: np.ndarray):
        self.layout, self.factor = layout, factor

    @classmethod
    def of(cls, K: sp.spmatrix) -> BandedCholesky | None:
        """Factorise K, or None when K is not positive definite."""
        if not isinstance(K, (sp.csr_matrix, sp.csc_matrix)) or not K.has_canonical_format:
            K = K.tocsr()
            K.sum_duplicates()
        # K is symmetric, so its CSC arrays read as CSR describe the same matrix
        return cls.with_layout(BandLayout.of(K.indptr, K.indices), K.data)

    @classmethod
    def with_layout(cls, layout: BandLayout, data: np.ndarray) -> BandedCholesky | None:
        """Factorise the matrix with the values ``data`` (in its CSR/CSC order) on the pattern
        of ``layout``, or None when it is not positive definite."""
        L = layout.band(data)
        return cls(layout, L) if band_factor(L) else None

    def solve(self, b: np.ndarray) -> np.ndarray:
        x = np.array(b[self.layout.perm], dtype=np.float64, order="F")
        for k in range(1 if x.ndim == 1 else x.shape[1]):
            band_solve(self.factor, x if x.ndim == 1 else x[:, k])
        return x[self.layout.inverse]


def lu_factor(K: sp.spmatrix):
    """SuperLU (symmetric mode) of the symmetric matrix K, for one that is not positive definite."""
    return spla.splu(K.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                     options={"SymmetricMode": True})


def spd_factor(K: sp.spmatrix):
    """A solver with ``.solve(b)`` for the symmetric matrix K: banded Cholesky when K is positive
    definite, else SuperLU (lu_factor)."""
    return BandedCholesky.of(K) or lu_factor(K)
