"""Lane-packed (SIMD) kernels of the PD solve: LANES = 8 samples per pack, in lock step, one
sample per lane of an 8 x float64 vector (one AVX-512 register; two AVX2 ones elsewhere).

A fish's solve is a long chain of small dependent operations (an element's 2 x 2 matrices, a
band row's 40 entries), which one sample alone cannot fill a vector unit with; eight samples of
the same mesh do exactly the same operations on different numbers, so each scalar operation of
kernels.py becomes one vector operation here. Arrays of a pack put the lane index last:
positions and forces [N, 2, LANES], the Newton band [rows, w + 4, LANES] (PackBand), per-element
weights [T, LANES]; one (vload) load reads an entry of all eight samples.

The vector is simd.py's `Vec` (one LLVM <8 x double> value); the element physics is
element.py's, the same code as the per-sample kernels'.

Kernels (each a pack, prange over packs): `lbfgs_packs`, the whole forward solve of kernels.py's
_lbfgs_sample for eight samples at a time, factorising each lane's Newton matrix at the start of
every step; `newton_solve_packs`, the adjoint's direct solve. Per lane the arithmetic is the
scalar kernels' up to round-off (the factor is computed in another order and keeps 1 / L_jj on
its diagonal), and a lane's results do not depend on the other lanes: a lane that fails
(indefinite matrix, NaN) is flagged alone.
"""

from __future__ import annotations

import numba
import numpy as np

from fishsim.compiled import jit
from fishsim.solid import element
from fishsim.solid.simd import LANES, count, fma, isnan, lane, splat, vabs, vload, vmax, vsqrt, vstore, where

# ---------------------------------------------------------------------------------------------
# Kernels on one pack. Arrays of a pack are C-contiguous with the lane index last and are
# indexed flat: entry (2 i + a) of a nodal array [N, 2, LANES] starts at (2 i + a) LANES.


@jit
def _deformation_gradient(X, triangles, grad, e):
    """F of element e from the pack's positions X: (F00, F01, F10, F11), Vecs."""
    k0, k1, k2 = triangles[e, 0], triangles[e, 1], triangles[e, 2]
    x0, y0 = vload(X, 2 * k0 * LANES), vload(X, (2 * k0 + 1) * LANES)
    x1, y1 = vload(X, 2 * k1 * LANES), vload(X, (2 * k1 + 1) * LANES)
    x2, y2 = vload(X, 2 * k2 * LANES), vload(X, (2 * k2 + 1) * LANES)
    return element.deformation_gradient(x0, y0, x1, y1, x2, y2, grad, e)


@jit
def _objective(X, Y, mass_h2, triangles, grad, w_corotated, muscle_of, w_muscle, stretch, g):
    """Phi of each lane (a Vec, J per unit depth), writing grad Phi into g: kernels'
    _objective_sample on a pack. X, Y, g [N, 2, LANES]; w_corotated [T, LANES]; stretch
    [n_act, LANES]; the other arrays as in kernels.objective."""
    phi = splat(0.0)
    for i in range(X.shape[0]):
        for a in range(2):
            o = (2 * i + a) * LANES
            d = vload(X, o) - vload(Y, o)
            vstore(g, o, mass_h2[i] * d)
            phi += 0.5 * mass_h2[i] * d * d
    for e in range(triangles.shape[0]):
        F00, F01, F10, F11 = _deformation_gradient(X, triangles, grad, e)
        psi, S00, S01, S10, S11 = element.corotated_stress(F00, F01, F10, F11, vload(w_corotated, e * LANES))
        phi += psi
        m = muscle_of[e]
        if m >= 0:
            psi, M00, M10 = element.muscle_stress(F00, F10, vload(stretch, m * LANES), w_muscle[m])
            phi += psi
            S00 += M00
            S10 += M10
        for k in range(3):                                          # dE/dx_ka = sum_j S_aj g_kj
            o = 2 * triangles[e, k] * LANES
            vstore(g, o, vload(g, o) + (S00 * grad[e, k, 0] + S01 * grad[e, k, 1]))
            vstore(g, o + LANES, vload(g, o + LANES) + (S10 * grad[e, k, 0] + S11 * grad[e, k, 1]))
    return phi


