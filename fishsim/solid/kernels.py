"""Compiled (numba) hot loops of the PD solve: the objective's energy and gradient, the L-BFGS two-
loop recursion, the element Newton matrices
and their assembly into banded factors, the per-sample banded solves on the solver's [B, N, 2]
layout, and the whole forward L-BFGS solve of a sample (lbfgs_samples); packed.py has their
8-lane versions for batches. The element physics (energies, stresses, their differentials) is
element.py's, shared with packed.py.

    Phi(X) = 1/(2 h^2) ||X - Y||_M^2 + E_int(X),   grad Phi = M/h^2 (X - Y) + G^T S(X)

with E_int the co-rotated and muscle energies (element.py; elastic.py is their numpy reference).
One pass over the elements computes F, the projections, the energy and the nodal gradient
without numpy temporaries: on the default fish (2142 elements) 0.05 ms instead of 0.29 ms per
evaluation, which L-BFGS does ~11 times per step. Models with the volume term use the numpy
paths (solve.Objective, elastic.element_hessians), which stay the reference
(tests/solid/test_kernels.py).

Batches: every kernel works on the samples of a mask or index list only (converged samples cost
nothing) and runs them in parallel over numba's threads (`prange`); one sample's arithmetic is
serial and in the same order whatever the batch, so a kernel's result for one sample does not
depend on the batch it is in. Arrays must be C-contiguous float64 (other layouts fail to compile).
"""

from __future__ import annotations

import numba
import numpy as np

from fishsim.compiled import jit
from fishsim.linalg.banded import band_factor, band_solve
from fishsim.solid import element


@jit
def _deformation_gradient(X, triangles, grad, e):
    """(F00, F01, F10, F11) of element e for one sample's nodal values X [N, 2] (F = G_e X)."""
    k0, k1, k2 = triangles[e, 0], triangles[e, 1], triangles[e, 2]
    return element.deformation_gradient(X[k0, 0], X[k0, 1], X[k1, 0], X[k1, 1], X[k2, 0], X[k2, 1], grad, e)


@jit
def _objective_sample(X, Y, mass_h2, triangles, grad, w_corotated, muscle_of, w_muscle, stretch, b, g) -> float:
    """Phi of one sample (X, Y, g: its [N, 2] arrays; b its column in w_corotated and stretch),
    writing grad Phi into g."""
    phi = 0.0
    for i in range(X.shape[0]):
        for a in range(2):
            d = X[i, a] - Y[i, a]
            g[i, a] = mass_h2[i] * d
            phi += 0.5 * mass_h2[i] * d * d
    for e in range(triangles.shape[0]):
        F00, F01, F10, F11 = _deformation_gradient(X, triangles, grad, e)
        psi, S00, S01, S10, S11 = element.corotated_stress(F00, F01, F10, F11, w_corotated[e, b])
        phi += psi
        m = muscle_of[e]
        if m >= 0:
            psi, M00, M10 = element.muscle_stress(F00, F10, stretch[m, b], w_muscle[m])
            phi += psi
            S00 += M00
            S10 += M10
        for k in range(3):                                          # dE/dx_ka = sum_j S_aj g_kj
            node = triangles[e, k]
            g[node, 0] += S00 * grad[e, k, 0] + S01 * grad[e, k, 1]
            g[node, 1] += S10 * grad[e, k, 0] + S11 * grad[e, k, 1]
    return phi


