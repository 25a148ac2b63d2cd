"""Compiled kernels of the PD solve on packs of W samples in lock step, written once for both
widths: W = LANES = 8 samples in the lanes of an 8 x float64 vector (simd.Vec: one AVX-512
register, two AVX2 ones elsewhere), or W = 1, one sample in plain floats.

A fish's solve is a long chain of small dependent operations (an element's 2 x 2 matrices, a
band row's 40 entries), which one sample alone cannot fill a vector unit with; eight samples of
the same mesh do exactly the same operations on different numbers, so each scalar operation
becomes one vector operation. Arrays of a pack put the lane index last: positions and forces
[N, 2, W], the Newton band [rows, w + 4, W] (PackBand), per-element weights [T, W]; one load
reads an entry of all W samples, and at W = 1 they are a sample's own arrays ([N, 2], ...).
Every function takes a prototype value `proto` (0.0 or a Vec; W = simd.width(proto)) and works
through simd's lane-generic load / store / fill / mask / select, so it compiles for either width.
The element physics is element.py's.

Entry points, each a prange over the packs p listed in `packs`; each compiles for W = 8 when its
nodal arrays are [P, N, 2, LANES] and for W = 1 when they are [B, N, 2] (prototype):
- objective: Phi of each lane and grad Phi;
- factor: each lane's Newton matrix at X assembled into its band and Cholesky-factorised (the
  exact matrix, else, in lanes where it is indefinite, the projected one);
- solve: z = K^-1 r with such factors;
- newton_solve: the adjoint's direct solve (the exact matrix at X factorised, then solved);
- lbfgs: the whole forward solve, L-BFGS with the Newton factor as H0, refactorising first the
  packs marked stale (solve.py: packs of 8 refactorise every step; single samples keep their
  lagged factor until it gets slow).
A lane's arithmetic does not depend on the other lanes: a lane that fails (indefinite matrix,
NaN) is flagged alone. The two widths agree up to round-off (the dot products' order).
"""

from __future__ import annotations

import threading

import numba
import numpy as np
from numba.extending import overload

from fishsim.compiled import jit
from fishsim.linalg import banded
from fishsim.linalg.simd import (
    LANES,
    absolute,
    fill,
    lanes_set,
    load,
    mask,
    maximum,
    nan_mask,
    select,
    splat,
    sqrt,
    store,
    width,
)
from fishsim.solid import element

# The forward line search's tests (solve._line_search documents them): Armijo's c1 and the
# round-off slack on Phi, the approximate Wolfe test's sigma and its bound on Phi's relative rise.
ARMIJO_C1, PHI_ROUND_OFF, WOLFE_SIGMA, WOLFE_FLAT = 1e-4, 64 * np.finfo(np.float64).eps, 0.9, 1e-10


def prototype(X):
    """The lane prototype of packs whose nodal array is X: a Vec for [P, N, 2, LANES] (compiled
    code only), 0.0 for one sample per pack, [B, N, 2]."""
    return 0.0


@overload(prototype)
def _prototype(X):
    if X.ndim == 4:
        return lambda X: splat(0.0)
    return lambda X: 0.0


# ---------------------------------------------------------------------------------------------
# Kernels on one pack. Its arrays are C-contiguous with the lane index last and are indexed
# flat: entry (2 i + a) of a nodal array [N, 2, W] starts at (2 i + a) W.


@jit
def _deformation_gradient(X, triangles, grad, e, proto):
    """F of element e from the pack's positions X: (F00, F01, F10, F11), like proto."""
    W = width(proto)
    k0, k1, k2 = triangles[e, 0], triangles[e, 1], triangles[e, 2]
    x0, y0 = load(X, 2 * k0 * W, proto), load(X, (2 * k0 + 1) * W, proto)
    x1, y1 = load(X, 2 * k1 * W, proto), load(X, (2 * k1 + 1) * W, proto)
    x2, y2 = load(X, 2 * k2 * W, proto), load(X, (2 * k2 + 1) * W, proto)
    return element.deformation_gradient(x0, y0, x1, y1, x2, y2, grad, e)