@jit
def _newton_band(X, triangles, grad, w_corotated, muscle_of, w_muscle, stretch, projected, slot, diagonal,
                 diagonal_values, L, H):
    """Each lane's Newton matrix M/h^2 + sum_e G_e^T H_e G_e at X, assembled into the band L
    [n, w + 1, LANES] (kernels._newton_factor's assembly with kernels._element_newton's element
    matrices; the projections are computed here from X). `projected` (a lane mask) clamps c and
    |F m| as elastic.stress_differential does; slot, diagonal, diagonal_values: PackBand's;
    H [4 * 4 * LANES] scratch."""
    band = L.reshape(-1)
    band[:] = 0.0
    for i in range(diagonal.shape[0]):
        o = diagonal[i] * LANES
        vstore(band, o, vload(band, o) + diagonal_values[i])
    zero = splat(0.0)
    for e in range(triangles.shape[0]):
        F00, F01, F10, F11 = _deformation_gradient(X, triangles, grad, e)
        alpha, beta, _, _ = element.conformal(F00, F01, F10, F11)
        alpha_R, beta_R, c = element.rotation(alpha, beta)
        ce = element.clamped(c, 1.0, projected)
        w = vload(w_corotated, e * LANES)
        m = muscle_of[e]
        n0, n1, length, a_m, w_m = zero, zero, zero, zero, 0.0
        if m >= 0:
            length = element.fiber_length(F00, F10)
            n0, n1 = F00 / length, F10 / length
            a_m = vload(stretch, m * LANES)
            length = element.clamped(length, a_m, projected)
            w_m = w_muscle[m]
        for col in range(4):                                        # unit dF_aj, col = 2a + j
            S00, S01, S10, S11 = element.corotated_differential(col, alpha_R, beta_R, ce, w)
            if m >= 0:
                M00, M10 = element.muscle_differential(col, n0, n1, length, a_m, w_m)
                S00 += M00
                S10 += M10
            vstore(H, col * LANES, S00)
            vstore(H, (4 + col) * LANES, S01)
            vstore(H, (8 + col) * LANES, S10)
            vstore(H, (12 + col) * LANES, S11)
        for r in range(6):                  # Ke[2k+a, 2l+b] = sum_ji g_kj H[2a+j, 2b+i] g_li
            k, a = r // 2, r % 2
            for s in range(6):
                if slot[e, r, s] >= 0:
                    l, b = s // 2, s % 2
                    total = zero
                    for j in range(2):
                        for i in range(2):
                            total += grad[e, k, j] * vload(H, ((2 * a + j) * 4 + 2 * b + i) * LANES) * grad[e, l, i]
                    o = slot[e, r, s] * LANES
                    vstore(band, o, vload(band, o) + total)


