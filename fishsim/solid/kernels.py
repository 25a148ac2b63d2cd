"""Compiled (numba) hot loops of the forward PD solve: the objective's energy and gradient, the
L-BFGS two-loop recursion, and the element Newton matrices of the lagged preconditioner.

    Phi(X) = 1/(2 h^2) ||X - Y||_M^2 + E_int(X),   grad Phi = M/h^2 (X - Y) + G^T S(X)

with E_int the co-rotated and muscle energies of elastic.py (same conventions: conformal
coordinates, fiber column j = 0, target stretch 1 - contraction). One pass over the elements
computes F, the projections, the energy and the nodal gradient without numpy temporaries: on the
default fish (2142 elements) 0.05 ms instead of 0.29 ms per evaluation, which L-BFGS does ~11
times per step. Models with the volume term use the numpy paths (solve.Objective,
elastic.element_hessians), which stay the reference (tests/solid/test_kernels.py). Arrays must
be C-contiguous float64 (another layout compiles another specialisation, or fails in the B = 1
fast paths).
"""

from __future__ import annotations

import numba
import numpy as np

from fishsim.solid.energies import _TINY


@numba.njit(cache=True, fastmath=False)
def objective(X: np.ndarray, Y: np.ndarray, mass_h2: np.ndarray, triangles: np.ndarray, grad: np.ndarray,
              w_corotated: np.ndarray, muscle_of: np.ndarray, w_muscle: np.ndarray, stretch: np.ndarray,
              g: np.ndarray) -> np.ndarray:
    """Phi [B] (J per unit depth), writing grad Phi into g [N, 2B] (N per unit depth).

    X, Y [N, 2B] (column a B + b); mass_h2 [N]; triangles [T, 3]; grad [T, 3, 2] shape-function
    gradients; w_corotated [T, B] = area 2 mu_s(E_b); muscle_of [T] muscle index or -1;
    w_muscle [n_act] = k_m area; stretch [n_act, B] = 1 - contraction."""
    N, B = X.shape[0], X.shape[1] // 2
    phi = np.zeros(B)
    for i in range(N):
        for col in range(2 * B):
            d = X[i, col] - Y[i, col]
            g[i, col] = mass_h2[i] * d
            phi[col % B] += 0.5 * mass_h2[i] * d * d
    for e in range(triangles.shape[0]):
        k0, k1, k2 = triangles[e, 0], triangles[e, 1], triangles[e, 2]
        m = muscle_of[e]
        for b in range(B):
            x0, x1, x2 = X[k0, b], X[k1, b], X[k2, b]
            y0, y1, y2 = X[k0, B + b], X[k1, B + b], X[k2, B + b]
            F00 = x0 * grad[e, 0, 0] + x1 * grad[e, 1, 0] + x2 * grad[e, 2, 0]
            F01 = x0 * grad[e, 0, 1] + x1 * grad[e, 1, 1] + x2 * grad[e, 2, 1]
            F10 = y0 * grad[e, 0, 0] + y1 * grad[e, 1, 0] + y2 * grad[e, 2, 0]
            F11 = y0 * grad[e, 0, 1] + y1 * grad[e, 1, 1] + y2 * grad[e, 2, 1]
            alpha, beta = (F00 + F11) / 2, (F10 - F01) / 2
            gamma, delta = (F00 - F11) / 2, (F01 + F10) / 2
            c = max(np.sqrt(alpha * alpha + beta * beta), _TINY)
            ra, rb = alpha - alpha / c, beta - beta / c             # F - R, conformal coordinates
            w = w_corotated[e, b]
            phi[b] += w * (ra * ra + rb * rb + gamma * gamma + delta * delta)
            S00, S01 = w * (ra + gamma), w * (delta - rb)
            S10, S11 = w * (rb + delta), w * (ra - gamma)
            if m >= 0:                                              # muscle: F m - a F m / |F m|
                length = max(np.sqrt(F00 * F00 + F10 * F10), _TINY)
                m0 = F00 - stretch[m, b] * F00 / length
                m1 = F10 - stretch[m, b] * F10 / length
                phi[b] += w_muscle[m] / 2 * (m0 * m0 + m1 * m1)
                S00 += w_muscle[m] * m0
                S10 += w_muscle[m] * m1
            for k, node in ((0, k0), (1, k1), (2, k2)):             # dE/dx_ka = sum_j S_aj g_kj
                g[node, b] += S00 * grad[e, k, 0] + S01 * grad[e, k, 1]
                g[node, B + b] += S10 * grad[e, k, 0] + S11 * grad[e, k, 1]
    return phi


@numba.njit(cache=True)
def _sample_dots(U: np.ndarray, V: np.ndarray, out: np.ndarray) -> None:
    """out[b] = sum over nodes and axes of U * V for sample b (columns a B + b of [N, 2B])."""
    B = out.shape[0]
    if B == 1:                                   # one contiguous vector: a vectorisable loop
        u, v = U.reshape(-1), V.reshape(-1)
        total = 0.0
        for j in range(u.shape[0]):
            total += u[j] * v[j]
        out[0] = total
        return
    out[:] = 0.0
    for i in range(U.shape[0]):
        for a in range(2):
            for b in range(B):
                out[b] += U[i, a * B + b] * V[i, a * B + b]