@jit
def _objective(X, Y, mass_h2, triangles, grad, w_corotated, w_volume, muscle_of, w_muscle, stretch, g, proto):
    """Phi of each lane (J per unit depth), writing grad Phi into g (module doc of solve.py):

        Phi(X) = 1/(2 h^2) ||X - Y||_M^2 + E_int(X),   grad Phi = M/h^2 (X - Y) + G^T S(X).

    X, Y, g [N, 2, W]; mass_h2 [N] = m_i / h^2; triangles [T, 3]; grad [T, 3, 2] shape-function
    gradients; w_corotated [T, W] = area 2 mu_s(E); w_volume [T, W] = area lambda_s(E), DiffPD's
    volume term ([0, W]: none); muscle_of [T] muscle index or -1; w_muscle [n_act] = k_m area
    fraction; stretch [n_act, W] = 1 - contraction."""
    W = width(proto)
    phi = fill(proto, 0.0)
    for i in range(X.shape[0]):
        for a in range(2):
            o = (2 * i + a) * W
            d = load(X, o, proto) - load(Y, o, proto)
            store(g, o, mass_h2[i] * d)
            phi += 0.5 * mass_h2[i] * d * d
    for e in range(triangles.shape[0]):
        F00, F01, F10, F11 = _deformation_gradient(X, triangles, grad, e, proto)
        psi, S00, S01, S10, S11 = element.corotated_stress(F00, F01, F10, F11, load(w_corotated, e * W, proto))
        phi += psi
        if w_volume.shape[0]:
            psi, V00, V01, V10, V11 = element.volume_stress(F00, F01, F10, F11, load(w_volume, e * W, proto))
            phi += psi
            S00, S01, S10, S11 = S00 + V00, S01 + V01, S10 + V10, S11 + V11
        m = muscle_of[e]
        if m >= 0:
            psi, M00, M10 = element.muscle_stress(F00, F10, load(stretch, m * W, proto), w_muscle[m])
            phi += psi
            S00 += M00
            S10 += M10
        for k in range(3):                                          # dE/dx_ka = sum_j S_aj g_kj
            o = 2 * triangles[e, k] * W
            store(g, o, load(g, o, proto) + (S00 * grad[e, k, 0] + S01 * grad[e, k, 1]))
            store(g, o + W, load(g, o + W, proto) + (S10 * grad[e, k, 0] + S11 * grad[e, k, 1]))
    return phi


@jit
def _newton_band(X, triangles, grad, w_corotated, w_volume, muscle_of, w_muscle, stretch, projected, slot,
                 diagonal, diagonal_values, L, H, proto):
    """Each lane's Newton matrix M/h^2 + sum_e G_e^T H_e G_e at X (H_e = d vec(S) / d vec(F) of
    the co-rotated, volume and muscle stresses, element.py) assembled into the band L
    [rows, w + 4, W]. `projected` (a lane mask) clamps c and |F m| and takes the volume term's
    Gauss-Newton part, as elastic.stress_differential does; slot,
    diagonal, diagonal_values: PackBand's; H [16 W] scratch."""
    W = width(proto)
    band = L.reshape(-1)
    band[:] = 0.0
    for i in range(diagonal.shape[0]):
        o = diagonal[i] * W
        store(band, o, load(band, o, proto) + diagonal_values[i])
    zero = fill(proto, 0.0)
    for e in range(triangles.shape[0]):
        F00, F01, F10, F11 = _deformation_gradient(X, triangles, grad, e, proto)
        alpha, beta, gamma, delta = element.conformal(F00, F01, F10, F11)
        alpha_R, beta_R, c = element.rotation(alpha, beta)
        ce = element.clamped(c, 1.0, projected)
        w = load(w_corotated, e * W, proto)
        volume = w_volume.shape[0] > 0
        w_v, t = zero, zero
        if volume:
            w_v = load(w_volume, e * W, proto)
            t = element.volume_multiplier(alpha * alpha + beta * beta, gamma * gamma + delta * delta)
        m = muscle_of[e]
        n0, n1, length, a_m, w_m = zero, zero, zero, zero, 0.0
        if m >= 0:
            length = element.fiber_length(F00, F10)
            n0, n1 = F00 / length, F10 / length
            a_m = load(stretch, m * W, proto)
            length = element.clamped(length, a_m, projected)
            w_m = w_muscle[m]
        for col in range(4):                                        # unit dF_aj, col = 2a + j
            S00, S01, S10, S11 = element.corotated_differential(col, alpha_R, beta_R, ce, w)
            if volume:
                V00, V01, V10, V11 = element.volume_differential(col, alpha, beta, gamma, delta, t, w_v, projected)
                S00, S01, S10, S11 = S00 + V00, S01 + V01, S10 + V10, S11 + V11
            if m >= 0:
                M00, M10 = element.muscle_differential(col, n0, n1, length, a_m, w_m)
                S00 += M00
                S10 += M10
            store(H, col * W, S00)
            store(H, (4 + col) * W, S01)
            store(H, (8 + col) * W, S10)
            store(H, (12 + col) * W, S11)
        for r in range(6):                  # Ke[2k+a, 2l+b] = sum_ji g_kj H[2a+j, 2b+i] g_li
            k, a = r // 2, r % 2
            for s in range(6):
                if slot[e, r, s] >= 0:
                    l, b = s // 2, s % 2
                    total = zero
                    for j in range(2):
                        for i in range(2):
                            total += grad[e, k, j] * load(H, ((2 * a + j) * 4 + 2 * b + i) * W, proto) * grad[e, l, i]
                    o = slot[e, r, s] * W
                    store(band, o, load(band, o, proto) + total)


