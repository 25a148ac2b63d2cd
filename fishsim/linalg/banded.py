"""Banded Cholesky factorisation of sparse symmetric positive definite matrices (the solid's
Newton and PD matrices, the pressure recovery's Poisson matrix).

The fish is long and thin, so after a reverse Cuthill-McKee reordering its FEM matrices are
narrow bands: the default mesh's 3606 x 3606 Newton matrix has half-bandwidth w = 41 (1.2 ms to
factor on one thread, 2026-11-30). A banded Cholesky K = L L^T costs n w^2 to factor and 4 n w to
solve, against SuperLU's general sparse LU (the former 1181-node mesh, w = 39, one thread: factor
0.84 vs 8.6 ms, solve 0.12 vs 0.57 ms).

The factor and the triangular solves (`factor`, `solve`) are compiled, written once for one
matrix (floats) and for eight of one pattern in the lanes of a SIMD vector (simd.py's
lane-generic operations, chosen by a prototype value `proto`): BandedCholesky runs them on one
matrix, the solid's compiled solver (solid/packed.py) on its packs of eight or one sample, many in
parallel over numba's threads (LAPACK's banded routines called from Python hold the GIL and
cannot be). The band is row-major, L[j, i] = L_{j+i, j} (column j of L from its diagonal down;
LAPACK's lower band storage transposed), padded for the blocked factor: n rounded up to a
multiple of 4 with identity rows, and w + 4 columns, zero past w (BandLayout.rows, .cols). A
matrix that is not positive definite falls back to SuperLU (`spd_factor`).
"""

from __future__ import annotations

from typing import ClassVar

import numba
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import reverse_cuthill_mckee

from fishsim.compiled import jit
from fishsim.linalg.simd import fill, load, mask, multiply_add, select, sqrt, store, width