@jit
def _factor(L, w):
    """In place, each lane's band (L[j, i] = K_{j+i, j}, half-bandwidth w) -> its Cholesky factor
    K = L L^T, the diagonal stored as 1 / L_jj (multiplications instead of slow vector
    divisions in the factor and the solves). Returns a lane mask: the matrix was positive definite (the other lanes' factors
    are garbage, but do not disturb the rest).

    Up-looking by blocks of 4 rows: each 4 x 4 tile of the rows' band entries is first reduced
    by the columns left of it (per column k: 4 + 4 loads, 16 fmas, the accumulators in
    registers), then finished by a small triangular solve with its columns' diagonal block (the
    diagonal tile: a 4 x 4 Cholesky). The block's own rows (11 kB) stay in the L1 cache while
    its tiles are done. L [n, W, LANES] needs n a multiple of 4 (identity rows appended) and
    W >= w + 4 columns whose entries beyond w are 0: the tiles read up to 3 entries past a
    column's band (the zeros) rather than branch."""
    n, width = L.shape[0], L.shape[1]
    band = L.reshape(-1)
    ok = splat(1.0)
    for r0 in range(0, n, 4):
        for j0 in range(max(0, (r0 - w - 3) // 4 * 4), r0, 4):
            _reduce_tile(band, width, w, j0, r0)
            _finish_tile(band, width, w, j0, r0)
        _reduce_tile(band, width, w, r0, r0)
        ok = ok * _finish_diagonal(band, width, r0)
    return ok


@jit
def _finish_tile(band, width, w, j0, r0):
    """L[r, c] = (A[r, c] - sum_{j0 <= k < c} L[r, k] L[c, k]) / L_cc for the tile's rows
    r = r0 + a and columns c = j0 + b < r0 (A: the entry reduced by the columns left of j0): a
    forward substitution per row with the columns' diagonal block. Entries past the band are
    0 and stay 0; a tile reaching past the band's padding takes the guarded path."""
    if r0 - j0 > width - 4:
        _finish_tile_guarded(band, width, w, j0, r0)
        return
    d0, d1 = vload(band, j0 * width * LANES), vload(band, (j0 + 1) * width * LANES)
    d2, d3 = vload(band, (j0 + 2) * width * LANES), vload(band, (j0 + 3) * width * LANES)
    o0, o1, o2 = j0 * width * LANES, (j0 + 1) * width * LANES, (j0 + 2) * width * LANES
    l10, l20, l30 = vload(band, o0 + LANES), vload(band, o0 + 2 * LANES), vload(band, o0 + 3 * LANES)
    l21, l31, l32 = vload(band, o1 + LANES), vload(band, o1 + 2 * LANES), vload(band, o2 + LANES)
    for a in range(4):
        r = r0 + a
        p0 = (j0 * width + r - j0) * LANES
        p1 = ((j0 + 1) * width + r - j0 - 1) * LANES
        p2 = ((j0 + 2) * width + r - j0 - 2) * LANES
        p3 = ((j0 + 3) * width + r - j0 - 3) * LANES
        x0 = vload(band, p0) * d0
        x1 = (vload(band, p1) - x0 * l10) * d1
        x2 = (vload(band, p2) - x0 * l20 - x1 * l21) * d2
        x3 = (vload(band, p3) - x0 * l30 - x1 * l31 - x2 * l32) * d3
        vstore(band, p0, x0)
        vstore(band, p1, x1)
        vstore(band, p2, x2)
        vstore(band, p3, x3)


@jit
def _finish_tile_guarded(band, width, w, j0, r0):
    """_finish_tile entry by entry, skipping entries outside the band."""
    for a in range(4):
        r = r0 + a
        for b in range(4):
            c = j0 + b
            if r - c > w:
                continue
            o = (c * width + r - c) * LANES
            s = vload(band, o)
            for k in range(j0, c):
                if r - k <= w:
                    s -= vload(band, (k * width + r - k) * LANES) * vload(band, (k * width + c - k) * LANES)
            vstore(band, o, s * vload(band, c * width * LANES))


@jit
def _finish_diagonal(band, width, r0):
    """Cholesky of the reduced 4 x 4 diagonal block of rows r0..r0 + 3 (diagonal stored as
    1 / L_jj); returns the lane mask of positive pivots."""
    good = splat(1.0)
    for b in range(4):
        c = r0 + b
        oc = c * width * LANES
        pivot = vload(band, oc)
        for k in range(r0, c):
            l_ck = vload(band, (k * width + c - k) * LANES)
            pivot -= l_ck * l_ck
        positive = pivot > 0.0
        good = good * positive
        inverse = 1.0 / vsqrt(where(positive, pivot, 1.0))
        vstore(band, oc, inverse)
        for a in range(b + 1, 4):
            r = r0 + a
            o = (c * width + r - c) * LANES
            s = vload(band, o)
            for k in range(r0, c):
                s -= vload(band, (k * width + r - k) * LANES) * vload(band, (k * width + c - k) * LANES)
            vstore(band, o, s * inverse)
    return good


@jit
def _reduce_tile(band, width, w, j0, r0):
    """L[r0 + a, j0 + b] -= sum_{k < j0} L[r0 + a, k] L[j0 + b, k] for a, b < 4 (the entries of
    the band only; r0 >= j0, both multiples of 4)."""
    z = splat(0.0)
    a00, a01, a02, a03, a10, a11, a12, a13 = z, z, z, z, z, z, z, z
    a20, a21, a22, a23, a30, a31, a32, a33 = z, z, z, z, z, z, z, z
    for k in range(max(0, r0 - w), j0):
        row = (k * (width - 1) + r0) * LANES            # L[r0 + a, k] = band[k, r0 + a - k]
        col = (k * (width - 1) + j0) * LANES            # L[j0 + b, k]
        r_0, r_1 = vload(band, row), vload(band, row + LANES)
        r_2, r_3 = vload(band, row + 2 * LANES), vload(band, row + 3 * LANES)
        c_0, c_1 = vload(band, col), vload(band, col + LANES)
        c_2, c_3 = vload(band, col + 2 * LANES), vload(band, col + 3 * LANES)
        a00, a01, a02, a03 = fma(r_0, c_0, a00), fma(r_0, c_1, a01), fma(r_0, c_2, a02), fma(r_0, c_3, a03)
        a10, a11, a12, a13 = fma(r_1, c_0, a10), fma(r_1, c_1, a11), fma(r_1, c_2, a12), fma(r_1, c_3, a13)
        a20, a21, a22, a23 = fma(r_2, c_0, a20), fma(r_2, c_1, a21), fma(r_2, c_2, a22), fma(r_2, c_3, a23)
        a30, a31, a32, a33 = fma(r_3, c_0, a30), fma(r_3, c_1, a31), fma(r_3, c_2, a32), fma(r_3, c_3, a33)
    _subtract(band, width, w, r0, j0, a00, a01, a02, a03)
    _subtract(band, width, w, r0 + 1, j0, a10, a11, a12, a13)
    _subtract(band, width, w, r0 + 2, j0, a20, a21, a22, a23)
    _subtract(band, width, w, r0 + 3, j0, a30, a31, a32, a33)


@numba.njit(inline="always")
def _subtract(band, width, w, r, j0, s0, s1, s2, s3):
    """L[r, j0 + b] -= s_b where (r, j0 + b) is in the band's lower triangle."""
    for b, s in enumerate((s0, s1, s2, s3)):
        offset = r - j0 - b
        if 0 <= offset <= w:
            o = ((j0 + b) * width + offset) * LANES
            vstore(band, o, vload(band, o) - s)


@jit
def _solve(L, w, perm, inverse, r, z, x):
    """z = K^-1 r per lane (r, z [N, 2, LANES], may be the same array) with _factor's band L
    (half-bandwidth w, diagonal 1 / L_jj) under the DOF permutation perm
    (kernels._solve_sample); x [2N * LANES] scratch."""
    n, width = perm.shape[0], L.shape[1]
    band, r, z = L.reshape(-1), r.reshape(-1), z.reshape(-1)
    for j in range(n):
        vstore(x, j * LANES, vload(r, perm[j] * LANES))
    for j in range(n):                                              # forward, by columns
        oj = j * width * LANES
        xj = vload(x, j * LANES) * vload(band, oj)
        vstore(x, j * LANES, xj)
        for i in range(1, min(w, n - 1 - j) + 1):
            o = (j + i) * LANES
            vstore(x, o, vload(x, o) - vload(band, oj + i * LANES) * xj)
    for j in range(n - 1, -1, -1):                                  # back, by dots
        oj = j * width * LANES
        s = vload(x, j * LANES)
        for i in range(1, min(w, n - 1 - j) + 1):
            s -= vload(band, oj + i * LANES) * vload(x, (j + i) * LANES)
        vstore(x, j * LANES, s * vload(band, oj))
    for dof in range(n):
        vstore(z, dof * LANES, vload(x, inverse[dof] * LANES))


@jit
def _dot(u, v):
    """Per-lane inner product (a Vec) of two flat pack arrays, summed in index order."""
    total = splat(0.0)
    for o in range(0, u.shape[0], LANES):
        total += vload(u, o) * vload(v, o)
    return total


@jit
def _max_nodal_norm(g):
    """Per lane max_i |g_i| of a pack's [N, 2, LANES] nodal vectors; NaN in a lane with a NaN."""
    largest, nan = splat(0.0), splat(0.0)
    for i in range(g.shape[0]):
        gx, gy = vload(g, 2 * i * LANES), vload(g, (2 * i + 1) * LANES)
        norm = vsqrt(gx * gx + gy * gy)
        largest, nan = vmax(largest, norm), vmax(nan, isnan(norm))
    return where(nan, np.nan, largest)


@jit
def _lbfgs_pack(X, Y, mass_h2, triangles, grad, w_corotated, muscle_of, w_muscle, stretch, slot, diagonal,
                diagonal_values, w, perm, inverse, L, atol, max_iter, m, g, iterations, ok):
    """The forward solve of a pack, in place on X [N, 2, LANES] (to the minimiser of each lane's
    Phi; g receives grad Phi there): each lane's Newton matrix at the start X is factorised (the
    exact one, else the projected one; ok [LANES] = one was positive definite, else the lane
    does not move), then kernels._lbfgs_sample's L-BFGS runs on all lanes in lock step. A lane
    stops (its direction becomes 0) once its residual is <= atol; it and lanes still searching
    keep their own step lengths. iterations [LANES] receives each lane's iterations."""
    c1, round_off = 1e-4, 64 * np.finfo(np.float64).eps
    H = np.empty(16 * LANES)
    lanes_ok = _factor_newton(X, triangles, grad, w_corotated, muscle_of, w_muscle, stretch, slot, diagonal,
                              diagonal_values, w, L, H)
    size = X.size
    Xf, gf = X.reshape(-1), g.reshape(-1)
    S, Yp = np.zeros((m, size)), np.zeros((m, size))                # pairs s, y; ring of m
    rho, alphas = np.zeros((m, LANES)), np.zeros((m, LANES))
    d, X_new, g_new, x = np.empty(size), np.empty(size), np.empty(size), np.empty(size)
    Xn, gn, dn = X_new.reshape(X.shape), g_new.reshape(X.shape), d.reshape(X.shape)
    phi = _objective(X, Y, mass_h2, triangles, grad, w_corotated, muscle_of, w_muscle, stretch, g)
    taken = splat(0.0)
    count_, head = 0, 0
    for _ in range(max_iter):
        active = lanes_ok * (_max_nodal_norm(g) > atol)
        if count(active) == 0:
            break
        taken += active
        d[:] = gf                                                   # d = -H g, two-loop recursion
        for k in range(count_):
            h = (head - 1 - k) % m
            alpha = vload(rho, h * LANES) * _dot(S[h], d)
            vstore(alphas, k * LANES, alpha)
            for o in range(0, size, LANES):
                vstore(d, o, vload(d, o) - alpha * vload(Yp[h], o))
        _solve(L, w, perm, inverse, dn, dn, x)
        for k in range(count_ - 1, -1, -1):
            h = (head - 1 - k) % m
            coefficient = vload(alphas, k * LANES) - vload(rho, h * LANES) * _dot(Yp[h], d)
            for o in range(0, size, LANES):
                vstore(d, o, vload(d, o) + coefficient * vload(S[h], o))
        for o in range(0, size, LANES):
            vstore(d, o, vload(d, o) * -active)
        slope = _dot(gf, d)
        uphill = active * (slope >= 0.0)
        if count(uphill) > 0:                                       # not a descent direction: restart
            for h in range(m):
                vstore(rho, h * LANES, vload(rho, h * LANES) * (1.0 - uphill))
            _solve(L, w, perm, inverse, g, gn, x)
            for o in range(0, size, LANES):
                vstore(d, o, where(uphill, -vload(g_new, o), vload(d, o)))
            slope = _dot(gf, d)
        t, accepted = splat(1.0), 1.0 - active                      # Armijo backtracking per lane
        for halvings in range(31):
            if halvings:
                t = where(accepted, t, t * 0.5)
            for o in range(0, size, LANES):
                vstore(X_new, o, vload(Xf, o) + t * vload(d, o))
            phi_new = _objective(Xn, Y, mass_h2, triangles, grad, w_corotated, muscle_of, w_muscle, stretch, gn)
            accepted = vmax(accepted, phi_new - phi <= c1 * t * slope + round_off * vabs(phi))
            if count(accepted) == LANES:
                break
        for o in range(0, size, LANES):                             # history: s, y, rho = 1 / s.y
            vstore(S[head], o, vload(X_new, o) - vload(Xf, o))
            vstore(Yp[head], o, vload(g_new, o) - vload(gf, o))
        sy = _dot(S[head], Yp[head])
        vstore(rho, head * LANES, where(sy > 1e-300, 1.0 / sy, 0.0))
        head, count_ = (head + 1) % m, min(count_ + 1, m)
        Xf[:] = X_new
        gf[:] = g_new
        phi = phi_new
    for k in range(LANES):
        iterations[k] = lane(taken, k)
        ok[k] = lane(lanes_ok, k) > 0


@jit
def _factor_newton(X, triangles, grad, w_corotated, muscle_of, w_muscle, stretch, slot, diagonal,
                   diagonal_values, w, L, H):
    """Each lane's Newton matrix at X assembled into L and factorised: the exact one, else (in
    lanes where it is indefinite) the projected one. Returns the lanes with a factor."""
    _newton_band(X, triangles, grad, w_corotated, muscle_of, w_muscle, stretch, splat(0.0), slot, diagonal,
                 diagonal_values, L, H)
    ok = _factor(L, w)
    if count(ok) < LANES:
        _newton_band(X, triangles, grad, w_corotated, muscle_of, w_muscle, stretch, 1.0 - ok, slot, diagonal,
                     diagonal_values, L, H)
        ok = _factor(L, w)
    return ok


@jit(parallel=True)
def lbfgs_packs(X, Y, phi_args, band, L, atol, max_iter, m, g, iterations, ok):
    """The forward solve of every pack p (in parallel): _lbfgs_pack on X[p], Y[p], g[p]
    ([P, N, 2, LANES]) with the band L[p] [P, n, w + 1, LANES]; iterations, ok [P, LANES].
    phi_args = (mass_h2, triangles, grad, w_corotated [P, T, LANES], muscle_of, w_muscle,
    stretch [P, n_act, LANES]) as in kernels.objective; band: PackBand.arrays."""
    mass_h2, triangles, grad, w_corotated, muscle_of, w_muscle, stretch = phi_args
    slot, diagonal, diagonal_values, w, perm, inverse = band
    for p in numba.prange(X.shape[0]):
        _lbfgs_pack(X[p], Y[p], mass_h2, triangles, grad, w_corotated[p], muscle_of, w_muscle, stretch[p], slot,
                    diagonal, diagonal_values, w, perm, inverse, L[p], atol, max_iter, m, g[p], iterations[p], ok[p])


@jit(parallel=True)
def newton_solve_packs(X, R, phi_args, band, L, Z, ok):
    """Z[p] = K^-1 R[p] per lane ([P, N, 2, LANES]) with K the exact Newton matrix at X[p], for
    every pack p in parallel; ok [P, LANES] = K was positive definite (else Z is garbage).
    phi_args as in lbfgs_packs (its mass_h2 unused); band: PackBand.arrays."""
    _, triangles, grad, w_corotated, muscle_of, w_muscle, stretch = phi_args
    slot, diagonal, diagonal_values, w, perm, inverse = band
    for p in numba.prange(X.shape[0]):
        H, x = np.empty(16 * LANES), np.empty(R[p].size)
        _newton_band(X[p], triangles, grad, w_corotated[p], muscle_of, w_muscle, stretch[p], splat(0.0), slot,
                     diagonal, diagonal_values, L[p], H)
        lanes_ok = _factor(L[p], w)
        _solve(L[p], w, perm, inverse, R[p], Z[p], x)
        for k in range(LANES):
            ok[p, k] = lane(lanes_ok, k) > 0


class PackBand:
    """The Newton band of a pack for the mesh's band layout (fem.NewtonBand) and nodal masses:
    rows padded to a multiple of 4 with identity rows, width w + 4 with zeros past w (as _factor
    needs). slot [T, 6, 6] and diagonal [rows]: flat indices (of one lane) of the element
    entries and of every row's diagonal, which starts at diagonal_values (M/h^2 per DOF, 1 for
    the padding)."""

    def __init__(self, newton_band, mass_diag: np.ndarray):
        layout = newton_band.layout
        self.w, n = layout.width, len(layout.perm)
        self.rows, self.width = -(-n // 4) * 4, self.w + 4

        def widened(flat: np.ndarray) -> np.ndarray:
            column, offset = np.divmod(flat, self.w + 1)
            return np.where(flat >= 0, column * self.width + offset, -1)

        self.slot = np.ascontiguousarray(widened(newton_band.slot))
        self.diagonal = np.concatenate([widened(newton_band.diagonal), np.arange(n, self.rows) * self.width])
        self.diagonal_values = np.concatenate([mass_diag, np.ones(self.rows - n)])
        self.arrays = (self.slot, self.diagonal, self.diagonal_values, self.w, layout.perm, layout.inverse)
        self._room = None

    def empty(self, packs: int) -> np.ndarray:
        """Room for the factors of `packs` packs, [packs, rows, width, LANES], 64-byte aligned
        (one vector per cache line). The room is kept and reused by the next call (so a step
        does not fault in ~6 MB of fresh pages per pack): a caller's factors live until then."""
        if self._room is None or len(self._room) < packs:
            self._room = aligned_empty((packs, self.rows, self.width, LANES))
        return self._room[:packs]


def aligned_empty(shape: tuple) -> np.ndarray:
    """np.empty(shape) of float64 starting on a 64-byte boundary."""
    size = int(np.prod(shape))
    buffer = np.empty(size + LANES)
    start = (-buffer.ctypes.data % 64) // 8
    return buffer[start:start + size].reshape(shape)