@jit
def _dot(u, v, proto):
    """Per-lane inner product of two flat pack arrays, summed in index order."""
    W = width(proto)
    total = fill(proto, 0.0)
    for o in range(0, u.shape[0], W):
        total += load(u, o, proto) * load(v, o, proto)
    return total


@jit
def _max_nodal_norm(g, proto):
    """Per lane max_i |g_i| of a pack's [N, 2, W] nodal vectors; NaN in a lane with a NaN (a
    blown-up sample then stops iterating)."""
    W = width(proto)
    largest, nan = fill(proto, 0.0), fill(proto, 0.0)
    for i in range(g.shape[0]):
        gx, gy = load(g, 2 * i * W, proto), load(g, (2 * i + 1) * W, proto)
        norm = sqrt(gx * gx + gy * gy)
        largest, nan = maximum(largest, norm), maximum(nan, nan_mask(norm))
    return select(nan, np.nan, largest)


@jit
def _factor_newton(X, triangles, grad, w_corotated, w_volume, muscle_of, w_muscle, stretch, slot, diagonal,
                   diagonal_values, w, L, projected_fallback, proto):
    """Each lane's Newton matrix at X assembled into L and factorised: the exact one, else (in
    lanes where it is indefinite, if ``projected_fallback``) the projected one. Returns the lanes
    with a factor."""
    H = np.empty(16 * width(proto))
    _newton_band(X, triangles, grad, w_corotated, w_volume, muscle_of, w_muscle, stretch, fill(proto, 0.0), slot,
                 diagonal, diagonal_values, L, H, proto)
    ok = banded.factor(L, w, proto)
    if projected_fallback and lanes_set(ok) < width(proto):
        _newton_band(X, triangles, grad, w_corotated, w_volume, muscle_of, w_muscle, stretch, 1.0 - ok, slot,
                     diagonal, diagonal_values, L, H, proto)
        ok = banded.factor(L, w, proto)
    return ok