@jit
def factor(L, w, proto):
    """In place, each lane's band (L[j, i] = K_{j+i, j}, half-bandwidth w) -> its Cholesky factor
    K = L L^T, the diagonal stored as 1 / L_jj (multiplications instead of slow vector
    divisions in the factor and the solves). Returns a lane mask: the matrix was positive
    definite (the other lanes' factors are garbage, but do not disturb the rest).

    Up-looking by blocks of 4 rows: each 4 x 4 tile of the rows' band entries is first reduced
    by the columns left of it (per column k: 4 + 4 loads, 16 fmas, the accumulators in
    registers), then finished by a small triangular solve with its columns' diagonal block (the
    diagonal tile: a 4 x 4 Cholesky). The block's own rows stay in the L1 cache while its tiles
    are done. L [n, C, W] needs n a multiple of 4 (identity rows appended) and C >= w + 4
    columns whose entries beyond w are 0: the tiles read up to 3 entries past a column's band
    (the zeros) rather than branch."""
    n, cols = L.shape[0], L.shape[1]
    band = L.reshape(-1)
    ok = fill(proto, 1.0)
    for r0 in range(0, n, 4):
        for j0 in range(max(0, (r0 - w - 3) // 4 * 4), r0, 4):
            _reduce_tile(band, cols, w, j0, r0, proto)
            _finish_tile(band, cols, w, j0, r0, proto)
        _reduce_tile(band, cols, w, r0, r0, proto)
        ok = ok * _finish_diagonal(band, cols, r0, proto)
    return ok


@jit
def _finish_tile(band, cols, w, j0, r0, proto):
    """L[r, c] = (A[r, c] - sum_{j0 <= k < c} L[r, k] L[c, k]) / L_cc for the tile's rows
    r = r0 + a and columns c = j0 + b < r0 (A: the entry reduced by the columns left of j0): a
    forward substitution per row with the columns' diagonal block. Entries past the band are
    0 and stay 0; a tile reaching past the band's padding takes the guarded path."""
    if r0 - j0 > cols - 4:
        _finish_tile_guarded(band, cols, w, j0, r0, proto)
        return
    W = width(proto)
    d0, d1 = load(band, j0 * cols * W, proto), load(band, (j0 + 1) * cols * W, proto)
    d2, d3 = load(band, (j0 + 2) * cols * W, proto), load(band, (j0 + 3) * cols * W, proto)
    o0, o1, o2 = j0 * cols * W, (j0 + 1) * cols * W, (j0 + 2) * cols * W
    l10, l20, l30 = load(band, o0 + W, proto), load(band, o0 + 2 * W, proto), load(band, o0 + 3 * W, proto)
    l21, l31, l32 = load(band, o1 + W, proto), load(band, o1 + 2 * W, proto), load(band, o2 + W, proto)
    for a in range(4):
        r = r0 + a
        p0 = (j0 * cols + r - j0) * W
        p1 = ((j0 + 1) * cols + r - j0 - 1) * W
        p2 = ((j0 + 2) * cols + r - j0 - 2) * W
        p3 = ((j0 + 3) * cols + r - j0 - 3) * W
        x0 = load(band, p0, proto) * d0
        x1 = (load(band, p1, proto) - x0 * l10) * d1
        x2 = (load(band, p2, proto) - x0 * l20 - x1 * l21) * d2
        x3 = (load(band, p3, proto) - x0 * l30 - x1 * l31 - x2 * l32) * d3
        store(band, p0, x0)
        store(band, p1, x1)
        store(band, p2, x2)
        store(band, p3, x3)


@jit
def _finish_tile_guarded(band, cols, w, j0, r0, proto):
    """_finish_tile entry by entry, skipping entries outside the band."""
    W = width(proto)
    for a in range(4):
        r = r0 + a
        for b in range(4):
            c = j0 + b
            if r - c > w:
                continue
            o = (c * cols + r - c) * W
            s = load(band, o, proto)
            for k in range(j0, c):
                if r - k <= w:
                    s -= load(band, (k * cols + r - k) * W, proto) * load(band, (k * cols + c - k) * W, proto)
            store(band, o, s * load(band, c * cols * W, proto))


@jit
def _finish_diagonal(band, cols, r0, proto):
    """Cholesky of the reduced 4 x 4 diagonal block of rows r0..r0 + 3 (diagonal stored as
    1 / L_jj); returns the lane mask of positive pivots."""
    W = width(proto)
    good = fill(proto, 1.0)
    for b in range(4):
        c = r0 + b
        oc = c * cols * W
        pivot = load(band, oc, proto)
        for k in range(r0, c):
            l_ck = load(band, (k * cols + c - k) * W, proto)
            pivot -= l_ck * l_ck
        positive = mask(pivot > 0.0)
        good = good * positive
        inverse = 1.0 / sqrt(select(positive, pivot, 1.0))
        store(band, oc, inverse)
        for a in range(b + 1, 4):
            r = r0 + a
            o = (c * cols + r - c) * W
            s = load(band, o, proto)
            for k in range(r0, c):
                s -= load(band, (k * cols + r - k) * W, proto) * load(band, (k * cols + c - k) * W, proto)
            store(band, o, s * inverse)
    return good


@jit
def _reduce_tile(band, cols, w, j0, r0, proto):
    """L[r0 + a, j0 + b] -= sum_{k < j0} L[r0 + a, k] L[j0 + b, k] for a, b < 4 (the entries of
    the band only; r0 >= j0, both multiples of 4)."""
    W = width(proto)
    z = fill(proto, 0.0)
    a00, a01, a02, a03, a10, a11, a12, a13 = z, z, z, z, z, z, z, z
    a20, a21, a22, a23, a30, a31, a32, a33 = z, z, z, z, z, z, z, z
    for k in range(max(0, r0 - w), j0):
        row = (k * (cols - 1) + r0) * W                 # L[r0 + a, k] = band[k, r0 + a - k]
        col = (k * (cols - 1) + j0) * W                 # L[j0 + b, k]
        r_0, r_1 = load(band, row, proto), load(band, row + W, proto)
        r_2, r_3 = load(band, row + 2 * W, proto), load(band, row + 3 * W, proto)
        c_0, c_1 = load(band, col, proto), load(band, col + W, proto)
        c_2, c_3 = load(band, col + 2 * W, proto), load(band, col + 3 * W, proto)
        a00, a01 = multiply_add(r_0, c_0, a00), multiply_add(r_0, c_1, a01)
        a02, a03 = multiply_add(r_0, c_2, a02), multiply_add(r_0, c_3, a03)
        a10, a11 = multiply_add(r_1, c_0, a10), multiply_add(r_1, c_1, a11)
        a12, a13 = multiply_add(r_1, c_2, a12), multiply_add(r_1, c_3, a13)
        a20, a21 = multiply_add(r_2, c_0, a20), multiply_add(r_2, c_1, a21)
        a22, a23 = multiply_add(r_2, c_2, a22), multiply_add(r_2, c_3, a23)
        a30, a31 = multiply_add(r_3, c_0, a30), multiply_add(r_3, c_1, a31)
        a32, a33 = multiply_add(r_3, c_2, a32), multiply_add(r_3, c_3, a33)
    _subtract(band, cols, w, r0, j0, a00, a01, a02, a03, proto)
    _subtract(band, cols, w, r0 + 1, j0, a10, a11, a12, a13, proto)
    _subtract(band, cols, w, r0 + 2, j0, a20, a21, a22, a23, proto)
    _subtract(band, cols, w, r0 + 3, j0, a30, a31, a32, a33, proto)


@numba.njit(inline="always")
def _subtract(band, cols, w, r, j0, s0, s1, s2, s3, proto):
    """L[r, j0 + b] -= s_b where (r, j0 + b) is in the band's lower triangle."""
    W = width(proto)
    for b, s in enumerate((s0, s1, s2, s3)):
        offset = r - j0 - b
        if 0 <= offset <= w:
            o = ((j0 + b) * cols + offset) * W
            store(band, o, load(band, o, proto) - s)


@jit
def solve(L, w, perm, inverse, r, z, x, proto):
    """z = K^-1 r per lane (r, z [n W], or any C-contiguous shape of that size, e.g. a pack's
    nodal [N, 2, W]; may be the same array) with factor's band L
    (half-bandwidth w, diagonal 1 / L_jj) under the DOF permutation perm (row k of the band is
    DOF perm[k], inverse = argsort(perm)); x [2N W] scratch. Forward substitution by columns,
    back substitution by dots."""
    W = width(proto)
    n, cols = perm.shape[0], L.shape[1]
    band, r, z = L.reshape(-1), r.reshape(-1), z.reshape(-1)
    for j in range(n):
        store(x, j * W, load(r, perm[j] * W, proto))
    for j in range(n):
        oj = j * cols * W
        xj = load(x, j * W, proto) * load(band, oj, proto)
        store(x, j * W, xj)
        for i in range(1, min(w, n - 1 - j) + 1):
            o = (j + i) * W
            store(x, o, load(x, o, proto) - load(band, oj + i * W, proto) * xj)
    for j in range(n - 1, -1, -1):
        oj = j * cols * W
        s = _band_dot(band, oj, x, j, min(w, n - 1 - j), proto)
        store(x, j * W, (load(x, j * W, proto) - s) * load(band, oj, proto))
    for dof in range(n):
        store(z, dof * W, load(x, inverse[dof] * W, proto))


@numba.njit(inline="always")
def _band_dot(band, oj, x, j, m, proto):
    """sum_{i = 1..m} L[j, i] x[j + i] per lane, in four independent partial sums: one running
    sum chains each multiply-add on the one before (~4 cycles each), and the back substitution,
    whose rows wait on each other, was then one chain n w long (0.20 against 0.11 ms now,
    default fish, one sample)."""
    W = width(proto)
    s0, s1, s2, s3 = fill(proto, 0.0), fill(proto, 0.0), fill(proto, 0.0), fill(proto, 0.0)
    i = 1
    while i + 3 <= m:
        s0 = multiply_add(load(band, oj + i * W, proto), load(x, (j + i) * W, proto), s0)
        s1 = multiply_add(load(band, oj + (i + 1) * W, proto), load(x, (j + i + 1) * W, proto), s1)
        s2 = multiply_add(load(band, oj + (i + 2) * W, proto), load(x, (j + i + 2) * W, proto), s2)
        s3 = multiply_add(load(band, oj + (i + 3) * W, proto), load(x, (j + i + 3) * W, proto), s3)
        i += 4
    while i <= m:
        s0 = multiply_add(load(band, oj + i * W, proto), load(x, (j + i) * W, proto), s0)
        i += 1
    return (s0 + s1) + (s2 + s3)


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
        self.rows, self.cols = -(-n // 4) * 4, self.width + 4               # the padded band

    @classmethod
    def ordered(cls, perm: np.ndarray, inverse: np.ndarray, width: int) -> BandLayout:
        """The layout of a band its caller assembled itself (row k is row perm[k] of K, inverse =
        argsort(perm), half-bandwidth ``width``): what the solves need; without the CSR entries'
        places (``band`` is not available)."""
        layout = cls.__new__(cls)
        layout.perm, layout.inverse, layout.width = perm, inverse, int(width)
        layout.lower = layout.column = layout.offset = None
        layout.rows, layout.cols = -(-len(perm) // 4) * 4, layout.width + 4
        return layout

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
        """The padded band [rows, cols] of the matrix with the values ``data`` (in its CSR/CSC
        order), identity rows past n."""
        L = np.zeros((self.rows, self.cols))
        L[self.column, self.offset] = data[self.lower]
        L[len(self.perm):, 0] = 1.0
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
        return cls(layout, L) if factor(L, layout.width, 0.0) > 0 else None

    def solve(self, b: np.ndarray) -> np.ndarray:
        """K^-1 b for b [n] or [n, k]."""
        layout, b = self.layout, np.asarray(b, np.float64)
        columns = b.reshape(len(b), -1).T.copy()                   # [k, n], each column contiguous
        x = np.empty(len(b))
        for column in columns:
            solve(self.factor, layout.width, layout.perm, layout.inverse, column, column, x, 0.0)
        return columns.T.reshape(b.shape)


def lu_factor(K: sp.spmatrix):
    """SuperLU (symmetric mode) of the symmetric matrix K, for one that is not positive definite."""
    return spla.splu(K.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                     options={"SymmetricMode": True})


def spd_factor(K: sp.spmatrix):
    """A solver with ``.solve(b)`` for the symmetric matrix K: banded Cholesky when K is positive
    definite, else SuperLU (lu_factor)."""
    return BandedCholesky.of(K) or lu_factor(K)