@numba.njit(cache=True)
def _axpy_per_sample(c: np.ndarray, X: np.ndarray, Z: np.ndarray) -> None:
    """Z += c_b X on the columns of sample b ([N, 2B] arrays, c [B])."""
    B = c.shape[0]
    if B == 1:
        x, z, c0 = X.reshape(-1), Z.reshape(-1), c[0]
        for j in range(z.shape[0]):
            z[j] += c0 * x[j]
        return
    for i in range(Z.shape[0]):
        for a in range(2):
            for b in range(B):
                Z[i, a * B + b] += c[b] * X[i, a * B + b]


@numba.njit(cache=True)
def lbfgs_first_loop(q: np.ndarray, S: np.ndarray, Y: np.ndarray, rho: np.ndarray, order: np.ndarray,
                     alphas: np.ndarray) -> None:
    """L-BFGS two-loop recursion, first half, in place on q [N, 2B]: for the pairs
    (S[h], Y[h], rho[h]) from newest to oldest (h = order[k]), alpha_k = rho s.q, q -= alpha_k y
    (per sample); alphas [len(order), B] receives the alpha_k."""
    B = alphas.shape[1]
    dots = np.empty(B)
    for k in range(order.shape[0]):
        h = order[k]
        _sample_dots(S[h], q, dots)
        for b in range(B):
            alphas[k, b] = rho[h, b] * dots[b]
        _axpy_per_sample(-alphas[k], Y[h], q)


@numba.njit(cache=True)
def lbfgs_second_loop(r: np.ndarray, S: np.ndarray, Y: np.ndarray, rho: np.ndarray, order: np.ndarray,
                      alphas: np.ndarray) -> None:
    """Second half, in place on r = H0 q: from oldest to newest, beta = rho y.r,
    r += (alpha_k - beta) s (per sample)."""
    B = alphas.shape[1]
    dots = np.empty(B)
    for k in range(order.shape[0] - 1, -1, -1):
        h = order[k]
        _sample_dots(Y[h], r, dots)
        for b in range(B):
            dots[b] = alphas[k, b] - rho[h, b] * dots[b]
        _axpy_per_sample(dots, S[h], r)


@numba.njit(cache=True)
def newton_elements(alpha_R: np.ndarray, beta_R: np.ndarray, c: np.ndarray, w_corotated: np.ndarray,
                    muscle_of: np.ndarray, w_muscle: np.ndarray, n0: np.ndarray, n1: np.ndarray,
                    length: np.ndarray, stretch: np.ndarray, grad: np.ndarray, projected: bool,
                    Ke: np.ndarray) -> None:
    """Element Newton matrices Ke [T, 6, 6] = G_e^T H_e G_e of one sample (element DOF 2k + a),
    H_e = d vec(S) / d vec(F) of the co-rotated and muscle energies: elastic.element_hessians
    without the volume term. Inputs are one sample's projections ([T] and [n_act] arrays, see
    elastic.Projections); `projected` clamps c and |F m| as elastic.stress_differential does."""
    H = np.empty((4, 4))
    for e in range(grad.shape[0]):
        ce = max(c[e], 1.0) if projected else c[e]
        m = muscle_of[e]
        for col in range(4):                         # unit dF_aj, col = 2a + j
            dF00, dF01 = 1.0 if col == 0 else 0.0, 1.0 if col == 1 else 0.0
            dF10, dF11 = 1.0 if col == 2 else 0.0, 1.0 if col == 3 else 0.0
            d_alpha, d_beta = (dF00 + dF11) / 2, (dF10 - dF01) / 2
            d_gamma, d_delta = (dF00 - dF11) / 2, (dF01 + dF10) / 2
            radial = alpha_R[e] * d_alpha + beta_R[e] * d_beta
            c0 = w_corotated[e] * (d_alpha - (d_alpha - radial * alpha_R[e]) / ce)
            c1 = w_corotated[e] * (d_beta - (d_beta - radial * beta_R[e]) / ce)
            c2, c3 = w_corotated[e] * d_gamma, w_corotated[e] * d_delta
            S00, S01, S10, S11 = c0 + c2, c3 - c1, c1 + c3, c0 - c2
            if m >= 0:
                L = max(length[m], stretch[m]) if projected else length[m]
                rad = n0[m] * dF00 + n1[m] * dF10
                S00 += w_muscle[m] * (dF00 - stretch[m] * (dF00 - rad * n0[m]) / L)
                S10 += w_muscle[m] * (dF10 - stretch[m] * (dF10 - rad * n1[m]) / L)
            H[0, col], H[1, col], H[2, col], H[3, col] = S00, S01, S10, S11
        for k in range(3):                            # Ke[2k+a, 2l+b] = sum_ji g_kj H[2a+j, 2b+i] g_li
            for a in range(2):
                for l in range(3):
                    for b in range(2):
                        s = 0.0
                        for j in range(2):
                            for i in range(2):
                                s += grad[e, k, j] * H[2 * a + j, 2 * b + i] * grad[e, l, i]
                        Ke[e, 2 * k + a, 2 * l + b] = s
