"""Compiled (numba) helpers of the PD solve on the solver's [B, N, 2] layout: the L-BFGS two-loop
recursion of solve._lbfgs (the iteration of the non-default preconditioners, and for samples
whose Newton matrix has no banded Cholesky factor) and the adjoint's parameter gradients. The
compiled forward and adjoint solves themselves are packed.py's.

Batches: every kernel works on the samples of an index list only and runs them in parallel over
numba's threads (`prange`); one sample's arithmetic is serial and in the same order whatever
the batch. Arrays must be C-contiguous float64 (other layouts fail to compile).
"""

from __future__ import annotations

import numba
import numpy as np

from fishsim.compiled import jit
from fishsim.solid import element
from fishsim.solid.packed import _deformation_gradient


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


@jit(parallel=True)
def parameter_gradients(X: np.ndarray, lam: np.ndarray, triangles: np.ndarray, grad: np.ndarray,
                        w_per_E: np.ndarray, w_volume_per_E: np.ndarray, muscle_of: np.ndarray, w_muscle: np.ndarray,
                        grad_u: np.ndarray, grad_E: np.ndarray) -> None:
    """The adjoint's parameter gradients, dL/dtheta = -lambda^T d(grad Phi)/dtheta at q+ = X, for
    every sample (in parallel), from X and lambda [B, N, 2]:

        dL/dE_b = -sum_e <G_e lambda, dS_e/dE>,  dS_e/dE = w_per_E_e (F - R) + w_volume_per_E_e (F - D),
        dL/du_m = -w_muscle_m <(G_e lambda) m, F m / |F m|>    (S_fiber = w (F m - (1 - u) n)),

    into grad_E [B] (per Pa) and grad_u [B, n_act]; w_per_E [T] = area 2 mu_s / E, w_volume_per_E
    [T] = area lambda_s / E (empty without the volume term; D the closest det-1 matrix)."""
    volume = w_volume_per_E.shape[0] > 0
    for b in numba.prange(X.shape[0]):
        total = 0.0
        for e in range(triangles.shape[0]):
            F00, F01, F10, F11 = _deformation_gradient(X[b], triangles, grad, e, 0.0)
            D00, D01, D10, D11 = _deformation_gradient(lam[b], triangles, grad, e, 0.0)
            _, S00, S01, S10, S11 = element.corotated_stress(F00, F01, F10, F11, w_per_E[e])
            if volume:
                _, V00, V01, V10, V11 = element.volume_stress(F00, F01, F10, F11, w_volume_per_E[e])
                S00, S01, S10, S11 = S00 + V00, S01 + V01, S10 + V10, S11 + V11
            total += D00 * S00 + D01 * S01 + D10 * S10 + D11 * S11
            m = muscle_of[e]
            if m >= 0:
                length = element.fiber_length(F00, F10)
                grad_u[b, m] = -w_muscle[m] * (D00 * F00 + D10 * F10) / length
        grad_E[b] = -total


@jit
def frame_checks(q: np.ndarray, qdot: np.ndarray, triangles: np.ndarray) -> tuple:
    """What the rollout's per-frame checks read, in one pass (~0.4 ms of small torch reductions
    before): (x min, x max, y min, y max of the nodes q [B, N, 2] in m, the largest nodal speed
    |qdot| in m/s, the smallest signed element area (triangles [T, 3], A = ((x1 - x0) x (x2 -
    x0)) / 2 as mesh.triangulate.element_areas) in m^2 and its flat index b T + k)."""
    x_lo, x_hi, y_lo, y_hi, speed = np.inf, -np.inf, np.inf, -np.inf, 0.0
    for b in range(q.shape[0]):
        for n in range(q.shape[1]):
            x, y = q[b, n, 0], q[b, n, 1]
            x_lo, x_hi, y_lo, y_hi = min(x_lo, x), max(x_hi, x), min(y_lo, y), max(y_hi, y)
            speed = max(speed, np.sqrt(qdot[b, n, 0] ** 2 + qdot[b, n, 1] ** 2))
    area, where, T = np.inf, -1, triangles.shape[0]
    for b in range(q.shape[0]):
        for k in range(T):
            i, j, m = triangles[k, 0], triangles[k, 1], triangles[k, 2]
            e1x, e1y = q[b, j, 0] - q[b, i, 0], q[b, j, 1] - q[b, i, 1]
            e2x, e2y = q[b, m, 0] - q[b, i, 0], q[b, m, 1] - q[b, i, 1]
            a = 0.5 * (e1x * e2y - e1y * e2x)
            if a < area:
                area, where = a, b * T + k
    return x_lo, x_hi, y_lo, y_hi, speed, area, where