@jit
def _lbfgs_pack(X, Y, mass_h2, triangles, grad, w_corotated, w_volume, muscle_of, w_muscle, stretch, slot,
                diagonal, diagonal_values, w, perm, inverse, L, stale, atol, max_iter, m, g, iterations, ok, proto):
    """The forward solve of a pack, in place on X [N, 2, W] (to the minimiser of each lane's Phi;
    g receives grad Phi there). If `stale`, each lane's Newton matrix at X is first factorised
    into L (_factor_newton; ok [W] = 1.0 where one was positive definite); a lane without a
    factor does not move. Then L-BFGS (history m, the factor as H0, backtracking to Armijo's or
    the approximate Wolfe test as in solve._line_search) on all lanes in lock step: a lane stops
    (its direction becomes 0) once its residual is <= atol, and keeps its own step lengths.
    iterations [W] receives each lane's iterations."""
    W = width(proto)
    if stale:
        store(ok, 0, _factor_newton(X, triangles, grad, w_corotated, w_volume, muscle_of, w_muscle, stretch, slot,
                                    diagonal, diagonal_values, w, L, True, proto))
    lanes_ok = load(ok, 0, proto)
    if lanes_set(lanes_ok) == 0:
        return
    size = X.size
    Xf, gf = X.reshape(-1), g.reshape(-1)
    S, Yp = np.zeros((m, size)), np.zeros((m, size))                # pairs s, y; ring of m
    rho, alphas = np.zeros(m * W), np.zeros(m * W)
    d, X_new, g_new, x = np.empty(size), np.empty(size), np.empty(size), np.empty(size)
    Xn, gn, dn = X_new.reshape(X.shape), g_new.reshape(X.shape), d.reshape(X.shape)
    phi = _objective(X, Y, mass_h2, triangles, grad, w_corotated, w_volume, muscle_of, w_muscle, stretch, g, proto)
    taken = fill(proto, 0.0)
    count, head = 0, 0
    for _ in range(max_iter):
        active = lanes_ok * mask(_max_nodal_norm(g, proto) > atol)
        if lanes_set(active) == 0:
            break
        taken += active
        d[:] = gf                                                   # d = -H g, two-loop recursion
        for k in range(count):
            h = (head - 1 - k) % m
            alpha = load(rho, h * W, proto) * _dot(S[h], d, proto)
            store(alphas, k * W, alpha)
            for o in range(0, size, W):
                store(d, o, load(d, o, proto) - alpha * load(Yp[h], o, proto))
        banded.solve(L, w, perm, inverse, dn, dn, x, proto)
        for k in range(count - 1, -1, -1):
            h = (head - 1 - k) % m
            coefficient = load(alphas, k * W, proto) - load(rho, h * W, proto) * _dot(Yp[h], d, proto)
            for o in range(0, size, W):
                store(d, o, load(d, o, proto) + coefficient * load(S[h], o, proto))
        for o in range(0, size, W):
            store(d, o, load(d, o, proto) * -active)
        slope = _dot(gf, d, proto)
        uphill = active * mask(slope >= 0.0)
        if lanes_set(uphill) > 0:                                   # not a descent direction: restart
            for h in range(m):
                store(rho, h * W, load(rho, h * W, proto) * (1.0 - uphill))
            banded.solve(L, w, perm, inverse, g, gn, x, proto)
            for o in range(0, size, W):
                store(d, o, select(uphill, -load(g_new, o, proto), load(d, o, proto)))
            slope = _dot(gf, d, proto)
        t, accepted = fill(proto, 1.0), 1.0 - active                # backtracking per lane (solve._line_search)
        for halvings in range(31):
            if halvings:
                t = select(accepted, t, t * 0.5)
            for o in range(0, size, W):
                store(X_new, o, load(Xf, o, proto) + t * load(d, o, proto))
            phi_new = _objective(Xn, Y, mass_h2, triangles, grad, w_corotated, w_volume, muscle_of, w_muscle, stretch,
                                 gn, proto)
            armijo = mask(phi_new - phi <= ARMIJO_C1 * t * slope + PHI_ROUND_OFF * absolute(phi))
            dphi = _dot(g_new, d, proto)                                # Phi'(t): exact to the gradient's round-off
            wolfe = (mask(dphi <= (2.0 * ARMIJO_C1 - 1.0) * slope) * mask(dphi >= WOLFE_SIGMA * slope)
                     * mask(phi_new - phi <= WOLFE_FLAT * absolute(phi)))
            accepted = maximum(accepted, maximum(armijo, wolfe))
            if lanes_set(accepted) == W:
                break
        for o in range(0, size, W):                                 # history: s, y, rho = 1 / s.y
            store(S[head], o, load(X_new, o, proto) - load(Xf, o, proto))
            store(Yp[head], o, load(g_new, o, proto) - load(gf, o, proto))
        sy = _dot(S[head], Yp[head], proto)
        usable = mask(sy > 1e-300)
        store(rho, head * W, select(usable, 1.0 / select(usable, sy, 1.0), 0.0))
        head, count = (head + 1) % m, min(count + 1, m)
        Xf[:] = X_new
        gf[:] = g_new
        phi = phi_new
    store(iterations, 0, taken)