@jit(parallel=True)
def objective(X: np.ndarray, Y: np.ndarray, phi_args, samples: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Phi [B] (J per unit depth), writing grad Phi into g [B, N, 2] (N per unit depth), for the
    given samples (indices; the others' entries are left as they are, Phi 0).

    X, Y [B, N, 2]; phi_args = (mass_h2 [N], triangles [T, 3], grad [T, 3, 2] shape-function
    gradients, w_corotated [T, B] = area 2 mu_s(E_b), muscle_of [T] muscle index or -1,
    w_muscle [n_act] = k_m area, stretch [n_act, B] = 1 - contraction)."""
    mass_h2, triangles, grad, w_corotated, muscle_of, w_muscle, stretch = phi_args
    phi = np.zeros(X.shape[0])
    for k in numba.prange(samples.shape[0]):
        b = samples[k]
        phi[b] = _objective_sample(X[b], Y[b], mass_h2, triangles, grad, w_corotated, muscle_of, w_muscle,
                                   stretch, b, g[b])
    return phi


@jit
def _dot(u: np.ndarray, v: np.ndarray) -> float:
    """sum_j u_j v_j of two contiguous arrays, flattened (in index order)."""
    u, v = u.reshape(-1), v.reshape(-1)
    total = 0.0
    for j in range(u.shape[0]):
        total += u[j] * v[j]
    return total


@jit
def _axpy(c: float, x: np.ndarray, z: np.ndarray) -> None:
    """z += c x for two contiguous arrays of one shape."""
    x, z = x.reshape(-1), z.reshape(-1)
    for j in range(z.shape[0]):
        z[j] += c * x[j]


@jit(parallel=True)
def lbfgs_first_loop(q: np.ndarray, S: np.ndarray, Y: np.ndarray, rho: np.ndarray, order: np.ndarray,
                     samples: np.ndarray, alphas: np.ndarray) -> None:
    """L-BFGS two-loop recursion, first half, in place on q [B, N, 2] for the given samples: for
    the pairs (S[h], Y[h], rho[h]) ([m, B, N, 2], [m, B]) from newest to oldest (h = order[k]),
    alpha_k = rho s.q, q -= alpha_k y; alphas [len(order), B] receives the alpha_k."""
    for j in numba.prange(samples.shape[0]):
        b = samples[j]
        for k in range(order.shape[0]):
            h = order[k]
            alphas[k, b] = rho[h, b] * _dot(S[h, b], q[b])
            _axpy(-alphas[k, b], Y[h, b], q[b])


@jit(parallel=True)
def lbfgs_second_loop(r: np.ndarray, S: np.ndarray, Y: np.ndarray, rho: np.ndarray, order: np.ndarray,
                      samples: np.ndarray, alphas: np.ndarray) -> None:
    """Second half, in place on r = H0 q: from oldest to newest, beta = rho y.r,
    r += (alpha_k - beta) s."""
    for j in numba.prange(samples.shape[0]):
        b = samples[j]
        for k in range(order.shape[0] - 1, -1, -1):
            h = order[k]
            _axpy(alphas[k, b] - rho[h, b] * _dot(Y[h, b], r[b]), S[h, b], r[b])


@jit
def _element_newton(e, b, alpha_R, beta_R, c, w_corotated, muscle_of, w_muscle, n0, n1, length, stretch,
                    grad, projected, H, Ke) -> None:
    """Ke [6, 6] = G_e^T H_e G_e of element e, sample b (element DOF 2k + a), with H [4, 4]
    scratch for H_e = d vec(S) / d vec(F) of the co-rotated and muscle energies."""
    m = muscle_of[e]
    ce = element.clamped(c[e, b], 1.0, projected)
    L = element.clamped(length[m, b], stretch[m, b], projected) if m >= 0 else 1.0
    for col in range(4):                         # unit dF_aj, col = 2a + j
        S00, S01, S10, S11 = element.corotated_differential(col, alpha_R[e, b], beta_R[e, b], ce, w_corotated[e, b])
        if m >= 0:
            M00, M10 = element.muscle_differential(col, n0[m, b], n1[m, b], L, stretch[m, b], w_muscle[m])
            S00 += M00
            S10 += M10
        H[0, col], H[1, col], H[2, col], H[3, col] = S00, S01, S10, S11
    for k in range(3):                            # Ke[2k+a, 2l+b] = sum_ji g_kj H[2a+j, 2b+i] g_li
        for a in range(2):
            for l in range(3):
                for bb in range(2):
                    s = 0.0
                    for j in range(2):
                        for i in range(2):
                            s += grad[e, k, j] * H[2 * a + j, 2 * bb + i] * grad[e, l, i]
                    Ke[2 * k + a, 2 * l + bb] = s


@jit
def newton_elements(alpha_R: np.ndarray, beta_R: np.ndarray, c: np.ndarray, w_corotated: np.ndarray,
                    muscle_of: np.ndarray, w_muscle: np.ndarray, n0: np.ndarray, n1: np.ndarray,
                    length: np.ndarray, stretch: np.ndarray, grad: np.ndarray, projected: bool, b: int,
                    Ke: np.ndarray) -> None:
    """Element Newton matrices Ke [T, 6, 6] = G_e^T H_e G_e of sample b (element DOF 2k + a):
    elastic.element_hessians without the volume term. The projections are elastic.Projections'
    arrays ([T, B] and [n_act, B]); `projected` clamps c and |F m| as
    elastic.stress_differential does."""
    H = np.empty((4, 4))
    for e in range(grad.shape[0]):
        _element_newton(e, b, alpha_R, beta_R, c, w_corotated, muscle_of, w_muscle, n0, n1, length, stretch,
                        grad, projected, H, Ke[e])


@jit
def _newton_factor(newton, slot: np.ndarray, diagonal: np.ndarray, mass_diag: np.ndarray, projected: bool,
                   b: int, L: np.ndarray) -> bool:
    """Assemble sample b's Newton matrix (newton_elements' element matrices, `newton` its argument
    tuple (alpha_R, ..., grad) without `projected`, plus diag(mass_diag)) straight into the band
    L [n, w + 1] and factorise it (band_factor); returns whether it was positive definite.
    slot [T, 6, 6]: flat band index of each element entry (-1 above the diagonal); diagonal
    [2N]: that of each DOF's diagonal."""
    alpha_R, beta_R, c, w_corotated, muscle_of, w_muscle, n0, n1, length, stretch, grad = newton
    band = L.reshape(-1)
    band[:] = 0.0
    for i in range(diagonal.shape[0]):
        band[diagonal[i]] += mass_diag[i]
    H, Ke = np.empty((4, 4)), np.empty((6, 6))
    for e in range(grad.shape[0]):
        _element_newton(e, b, alpha_R, beta_R, c, w_corotated, muscle_of, w_muscle, n0, n1, length, stretch,
                        grad, projected, H, Ke)
        for r in range(6):
            for s in range(6):
                if slot[e, r, s] >= 0:
                    band[slot[e, r, s]] += Ke[r, s]
    return band_factor(L)


@jit(parallel=True)
def newton_factors(newton, projected: bool, slot: np.ndarray, diagonal: np.ndarray, mass_diag: np.ndarray,
                   samples: np.ndarray, L: np.ndarray, ok: np.ndarray) -> None:
    """For each sample b in samples (in parallel): its Newton matrix's banded factor in L[b]
    [n, w + 1] (_newton_factor; exact, or `projected`); ok[b] = it was positive definite."""
    for k in numba.prange(samples.shape[0]):
        b = samples[k]
        ok[b] = _newton_factor(newton, slot, diagonal, mass_diag, projected, b, L[b])


@jit
def _solve_sample(L: np.ndarray, perm: np.ndarray, inverse: np.ndarray, r: np.ndarray, z: np.ndarray,
                  x: np.ndarray) -> None:
    """z = K^-1 r for one sample (r, z: contiguous [N, 2], DOF 2i + a; r and z may be the same
    array) with K's banded factor L under the DOF permutation perm (row k of the band is DOF
    perm[k], inverse = argsort(perm)); x [2N] scratch."""
    r, z = r.reshape(-1), z.reshape(-1)
    for j in range(x.shape[0]):
        x[j] = r[perm[j]]
    band_solve(L, x)
    for dof in range(x.shape[0]):
        z[dof] = x[inverse[dof]]


@jit(parallel=True)
def solve_samples(L: np.ndarray, perm: np.ndarray, inverse: np.ndarray, R: np.ndarray, samples: np.ndarray,
                  Z: np.ndarray) -> None:
    """Z[b] = K_b^-1 R[b] ([B, N, 2]) for each b in samples (in parallel), with K_b's banded factor
    L[b] (_solve_sample)."""
    for k in numba.prange(samples.shape[0]):
        b = samples[k]
        _solve_sample(L[b], perm, inverse, R[b], Z[b], np.empty(L.shape[1]))


@jit
def _max_nodal_norm(g: np.ndarray) -> float:
    """max_i |g_i| of one sample's [N, 2] nodal vectors; NaN if any is (a blown-up sample then
    stops iterating, as in the numpy path)."""
    largest = 0.0
    for i in range(g.shape[0]):
        norm = np.sqrt(g[i, 0] ** 2 + g[i, 1] ** 2)
        if np.isnan(norm):
            return norm
        largest = max(largest, norm)
    return largest


@jit
def _lbfgs_sample(X, Y, mass_h2, triangles, grad, w_corotated, muscle_of, w_muscle, stretch, b, L, perm,
                  inverse, atol, max_iter, m, g) -> int:
    """L-BFGS on Phi of sample b from X (its [N, 2] positions, updated in place to the minimiser;
    g receives grad Phi there): solve.pd_solve's iteration for one sample, compiled, with the
    sample's banded Newton factor L as H0 (_solve_sample). Returns the iterations taken. (The
    objective's arrays are passed one by one: taking lbfgs_samples' tuple made a B = 1 step
    ~50 % slower.)"""
    c1, round_off = 1e-4, 64 * np.finfo(np.float64).eps
    S, Yp = np.zeros((m, X.shape[0], 2)), np.zeros((m, X.shape[0], 2))  # pairs s, y; ring of m
    rho, alphas = np.zeros(m), np.zeros(m)
    d, X_new, g_new, x = np.empty_like(X), np.empty_like(X), np.empty_like(X), np.empty(2 * X.shape[0])
    phi = _objective_sample(X, Y, mass_h2, triangles, grad, w_corotated, muscle_of, w_muscle, stretch, b, g)
    count, head, iterations = 0, 0, 0
    while iterations < max_iter and _max_nodal_norm(g) > atol:
        iterations += 1
        d[:] = g                                                      # d = -H g, two-loop recursion
        for k in range(count):
            h = (head - 1 - k) % m
            alphas[k] = rho[h] * _dot(S[h], d)
            _axpy(-alphas[k], Yp[h], d)
        _solve_sample(L, perm, inverse, d, d, x)
        for k in range(count - 1, -1, -1):
            h = (head - 1 - k) % m
            _axpy(alphas[k] - rho[h] * _dot(Yp[h], d), S[h], d)
        d *= -1.0
        slope = _dot(g, d)
        if slope >= 0:                                                # not a descent direction: restart
            rho[:] = 0.0
            _solve_sample(L, perm, inverse, g, d, x)
            d *= -1.0
            slope = _dot(g, d)
        t = 1.0                                                       # Armijo backtracking
        for halvings in range(31):
            if halvings:
                t /= 2
            X_new[:] = X
            _axpy(t, d, X_new)
            phi_new = _objective_sample(X_new, Y, mass_h2, triangles, grad, w_corotated, muscle_of, w_muscle,
                                        stretch, b, g_new)
            if phi_new - phi <= c1 * t * slope + round_off * abs(phi):
                break
        np.subtract(X_new, X, S[head])                                # history: s, y, rho = 1 / s.y
        np.subtract(g_new, g, Yp[head])
        sy = _dot(S[head], Yp[head])
        rho[head] = 1.0 / sy if sy > 1e-300 else 0.0
        head, count = (head + 1) % m, min(count + 1, m)
        X[:] = X_new
        g[:] = g_new
        phi = phi_new
    return iterations


@jit(parallel=True)
def lbfgs_samples(X: np.ndarray, Y: np.ndarray, phi_args, L: np.ndarray, perm: np.ndarray, inverse: np.ndarray,
                  newton, slot: np.ndarray, diagonal: np.ndarray, mass_diag: np.ndarray, stale: np.ndarray,
                  banded: np.ndarray, atol: float, max_iter: int, m: int, samples: np.ndarray, g: np.ndarray,
                  iterations: np.ndarray) -> None:
    """The whole forward solve of each sample b in samples, in parallel: where stale[b], first
    the banded factor L[b] of its Newton matrix (_newton_factor: the exact one, else the
    projected one; banded[b] = one was positive definite, else the sample is skipped); then
    L-BFGS with L[b] as H0 (_lbfgs_sample), moving X[b] ([B, N, 2]) to the minimiser of Phi, g[b]
    receiving grad Phi there and iterations[b] the iterations taken. phi_args: objective's
    arrays (mass_h2, triangles, grad, w_corotated, muscle_of, w_muscle, stretch); perm, inverse:
    the band's DOF permutation; newton, slot, diagonal, mass_diag: _newton_factor's; atol (N),
    max_iter, m: stopping rule, iteration limit, history size."""
    mass_h2, triangles, grad, w_corotated, muscle_of, w_muscle, stretch = phi_args
    for k in numba.prange(samples.shape[0]):
        b = samples[k]
        if stale[b]:
            banded[b] = (_newton_factor(newton, slot, diagonal, mass_diag, False, b, L[b])
                         or _newton_factor(newton, slot, diagonal, mass_diag, True, b, L[b]))
        if banded[b]:
            iterations[b] = _lbfgs_sample(X[b], Y[b], mass_h2, triangles, grad, w_corotated, muscle_of, w_muscle,
                                          stretch, b, L[b], perm, inverse, atol, max_iter, m, g[b])


@jit(parallel=True)
def parameter_gradients(X: np.ndarray, lam: np.ndarray, triangles: np.ndarray, grad: np.ndarray,
                        w_per_E: np.ndarray, muscle_of: np.ndarray, w_muscle: np.ndarray, grad_u: np.ndarray,
                        grad_E: np.ndarray) -> None:
    """The adjoint's parameter gradients, dL/dtheta = -lambda^T d(grad Phi)/dtheta at q+ = X, for
    every sample (in parallel), from X and lambda [B, N, 2] (models without the volume term):

        dL/dE_b = -sum_e <G_e lambda, dS_e/dE>,  dS_e/dE = w_per_E_e (F - R) (conformal parts),
        dL/du_m = -w_muscle_m <(G_e lambda) m, F m / |F m|>    (S_fiber = w (F m - (1 - u) n)),

    into grad_E [B] (per Pa) and grad_u [B, n_act]; w_per_E [T] = area 2 mu_s / E."""
    for b in numba.prange(X.shape[0]):
        total = 0.0
        for e in range(triangles.shape[0]):
            F00, F01, F10, F11 = _deformation_gradient(X[b], triangles, grad, e)
            D00, D01, D10, D11 = _deformation_gradient(lam[b], triangles, grad, e)
            _, S00, S01, S10, S11 = element.corotated_stress(F00, F01, F10, F11, w_per_E[e])
            total += D00 * S00 + D01 * S01 + D10 * S10 + D11 * S11
            m = muscle_of[e]
            if m >= 0:
                length = element.fiber_length(F00, F10)
                grad_u[b, m] = -w_muscle[m] * (D00 * F00 + D10 * F10) / length
        grad_E[b] = -total