# ---------------------------------------------------------------------------------------------
# Entry points. phi_args = (mass_h2, triangles, grad, w_corotated [P, T, W], w_volume [P, T or 0, W],
# muscle_of, w_muscle, stretch [P, n_act, W]) as in _objective; band = PackBand.arrays (slot, diagonal,
# diagonal_values, w, perm, inverse); L [P, rows, w + 4, W] the packs' bands; packs: the indices
# p to work on (in parallel over numba's threads, in this order: solve.balanced_order).


@jit(parallel=True)
def objective(X, Y, phi_args, packs, g, phi):
    """phi[p] = Phi per lane [W], g[p] = grad Phi ([P, N, 2, W]) at X[p]."""
    mass_h2, triangles, grad, w_corotated, w_volume, muscle_of, w_muscle, stretch = phi_args
    for k in numba.prange(packs.shape[0]):
        p = packs[k]
        store(phi[p], 0, _objective(X[p], Y[p], mass_h2, triangles, grad, w_corotated[p], w_volume[p], muscle_of,
                                    w_muscle, stretch[p], g[p], prototype(X)))


@jit(parallel=True)
def factor(X, phi_args, band, L, packs, ok):
    """L[p] = each lane's Newton factor at X[p] (_factor_newton); ok[p] [W] = 1.0 where one was
    positive definite. phi_args' mass_h2 is unused (the band's diagonal_values hold M/h^2)."""
    _, triangles, grad, w_corotated, w_volume, muscle_of, w_muscle, stretch = phi_args
    slot, diagonal, diagonal_values, w, _, _ = band
    for k in numba.prange(packs.shape[0]):
        p = packs[k]
        store(ok[p], 0, _factor_newton(X[p], triangles, grad, w_corotated[p], w_volume[p], muscle_of, w_muscle,
                                       stretch[p], slot, diagonal, diagonal_values, w, L[p], True, prototype(X)))


@jit(parallel=True)
def solve(L, band, R, packs, Z):
    """Z[p] = K^-1 R[p] per lane ([P, N, 2, W]) with the factors L[p] of `factor`."""
    _, _, _, w, perm, inverse = band
    for k in numba.prange(packs.shape[0]):
        p = packs[k]
        banded.solve(L[p], w, perm, inverse, R[p], Z[p], np.empty(R[p].size), prototype(R))


@jit(parallel=True)
def newton_solve(X, R, phi_args, band, L, packs, Z, ok):
    """Z[p] = K^-1 R[p] per lane with K the exact Newton matrix at X[p] ([P, N, 2, W]); ok[p]
    [W] = 1.0 where K was positive definite (else Z is garbage)."""
    _, triangles, grad, w_corotated, w_volume, muscle_of, w_muscle, stretch = phi_args
    slot, diagonal, diagonal_values, w, perm, inverse = band
    for k in numba.prange(packs.shape[0]):
        p = packs[k]
        proto = prototype(X)
        store(ok[p], 0, _factor_newton(X[p], triangles, grad, w_corotated[p], w_volume[p], muscle_of, w_muscle,
                                       stretch[p], slot, diagonal, diagonal_values, w, L[p], False, proto))
        banded.solve(L[p], w, perm, inverse, R[p], Z[p], np.empty(R[p].size), proto)


@jit(parallel=True)
def lbfgs(X, Y, phi_args, band, L, stale, packs, atol, max_iter, m, g, iterations, ok):
    """The forward solve of every listed pack (_lbfgs_pack), in place on X[p] and g[p]
    ([P, N, 2, W]); stale [P] bool: refactorise the pack's Newton matrices at X[p] first (ok[p]
    [W] then receives where that succeeded; else ok[p] and L[p] are the kept ones); iterations
    [P, W] (float) receives each lane's L-BFGS iterations. atol (N), max_iter, m: the stopping
    rule, iteration limit and history size."""
    mass_h2, triangles, grad, w_corotated, w_volume, muscle_of, w_muscle, stretch = phi_args
    slot, diagonal, diagonal_values, w, perm, inverse = band
    for k in numba.prange(packs.shape[0]):
        p = packs[k]
        _lbfgs_pack(X[p], Y[p], mass_h2, triangles, grad, w_corotated[p], w_volume[p], muscle_of, w_muscle,
                    stretch[p], slot, diagonal, diagonal_values, w, perm, inverse, L[p], stale[p], atol, max_iter, m,
                    g[p], iterations[p], ok[p], prototype(X))


def kernel_arrays(model, contraction: np.ndarray, E: np.ndarray) -> tuple:
    """The entry points' phi_args for one sample per pack (width 1) of a SolidModel, for
    contraction [n_act, B] and E [B]: (mass_h2 [N], triangles [T, 3], grad [T, 3, 2], w_corotated
    [B, T] = area 2 mu_s(E_b), w_volume [B, T] = area lambda_s(E_b) ([B, 0] without the volume
    term), muscle_of [T], w_muscle [n_act], stretch [B, n_act] = 1 - contraction);
    solve.pack_arrays deals them into packs of eight."""
    material, area = model.material, model.fem.area
    w_corotated = np.ascontiguousarray(np.outer(E, area * material.corotated_per_E))
    w_volume = np.ascontiguousarray(np.outer(E, area * material.volume_per_E) if material.volume_term
                                    else np.zeros((len(E), 0)))
    return (model.mass_h2, model.mesh_triangles, model.fem.grad, w_corotated, w_volume, model.muscle_of,
            model.muscle_weight, np.ascontiguousarray(1.0 - contraction.T))


class PackBand:
    """The Newton band of the compiled solver's packs for the mesh's band layout (fem.NewtonBand;
    banded.py's padding: rows a multiple of 4, identity rows past 2N, cols = w + 4) and nodal
    masses. `arrays`, as the entry points take them: (slot [T, 6, 6] and diagonal [rows], flat
    indices (of one lane) of the element entries and of every row's diagonal, diagonal_values
    (M/h^2 per DOF, 1 for the padding) where the diagonal starts, the half-bandwidth w, the RCM
    permutation and its inverse)."""

    def __init__(self, newton_band, mass_diag: np.ndarray):
        layout = self.layout = newton_band.layout
        n = len(layout.perm)
        diagonal = np.concatenate([newton_band.diagonal, np.arange(n, layout.rows) * layout.cols])
        self.arrays = (np.ascontiguousarray(newton_band.slot), diagonal,
                       np.concatenate([mass_diag, np.ones(layout.rows - n)]), layout.width, layout.perm,
                       layout.inverse)
        self._room = threading.local()

    def shape(self, packs: int, lanes: int = LANES) -> tuple:
        """The factors' array shape for `packs` packs of `lanes` lanes: [packs, rows, cols, lanes]."""
        return packs, self.layout.rows, self.layout.cols, lanes

    def empty(self, packs: int, lanes: int = LANES) -> np.ndarray:
        """Room for the factors of `packs` packs of `lanes` lanes (shape), 64-byte aligned (one
        vector per cache line). The room is kept and reused by the thread's next call (so a step
        does not fault in ~6 MB of fresh pages per pack): a caller's factors live until then.
        One room per thread: a backward's adjoint and the recomputation beside it
        (rollout.Segments) each have their own."""
        shape = self.shape(packs, lanes)
        size = int(np.prod(shape))
        room = getattr(self._room, "array", None)
        if room is None or len(room) < size:
            room = self._room.array = aligned_empty((size,))
        return room[:size].reshape(shape)


def aligned_empty(shape: tuple) -> np.ndarray:
    """np.empty(shape) of float64 starting on a 64-byte boundary."""
    size = int(np.prod(shape))
    buffer = np.empty(size + LANES)
    start = (-buffer.ctypes.data % 64) // 8
    return buffer[start:start + size].reshape(shape)
