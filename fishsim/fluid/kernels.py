"""Compiled (numba) loops of the numerical fluid on the CPU, with their hand-written adjoints:
``SplitStep`` runs a step's sub-steps (``NumericalFluid._substeps``: per sub-step two stages of
``numerical.predict``, i.e. ghost values, Koren advection, 5-point diffusion and the explicit
update, then ``NumericalFluid._constrain``: the K penalise -> project passes, or the joint
penalisation + projection solve of ``numerical.immerse``, ``Immersion``) in one call; ``Predict``
is the predictor alone. Other devices and schemes use the torch formulas, which stay the reference
(tests/fluid/test_kernels.py; ``numerical.COMPILED``).

The joint stage's adjoint: with v = u - c grad phi, pen = v - w + grad phi, phi = A(c)^+ (-div
u), A(c) = -div(c grad .) (symmetric, so its adjoint solve is the same PCG), u = c (w + a s v_d)
and c = 1 / (1 + a s), a = lambda dt, for dL/d(v, phi, pen) = (g_v, g_phi, g_pen) and g_t = g_v
+ g_pen:

    lam = A^+ (g_phi + grad^T (g_pen - c g_t)),   dL/du = g_t - div^T lam,
    dL/dc = -grad phi (g_t + grad lam),           dL/dw = c dL/du - g_pen,
    dL/ds = a c^2 (dL/du (v_d - w) - dL/dc),      dL/dv_d = a c s dL/du

on the interior faces (on the box-wall faces u = s v_d: dL/dw = -g_pen, dL/ds = v_d dL/du,
dL/dv_d = s dL/du).

Why: the torch formula tapes ~100 small full-grid temporaries per stage (the ghost layers'
concatenations, the limiter's minima, maxima and selections, the slices) and its backward replays
them. On the 100 x 300 grid, one thread, a stage cost 4.8 ms forward and ~50 ms forward + backward,
16 stages a frame: the numerical fluid's backward was mostly this.

    w = v + dt (nu lap v - (v.grad) v)     on the interior faces; w = v on the box-wall faces

with ``grid``'s stencils: ghost values of two layers (``grid.pad_faces``: the normal velocity
continued by odd reflection about the wall face, the tangential one mirrored about the wall half a
cell away, 2 u_wall - u or u with slip), the flux-form advection of ``grid.advection``

    F = U q_f,  U = (a + b)/2 the transporting velocity,
    q_f = koren(q[k-1], q[k], q[k+1]) if U >= 0 else koren(q[k+2], q[k+1], q[k]),
    (v.grad v)_x = (F_x[j+1] - F_x[j] + G_x[i+1] - G_x[i]) / dx, the y-component likewise,

and the 5-point Laplacian. koren(u, c, d) = median(c, (5c + 2d - u)/6, median(c, d, 3c - 2u)) is
piecewise linear: its derivative is that of the candidate selected (ties: the first in the order c,
(5c + 2d - u)/6, d, 3c - 2u; torch splits a tie between minima or maxima evenly, so the adjoints
can differ where the limiter's branches meet exactly; in water at rest U = 0 makes both vanish).

P, Q are vx, vy with their ghost layers ([H+4, W+5], [H+5, W+4] per sample) and PT, QT their
transposes, so that every flux family runs along the rows of one array. Each sample's loops are
serial and in a fixed order (its result does not depend on its batch); ``Predict`` runs the samples
of a batch in parallel over numba's threads and a single sample in the calling thread
(``fishsim.compiled.each_sample``: a parallel region's start costs more than one sample's pass);
``SplitStep`` cuts a batch into one chunk per torch thread and runs each chunk's
whole step, forward or adjoint, in a Python thread of its own (``compiled.in_sample_chunks``; 16
fish on 100 x 300, two threads: a step 257-296 -> 180-233 ms forward, 568-801 -> 351-458 ms
forward + backward). Within a chunk each sample's whole step, its Poisson solves included
(``dct.inverse_sample``: the DCTs through rocket-fft inside compiled code), is one compiled call
(``_sample_steps``, ``_sample_steps_adjoint``) that holds no GIL: before, the loop over sub-steps
and passes ran in Python, ~340 calls a step, and took ~40 % of a step at B = 1 (2026-11-28, one
thread, old and new alternating, results bit for bit equal: forward 17-29 -> 13.3-14.5 ms, forward
+ backward 46-75 -> 36.5-39 ms; 16 fish, two threads: 229-288 -> 112-148 ms forward, 540-676 ->
416-482 ms forward + backward).
Grids need at least 3 cells a side. Arithmetic runs in the data's dtype (``_constants``; nu, dt and
1/dx cast on entry): numba's literals are float64, and float32 data mixed with them converted every
operand (the float32 predictor ran 2x, its adjoint 2.1x slower than now: 0.42 / 1.15 against 0.17 /
0.55 ms on 100 x 300, one thread).
"""

from __future__ import annotations

from collections import namedtuple
from dataclasses import dataclass

import numpy as np
import torch
from numba import prange
from torch import Tensor

from fishsim.compiled import each_sample, in_sample_chunks, jit, sample_chunks
from fishsim.fluid.pressure import _pcg_sample, local_solver, subdomain
from fishsim.linalg.dct import inverse_sample

Constants = namedtuple("Constants", "zero half one two three four five six sixth five_sixths third")


@jit(inline="always")
def _constants(q):
    """The loops' constants (``Constants``) in q's dtype: literals are float64 in numba, and
    mixing them with float32 data makes every loop convert both ways (float32 data then ran
    slower than float64)."""
    T = q.dtype.type
    return Constants(T(0.0), T(0.5), T(1.0), T(2.0), T(3.0), T(4.0), T(5.0), T(6.0), T(1.0 / 6.0),
                     T(5.0 / 6.0), T(1.0 / 3.0))


@jit(inline="always")
def _median(a, b, c):
    return max(min(a, b), min(max(a, b), c))


@jit(inline="always")
def _koren(u, c, d, k):
    """koren(u, c, d) with k = ``_constants`` of the data's dtype."""
    return _median(c, (k.five * c + k.two * d - u) / k.six, _median(c, d, k.three * c - k.two * u))


@jit(inline="always")
def _koren_grad(u, c, d, k):
    """(koren(u, c, d), d/du, d/dc, d/dd): the derivative of the candidate selected, c first on
    ties, then t = (5c + 2d - u)/6, d, 3c - 2u (selects, no branches: the loop vectorises); k =
    ``_constants`` of the data's dtype."""
    t = (k.five * c + k.two * d - u) / k.six
    v = _median(c, t, _median(c, d, k.three * c - k.two * u))
    fc = k.one if v == c else k.zero
    ft = k.one - fc if v == t else k.zero
    fd = k.one - fc - ft if v == d else k.zero
    fe = k.one - fc - ft - fd
    return v, -k.sixth * ft - k.two * fe, fc + k.five_sixths * ft + k.three * fe, k.third * ft + fd


@jit(inline="always")
def _upwind(qr, k, pos):
    """(u, c, d) of Koren's face value between qr[k+1] and qr[k+2] for a transporting velocity
    pointing to +k (``pos``) or -k: selects of four contiguous loads, so the loops vectorise."""
    q0, q1, q2, q3 = qr[k], qr[k + 1], qr[k + 2], qr[k + 3]
    return (q0 if pos else q3, q1 if pos else q2, q2 if pos else q1)


@jit(error_model="numpy")
def _family_forward(q, T, tr0, tc0, tr1, tc1, F):
    """One flux family along rows: F[a, k] = U upwind(q[a+2, k .. k+3], U), U = (T[a+tr0, k+tc0]
    + T[a+tr1, k+tc1]) / 2, the face value between q[a+2, k+1] and q[a+2, k+2]. Rows as 1D views,
    the upwind side as selects: the loop vectorises."""
    n, K = F.shape[1], _constants(q)
    for a in range(F.shape[0]):
        qr, out = q[a + 2], F[a]
        t0, t1 = T[a + tr0, tc0:tc0 + n], T[a + tr1, tc1:tc1 + n]
        for k in range(n):
            U = K.half * (t0[k] + t1[k])
            u, c, d = _upwind(qr, k, U >= K.zero)
            out[k] = U * _koren(u, c, d, K)


@jit(error_model="numpy")
def _family_backward(q, T, tr0, tc0, tr1, tc1, g, gq, gT):
    """Adjoint of ``_family_forward`` for dL/dF = g: adds dL/dq into gq and dL/dT into gT (they may
    be one array). Per row: the weights dL/dq[k + s] of every flux (a vectorised loop), then their
    sum per q entry (a gather: no flux waits for its neighbour's store)."""
    n0, n1 = g.shape
    K = _constants(q)
    zero, half = K.zero, K.half
    w0, w1 = np.zeros(n1 + 6, dtype=q.dtype), np.zeros(n1 + 6, dtype=q.dtype)    # flux k's at k + 3
    w2, w3 = np.zeros(n1 + 6, dtype=q.dtype), np.zeros(n1 + 6, dtype=q.dtype)
    w4 = np.empty(n1, dtype=q.dtype)
    for a in range(n0):
        qr, ga = q[a + 2], g[a]
        t0, t1 = T[a + tr0, tc0:tc0 + n1], T[a + tr1, tc1:tc1 + n1]
        for k in range(n1):
            U = half * (t0[k] + t1[k])
            pos = U >= zero
            u, c, d = _upwind(qr, k, pos)
            v, du, dc, dd = _koren_grad(u, c, d, K)
            gv = ga[k] * U
            w0[k + 3] = gv * du if pos else zero
            w1[k + 3] = gv * (dc if pos else dd)
            w2[k + 3] = gv * (dd if pos else dc)
            w3[k + 3] = zero if pos else gv * du
            w4[k] = half * ga[k] * v
        gr = gq[a + 2]
        for m in range(n1 + 3):
            gr[m] += w0[m + 3] + w1[m + 2] + w2[m + 1] + w3[m]
        s0 = gT[a + tr0, tc0:tc0 + n1]
        for k in range(n1):
            s0[k] += w4[k]
        s1 = gT[a + tr1, tc1:tc1 + n1]
        for k in range(n1):
            s1[k] += w4[k]


@jit
def _pad(v, slip, lo, hi):
    """v [n, m] -> [n+4, m+4] with two ghost layers: along the rows' direction (columns) the odd
    reflection about the first and last entries (normal velocity), along the columns' (rows) the
    mirror about walls half a cell beyond (tangential velocity; wall speeds lo, hi; slip)."""
    n, m = v.shape
    P = np.empty((n + 4, m + 4), v.dtype)
    for i in range(n):
        r = i + 2
        for j in range(m):
            P[r, j + 2] = v[i, j]
        P[r, 0] = 2 * v[i, 0] - v[i, 2]
        P[r, 1] = 2 * v[i, 0] - v[i, 1]
        P[r, m + 2] = 2 * v[i, m - 1] - v[i, m - 2]
        P[r, m + 3] = 2 * v[i, m - 1] - v[i, m - 3]
    s, c_lo, c_hi = (1.0, 0.0, 0.0) if slip else (-1.0, 2 * lo, 2 * hi)
    for j in range(m + 4):
        P[0, j] = c_lo + s * P[3, j]
        P[1, j] = c_lo + s * P[2, j]
        P[n + 2, j] = c_hi + s * P[n + 1, j]
        P[n + 3, j] = c_hi + s * P[n, j]
    return P


@jit
def _pad_adjoint(gP, slip, gv):
    """Adds the adjoint of ``_pad`` applied to gP [n+4, m+4] into gv [n, m] (gP is consumed)."""
    n, m = gv.shape
    s = 1.0 if slip else -1.0
    for j in range(m + 4):
        gP[3, j] += s * gP[0, j]
        gP[2, j] += s * gP[1, j]
        gP[n + 1, j] += s * gP[n + 2, j]
        gP[n, j] += s * gP[n + 3, j]
    for i in range(n):
        r = i + 2
        for j in range(m):
            gv[i, j] += gP[r, j + 2]
        gv[i, 0] += 2 * (gP[r, 0] + gP[r, 1])
        gv[i, 2] -= gP[r, 0]
        gv[i, 1] -= gP[r, 1]
        gv[i, m - 1] += 2 * (gP[r, m + 2] + gP[r, m + 3])
        gv[i, m - 2] -= gP[r, m + 2]
        gv[i, m - 3] -= gP[r, m + 3]


# The four flux families, (q, T, tr0, tc0, tr1, tc1) of ``_family_forward``:
#   F_x [H, W+2]     P,  P,  2, 1, 2, 2    U at the cell centres, from the x-faces
#   G_x^T [W+1, H+1] PT, QT, 1, 2, 2, 2    V at the vertices, from the y-faces
#   F_y^T [W, H+2]   QT, QT, 2, 1, 2, 2    V at the cell centres, from the y-faces
#   G_y [H+1, W+1]   Q,  P,  1, 2, 2, 2    U at the vertices, from the x-faces


@jit
def _padded(vx, vy, walls):
    slip, u_bottom, u_top, v_left, v_right = walls
    P, QT = _pad(vx, slip, u_bottom, u_top), _pad(vy.T, slip, v_left, v_right)
    return P, QT, np.ascontiguousarray(P.T), np.ascontiguousarray(QT.T)


@jit
def _fluxes(P, QT, PT, Q):
    """(F_x, G_x^T, F_y^T, G_y) of the padded faces."""
    H, W = P.shape[0] - 4, Q.shape[1] - 4
    Fx, GxT = np.empty((H, W + 2), P.dtype), np.empty((W + 1, H + 1), P.dtype)
    FyT, Gy = np.empty((W, H + 2), P.dtype), np.empty((H + 1, W + 1), P.dtype)
    _family_forward(P, P, 2, 1, 2, 2, Fx)
    _family_forward(PT, QT, 1, 2, 2, 2, GxT)
    _family_forward(QT, QT, 2, 1, 2, 2, FyT)
    _family_forward(Q, P, 1, 2, 2, 2, Gy)
    return Fx, GxT, FyT, Gy


@jit(error_model="numpy")
def _sample_forward(vx, vy, nu, dt, inv_dx, walls, wx, wy):
    H, W = vx.shape[0], vy.shape[1]
    P, QT, PT, Q = _padded(vx, vy, walls)
    Fx, GxT, FyT, Gy = _fluxes(P, QT, PT, Q)
    Gx, Fy = np.ascontiguousarray(GxT.T), np.ascontiguousarray(FyT.T)    # [H+1, W+1], [H+2, W]
    T, four = vx.dtype.type, _constants(vx).four
    nu, dt, inv_dx = T(nu), T(dt), T(inv_dx)
    inv_dx2 = inv_dx * inv_dx
    wx[:, :] = vx
    wy[:, :] = vy
    for i in range(H):
        up, mid, down, f, g0, g1, out = P[i + 1], P[i + 2], P[i + 3], Fx[i], Gx[i], Gx[i + 1], wx[i]
        for j in range(1, W):
            lap = (mid[j + 1] + mid[j + 3] + up[j + 2] + down[j + 2] - four * mid[j + 2]) * inv_dx2
            out[j] += dt * (nu * lap - (f[j + 1] - f[j] + g1[j] - g0[j]) * inv_dx)
    for i in range(1, H):
        up, mid, down, f0, f1, g, out = Q[i + 1], Q[i + 2], Q[i + 3], Fy[i], Fy[i + 1], Gy[i], wy[i]
        for j in range(W):
            lap = (mid[j + 1] + mid[j + 3] + up[j + 2] + down[j + 2] - four * mid[j + 2]) * inv_dx2
            out[j] += dt * (nu * lap - (f1[j] - f0[j] + g[j + 1] - g[j]) * inv_dx)


@jit(error_model="numpy")
def _stencil_adjoint(E, c, out):
    """out[R, C] = c lap(E)[R, C] (the 5-point sum, unscaled by dx) for 1 <= R, C < shape - 1: the
    stencil is symmetric, so this is its adjoint applied to E (E zero outside the faces it acts on)."""
    four = _constants(E).four
    for R in range(1, E.shape[0] - 1):
        up, mid, down, o = E[R - 1], E[R], E[R + 1], out[R]
        for C in range(1, E.shape[1] - 1):
            o[C] = c * (mid[C - 1] + mid[C + 1] + up[C] + down[C] - four * mid[C])


@jit(error_model="numpy")
def _sample_backward(vx, vy, nu, dt, inv_dx, walls, gwx, gwy, gvx, gvy, need_nu, need_dt):
    """Adds dL/dv into gvx, gvy; returns (dL/dnu, dL/dt) (dL/dnu 0 unless need_nu or need_dt: a
    pass over the Laplacian; dL/dt 0 unless need_dt: it recomputes the fluxes). Gather form: Ex,
    Ey hold dL/dw of the updated (interior) faces at their places in P, Q (zero elsewhere), and
    every adjoint reads its neighbours there."""
    H, W = vx.shape[0], vy.shape[1]
    P, QT, PT, Q = _padded(vx, vy, walls)
    T, four = vx.dtype.type, _constants(vx).four
    nu_t, dt_t, inv_dx_t = T(nu), T(dt), T(inv_dx)
    inv_dx2 = inv_dx_t * inv_dx_t
    Ex, Ey = np.zeros_like(P), np.zeros_like(Q)
    for i in range(H):
        Ex[i + 2, 3:W + 2] = gwx[i, 1:W]
    for i in range(1, H):
        Ey[i + 2, 2:W + 2] = gwy[i]
    acc = np.zeros(W + 5, vx.dtype)      # per column (a vectorised loop), then summed
    if need_nu or need_dt:
        for E, V in ((Ex, P), (Ey, Q)):
            for R in range(2, E.shape[0] - 2):
                e, up, mid, down = E[R], V[R - 1], V[R], V[R + 1]
                for C in range(2, E.shape[1] - 2):
                    acc[C] += e[C] * (mid[C - 1] + mid[C + 1] + up[C] + down[C] - four * mid[C]) * inv_dx2
    lap_sum, adv_sum = np.float64(acc.sum()), 0.0    # sum of dL/dw (nu lap v) / nu and of dL/dw (v.grad v)
    if need_dt:
        Fx, GxT, FyT, Gy = _fluxes(P, QT, PT, Q)
        for i in range(H):
            for j in range(1, W):
                adv_sum += Ex[i + 2, j + 2] * (Fx[i, j + 1] - Fx[i, j] + GxT[j, i + 1] - GxT[j, i]) * inv_dx
        for i in range(1, H):
            for j in range(W):
                adv_sum += Ey[i + 2, j + 2] * (FyT[j, i + 1] - FyT[j, i] + Gy[i, j + 1] - Gy[i, j]) * inv_dx
    gP, gQ = np.zeros_like(P), np.zeros_like(Q)
    _stencil_adjoint(Ex, dt_t * nu_t * inv_dx2, gP)
    _stencil_adjoint(Ey, dt_t * nu_t * inv_dx2, gQ)
    s = -dt_t * inv_dx_t                 # w -= dt (flux differences) / dx
    gFx, gGx = np.empty((H, W + 2), vx.dtype), np.empty((H + 1, W + 1), vx.dtype)
    gFy, gGy = np.empty((H + 2, W), vx.dtype), np.empty((H + 1, W + 1), vx.dtype)
    for i in range(H):
        e = Ex[i + 2]
        for k in range(W + 2):
            gFx[i, k] = s * (e[k + 1] - e[k + 2])
    for m in range(H + 1):
        e0, e1 = Ex[m + 1], Ex[m + 2]
        for j in range(W + 1):
            gGx[m, j] = s * (e0[j + 2] - e1[j + 2])
    for k in range(H + 2):
        e0, e1 = Ey[k + 1], Ey[k + 2]
        for j in range(W):
            gFy[k, j] = s * (e0[j + 2] - e1[j + 2])
    for i in range(H + 1):
        e = Ey[i + 2]
        for m in range(W + 1):
            gGy[i, m] = s * (e[m + 1] - e[m + 2])
    gPT, gQT = np.zeros_like(PT), np.zeros_like(QT)
    _family_backward(P, P, 2, 1, 2, 2, gFx, gP, gP)
    _family_backward(PT, QT, 1, 2, 2, 2, np.ascontiguousarray(gGx.T), gPT, gQT)
    _family_backward(QT, QT, 2, 1, 2, 2, np.ascontiguousarray(gFy.T), gQT, gQT)
    _family_backward(Q, P, 1, 2, 2, 2, gGy, gQ, gP)
    gP += gPT.T
    gQT += gQ.T
    gvx += gwx
    gvy += gwy
    _pad_adjoint(gP, walls[0], gvx)
    _pad_adjoint(gQT, walls[0], gvy.T)
    return dt * lap_sum, nu * lap_sum - adv_sum


@jit
def _forward_serial(vx, vy, nu, dt, inv_dx, walls, wx, wy):
    for n in range(vx.shape[0]):
        _sample_forward(vx[n], vy[n], nu[n], dt[n], inv_dx, walls, wx[n], wy[n])


@jit(parallel=True)
def _forward_parallel(vx, vy, nu, dt, inv_dx, walls, wx, wy):
    for n in prange(vx.shape[0]):
        _sample_forward(vx[n], vy[n], nu[n], dt[n], inv_dx, walls, wx[n], wy[n])


@jit
def _backward_serial(vx, vy, nu, dt, inv_dx, walls, gwx, gwy, gvx, gvy, g_nu, g_dt, need_nu, need_dt):
    for n in range(vx.shape[0]):
        g_nu[n], g_dt[n] = _sample_backward(vx[n], vy[n], nu[n], dt[n], inv_dx, walls, gwx[n], gwy[n],
                                            gvx[n], gvy[n], need_nu, need_dt)


@jit(parallel=True)
def _backward_parallel(vx, vy, nu, dt, inv_dx, walls, gwx, gwy, gvx, gvy, g_nu, g_dt, need_nu, need_dt):
    for n in prange(vx.shape[0]):
        g_nu[n], g_dt[n] = _sample_backward(vx[n], vy[n], nu[n], dt[n], inv_dx, walls, gwx[n], gwy[n],
                                            gvx[n], gvy[n], need_nu, need_dt)


def _flat(t: Tensor) -> np.ndarray:
    """[..., rows, cols] -> a C-contiguous numpy view [N, rows, cols] (a copy if t is not contiguous;
    reshaped in numpy, half the cost of torch's reshape + contiguous: ~1700 calls a step)."""
    a = t.detach().numpy()
    if not a.flags.c_contiguous:
        a = np.ascontiguousarray(a)
    return a.reshape(-1, *a.shape[-2:])


@jit
def _face_speed(v, b, v_d, speed, finite):
    """speed[n] = max(speed[n], max over sample n's faces of |v| and |b v_d|) (in the faces'
    dtype, as torch computes them); finite[n] &= every one of them is finite. v, b, v_d: [N, cells]."""
    for n in range(v.shape[0]):
        top, ok = speed[n], finite[n]
        for i in range(v.shape[1]):
            a, c = abs(v[n, i]), abs(b[n, i] * v_d[n, i])
            ok = ok & (a < np.inf) & (c < np.inf)                 # False for inf and NaN
            top = max(top, a, c)
        speed[n], finite[n] = top, ok


def face_speed(v: tuple[Tensor, Tensor], b: tuple[Tensor, Tensor], v_d: tuple[Tensor, Tensor]) -> Tensor:
    """max over each sample's faces of |v| and |b v_d|, [B] float64 (NaN where any is not
    finite), from the face fields [B, 1, ., .] (b, v_d broadcast to v): the sub-step count's
    speed (NumericalFluid._count_substeps) in one compiled pass, not ~20 torch operations."""
    B = v[0].shape[0]
    speed, finite = np.zeros(B), np.ones(B, np.bool_)
    for c, bc, dc in zip(v, b, v_d):
        _face_speed(*(_flat(t.expand_as(c)).reshape(B, -1) for t in (c, bc, dc)), speed, finite)
    speed[~finite] = np.nan
    return torch.from_numpy(speed)


def _per_sample(x: Tensor | float, like: Tensor) -> np.ndarray:
    """A scalar or [B, 1, 1, 1] tensor as one float64 per sample [B * C]."""
    x = torch.as_tensor(x, dtype=torch.float64).detach()
    return torch.broadcast_to(x.reshape(-1, 1) if x.dim() else x, like.shape[:2]).reshape(-1).contiguous().numpy()


class Predict(torch.autograd.Function):
    """(w_x, w_y) = ``numerical.predict``'s momentum update of the faces v = (v_x [B, C, H, W+1],
    v_y [B, C, H+1, W]) in m/s, with nu [m^2/s] and dt [s] scalars or [B, 1, 1, 1], cell size dx
    [m], ``walls`` a grid.WallBC; the Koren scheme, CPU tensors. Differentiable in v, nu and dt."""

    @staticmethod
    def forward(ctx, vx: Tensor, vy: Tensor, nu, dt, dx: float, walls):
        wall_args = (bool(walls.slip), float(walls.u_bottom), float(walls.u_top), float(walls.v_left),
                     float(walls.v_right))
        nu_n, dt_n = _per_sample(nu, vx), _per_sample(dt, vx)
        wx, wy = torch.empty_like(vx, memory_format=torch.contiguous_format), torch.empty_like(
            vy, memory_format=torch.contiguous_format)
        each_sample(_forward_serial, _forward_parallel, _flat(vx), _flat(vy), nu_n, dt_n, 1.0 / dx, wall_args,
                    _flat(wx), _flat(wy))
        ctx.save_for_backward(vx, vy)
        ctx.args = (nu_n, dt_n, 1.0 / dx, wall_args)
        ctx.shapes = [(torch.as_tensor(x).shape, isinstance(x, Tensor)) for x in (nu, dt)]
        return wx, wy

    @staticmethod
    def backward(ctx, gwx: Tensor, gwy: Tensor):
        vx, vy = ctx.saved_tensors
        nu_n, dt_n, inv_dx, wall_args = ctx.args
        gvx, gvy = torch.zeros(vx.shape, dtype=vx.dtype), torch.zeros(vy.shape, dtype=vy.dtype)
        g = np.zeros((2, nu_n.shape[0]))
        each_sample(_backward_serial, _backward_parallel, _flat(vx), _flat(vy), nu_n, dt_n, inv_dx, wall_args,
                    _flat(gwx), _flat(gwy), _flat(gvx), _flat(gvy), g[0], g[1], bool(ctx.needs_input_grad[2]),
                    bool(ctx.needs_input_grad[3]))
        g_params = []
        for (shape, is_tensor), gs, need in zip(ctx.shapes, g, ctx.needs_input_grad[2:4]):
            if not (is_tensor and need):
                g_params.append(None)
                continue
            per_sample = torch.from_numpy(gs).to(vx.dtype).reshape(*vx.shape[:2], 1, 1)
            g_params.append(per_sample.sum_to_size(shape) if len(shape) else per_sample.sum())
        return gvx, gvy, *g_params, None, None


# --------------------------------------------------------------------------------------------
# The penalise -> project passes: u = w + b (v_d - w) (u = b v_d on the box-wall faces),
# phi = L^+ div u, w' = u - grad phi (grad phi = 0 on the wall faces)
# --------------------------------------------------------------------------------------------


@jit(inline="always")
def _blend_row(w, b, d, u, p, lo, hi):
    """u = w + b (d - w) on entries lo..hi-1 of one row, and the increment p += u - w (a loop
    without branches: it vectorises)."""
    for j in range(lo, hi):
        u[j] = w[j] + b[j] * (d[j] - w[j])
        p[j] += u[j] - w[j]


@jit(inline="always")
def _wall_face(w, b, d, u, p, j):
    """u = b v_d on a box-wall face (entry j of one row), and the increment p += u - w."""
    u[j] = b[j] * d[j]
    p[j] += u[j] - w[j]


@jit
def _penalize_divergence_sample(wx, wy, bx, by, dx_, dy_, inv_dx, ux, uy, div, px, py):
    """One sample's u = w + b (v_d - w) on the interior faces, b v_d on the wall faces; div =
    div u; the penalisation's increment summed over the passes: (px, py) += u - w. The wall faces
    are set apart from the rows' loops, which then have no branches and vectorise (69 -> ~25 us on
    100 x 300, float32)."""
    H, W = div.shape
    inv_dx = div.dtype.type(inv_dx)
    for i in range(H):
        _wall_face(wx[i], bx[i], dx_[i], ux[i], px[i], 0)
        _blend_row(wx[i], bx[i], dx_[i], ux[i], px[i], 1, W)
        _wall_face(wx[i], bx[i], dx_[i], ux[i], px[i], W)
    for i in range(H + 1):
        if i == 0 or i == H:
            for j in range(W):
                _wall_face(wy[i], by[i], dy_[i], uy[i], py[i], j)
        else:
            _blend_row(wy[i], by[i], dy_[i], uy[i], py[i], 0, W)
    for i in range(H):
        a, b0, b1, d = ux[i], uy[i], uy[i + 1], div[i]
        for j in range(W):
            d[j] = (a[j + 1] - a[j] + b1[j] - b0[j]) * inv_dx


@jit
def _subtract_gradient_sample(ux, uy, phi, inv_dx, vx, vy, phi_sum):
    """One sample's v = u - grad phi on the interior faces, u on the wall faces; phi summed over
    the passes (phi_sum += phi)."""
    H, W = phi.shape
    inv_dx = phi.dtype.type(inv_dx)
    for i in range(H):
        for j in range(W):
            phi_sum[i, j] += phi[i, j]
    for i in range(H):
        vx[i, 0], vx[i, W] = ux[i, 0], ux[i, W]
        for j in range(1, W):
            vx[i, j] = ux[i, j] - (phi[i, j] - phi[i, j - 1]) * inv_dx
    for j in range(W):
        vy[0, j], vy[H, j] = uy[0, j], uy[H, j]
    for i in range(1, H):
        for j in range(W):
            vy[i, j] = uy[i, j] - (phi[i, j] - phi[i - 1, j]) * inv_dx


@jit
def _gradient_adjoint_sample(gx, gy, inv_dx, out):
    """One sample's out += -grad^T g = div of g with its wall faces zeroed (the adjoint of
    - grad phi)."""
    H, W = out.shape
    zero, inv_dx = out.dtype.type(0.0), out.dtype.type(inv_dx)
    for i in range(H):
        for j in range(W):
            s = zero
            if j >= 1:
                s -= gx[i, j]
            if j + 1 <= W - 1:
                s += gx[i, j + 1]
            if i >= 1:
                s -= gy[i, j]
            if i + 1 <= H - 1:
                s += gy[i + 1, j]
            out[i, j] += s * inv_dx


@jit(inline="always")
def _blend_adjoint(g, wall, w, b, d, zero):
    """(dL/dw, dL/db, dL/dv_d) of u = b v_d (a wall face) or w + b (v_d - w) for dL/du = g (zero:
    0 in g's dtype)."""
    if wall:
        return zero, g * d, g * b
    return g - g * b, g * (d - w), g * b


@jit
def _penalize_divergence_adjoint_sample(gvx, gvy, gpx, gpy, gdiv, wx, wy, bx, by, dx_, dy_, inv_dx, gwx, gwy,
                                        gbx, gby, gdx, gdy):
    """One sample's adjoint of one pass u = penalize(w), div = div u, pen += u - w: given dL/du =
    gv + gp (through the projection and the increment) and dL/ddiv, writes dL/dw (gwx, gwy; the
    increment's -gp included), adds dL/db and dL/dv_d."""
    H, W = gdiv.shape
    zero, inv_dx = gdiv.dtype.type(0.0), gdiv.dtype.type(inv_dx)
    for i in range(H):
        for j in range(W + 1):
            g = (gvx[i, j] + gpx[i, j]) + ((gdiv[i, j - 1] if j >= 1 else zero) - (gdiv[i, j] if j < W else zero)) * inv_dx
            gwx[i, j], gb, gd = _blend_adjoint(g, j == 0 or j == W, wx[i, j], bx[i, j], dx_[i, j], zero)
            gwx[i, j] -= gpx[i, j]
            gbx[i, j] += gb
            gdx[i, j] += gd
    for i in range(H + 1):
        for j in range(W):
            g = (gvy[i, j] + gpy[i, j]) + ((gdiv[i - 1, j] if i >= 1 else zero) - (gdiv[i, j] if i < H else zero)) * inv_dx
            gwy[i, j], gb, gd = _blend_adjoint(g, i == 0 or i == H, wy[i, j], by[i, j], dy_[i, j], zero)
            gwy[i, j] -= gpy[i, j]
            gby[i, j] += gb
            gdy[i, j] += gd


@jit
def _constrain_sample(wx, wy, bx, by, dx_, dy_, inv_dx, pivots, pdx, passes, keep, tx, ty, slot, phi_sum, px, py):
    """One sample's K passes u = penalize(w), (w, phi) = project(u) from w = (wx, wy); returns v;
    phi_sum and the increments (px, py) accumulate over the passes; with ``keep`` each pass's
    input w goes to the tape (tx, ty)[slot + k] (what ``_constrain_adjoint_sample`` reads). The
    Poisson solves run compiled (``dct.inverse_sample``), so the passes never return to Python."""
    div = np.empty(phi_sum.shape, wx.dtype)
    for k in range(passes):
        if keep:
            tx[slot + k] = wx
            ty[slot + k] = wy
        ux, uy = np.empty_like(wx), np.empty_like(wy)
        _penalize_divergence_sample(wx, wy, bx, by, dx_, dy_, inv_dx, ux, uy, div, px, py)
        phi = inverse_sample(div, pivots, pdx)
        wx, wy = np.empty_like(ux), np.empty_like(uy)
        _subtract_gradient_sample(ux, uy, phi, inv_dx, wx, wy, phi_sum)
    return wx, wy


@jit
def _constrain_adjoint_sample(gvx, gvy, gphi, gpx, gpy, tx, ty, slot, passes, bx, by, dx_, dy_, inv_dx, pivots,
                              pdx, gbx, gby, gdx, gdy):
    """dL/dw of ``_constrain_sample`` (its pass inputs on the tape at slot..slot+K-1) for dL/d(v,
    phi sum, increments) = (gv, gphi, gp); adds dL/d(b_x, b_y, v_d,x, v_d,y) into the g*."""
    for k in range(passes - 1, -1, -1):
        g_phi = gphi.copy()
        _gradient_adjoint_sample(gvx, gvy, inv_dx, g_phi)
        g_div = inverse_sample(g_phi, pivots, pdx)
        nx, ny = np.empty_like(gvx), np.empty_like(gvy)
        _penalize_divergence_adjoint_sample(gvx, gvy, gpx, gpy, g_div, tx[slot + k], ty[slot + k], bx, by, dx_, dy_,
                                            inv_dx, nx, ny, gbx, gby, gdx, gdy)
        gvx, gvy = nx, ny
    return gvx, gvy


@jit
def _sample_steps(vx, vy, bx, by, dx_, dy_, nu, dt, count, inv_dx, walls, pivots, pdx, passes, keep, tx, ty,
                  phi_sum, pen_x, pen_y):
    """One sample's ``count`` Heun sub-steps (``NumericalFluid._substep``): v1 = C(P(v)), v' =
    C((v + P(v1)) / 2), C ``_constrain_sample``, in one compiled call; returns v'. phi_sum and
    (pen_x, pen_y) (zeros on entry) receive the sums over the sub-steps of phi1/2 + phi2 and of
    pen1/2 + pen2. With ``keep``, sub-step s fills the tape (tx, ty)[s (2 + 2K) + ...]: v, v1, the
    first stage's K pass inputs, the second's."""
    half = _constants(vx).half
    stride = 2 + 2 * passes
    for s in range(count):
        base = s * stride
        if keep:
            tx[base] = vx
            ty[base] = vy
        w1x, w1y = np.empty_like(vx), np.empty_like(vy)
        _sample_forward(vx, vy, nu, dt, inv_dx, walls, w1x, w1y)
        phi1, p1x, p1y = np.zeros_like(phi_sum), np.zeros_like(vx), np.zeros_like(vy)
        v1x, v1y = _constrain_sample(w1x, w1y, bx, by, dx_, dy_, inv_dx, pivots, pdx, passes, keep, tx, ty, base + 2,
                                     phi1, p1x, p1y)
        if keep:
            tx[base + 1] = v1x
            ty[base + 1] = v1y
        w2x, w2y = np.empty_like(vx), np.empty_like(vy)
        _sample_forward(v1x, v1y, nu, dt, inv_dx, walls, w2x, w2y)
        w2x, w2y = half * (vx + w2x), half * (vy + w2y)
        phi2, p2x, p2y = np.zeros_like(phi_sum), np.zeros_like(vx), np.zeros_like(vy)
        vx, vy = _constrain_sample(w2x, w2y, bx, by, dx_, dy_, inv_dx, pivots, pdx, passes, keep, tx, ty,
                                   base + 2 + passes, phi2, p2x, p2y)
        phi_sum += half * phi1 + phi2
        pen_x += half * p1x + p2x
        pen_y += half * p1y + p2y
    return vx, vy


@jit
def _sample_steps_adjoint(tx, ty, gvx, gvy, gphi, gpx, gpy, bx, by, dx_, dy_, nu, dt, count, inv_dx, walls, pivots,
                          pdx, passes, need_nu, gbx, gby, gdx, gdy):
    """The adjoint of ``_sample_steps`` from its tape for dL/d(v', phi sum, pen sum) = (gv, gphi,
    gp): returns (dL/dv_x, dL/dv_y, dL/dnu) and adds dL/d(b_x, b_y, v_d,x, v_d,y) into the g*."""
    half = _constants(gvx).half
    stride = 2 + 2 * passes
    g_nu = 0.0
    gvx, gvy = gvx.copy(), gvy.copy()
    for s in range(count - 1, -1, -1):
        base = s * stride
        g2x, g2y = _constrain_adjoint_sample(gvx, gvy, gphi, gpx, gpy, tx, ty, base + 2 + passes, passes, bx, by,
                                             dx_, dy_, inv_dx, pivots, pdx, gbx, gby, gdx, gdy)
        g1x, g1y = np.zeros_like(g2x), np.zeros_like(g2y)
        g_nu += _sample_backward(tx[base + 1], ty[base + 1], nu, dt, inv_dx, walls, half * g2x, half * g2y, g1x,
                                 g1y, need_nu, False)[0]
        g1x, g1y = _constrain_adjoint_sample(g1x, g1y, half * gphi, half * gpx, half * gpy, tx, ty, base + 2, passes,
                                             bx, by, dx_, dy_, inv_dx, pivots, pdx, gbx, gby, gdx, gdy)
        gvx, gvy = half * g2x, half * g2y
        g_nu += _sample_backward(tx[base], ty[base], nu, dt, inv_dx, walls, g1x, g1y, gvx, gvy, need_nu, False)[0]
    return gvx, gvy, g_nu


def _steps(v, masks, nu_n, dt_n, counts, inv_dx, walls, inverse, passes, keep, guesses, solves):
    """``SplitStep``'s sub-steps on numpy samples (v = (v_x [N, H, W+1], v_y [N, H+1, W]), masks
    (b_x, b_y, v_d,x, v_d,y) alike; counts [N] the samples' sub-step counts), one compiled call a
    sample: returns (v', sum of phi, sum of pen (x, y), the samples' tapes if keep, else empty).
    ``guesses`` and ``solves``: unused (the passes' solves are direct; ``_immersed_steps``)."""
    N, H, W = v[1].shape[0], v[0].shape[1], v[1].shape[2]
    out = (np.empty_like(v[0]), np.empty_like(v[1]))
    phi_sum, pen = np.zeros((N, H, W), v[0].dtype), (np.zeros_like(v[0]), np.zeros_like(v[1]))
    tapes = []
    for n in range(N):
        size = int(counts[n]) * (2 + 2 * passes) if keep else 0       # no tape without a gradient
        tape = (np.empty((size, H, W + 1), v[0].dtype), np.empty((size, H + 1, W), v[0].dtype))
        out[0][n], out[1][n] = _sample_steps(v[0][n], v[1][n], *(m[n] for m in masks), nu_n[n], dt_n[n], int(counts[n]),
                                             inv_dx, walls, inverse.pivots, inverse.dx, passes, keep, *tape,
                                             phi_sum[n], pen[0][n], pen[1][n])
        if keep:
            tapes.append(tape)
    return out, phi_sum, pen, tapes


def _steps_adjoint(tapes, gv, gphi_all, gpen_all, masks, counts, nu_n, dt_n, inv_dx, walls, inverse, passes, need_nu):
    """The adjoint of ``_steps`` from its tapes, for dL/d(v', phi sum, pen sum) = (gv, gphi_all,
    gpen_all): returns (dL/dv, dL/d(b_x, b_y, v_d,x, v_d,y), dL/dnu per sample [N] (zeros unless
    need_nu))."""
    gmasks = tuple(np.zeros_like(m) for m in masks)
    g_nu = np.zeros(len(nu_n))
    out = (np.empty_like(gv[0]), np.empty_like(gv[1]))
    for n, tape in enumerate(tapes):
        out[0][n], out[1][n], g = _sample_steps_adjoint(*tape, gv[0][n], gv[1][n], gphi_all[n], gpen_all[0][n],
                                                        gpen_all[1][n], *(m[n] for m in masks), nu_n[n], dt_n[n],
                                                        int(counts[n]), inv_dx, walls, inverse.pivots, inverse.dx,
                                                        passes, need_nu, *(m[n] for m in gmasks))
        g_nu[n] = g                                   # 0 unless need_nu (``_sample_backward``)
    return out, gmasks, g_nu


# --------------------------------------------------------------------------------------------
# The joint penalisation + projection stage (numerical.immerse) and its sub-steps, with adjoints
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Immersion:
    """``SplitStep``'s stage for a joint solve (``numerical.immerse``): lambda [1/s], the PCG's
    relative tolerances of the forward and the adjoint solves and its iteration cap."""

    stiffness: float
    tol: float
    adjoint_tol: float
    max_iter: int


@jit
def _immerse_sample(wx, wy, sx, sy, dx_, dy_, cx, cy, a, inv_dx, pivots, pdx, cells, band, width, perm, inverse,
                    local, tol, max_iter, phi, px, py):
    """One sample's ``numerical.immerse`` from w = (wx, wy): u = c (w + a s v_d) on the interior
    faces (c = 1 / (1 + a s), a = lambda dt), s v_d on the wall faces; -div(c grad phi) = -div u
    by ``_pcg_sample`` from phi (the start, overwritten with the mean-free solution); returns v = u
    - c grad phi and adds the increment v - w + grad phi to (px, py)."""
    H, W = phi.shape
    a, inv_dx = wx.dtype.type(a), wx.dtype.type(inv_dx)
    ux, uy = np.empty_like(wx), np.empty_like(wy)
    for i in range(H):
        ux[i, 0], ux[i, W] = sx[i, 0] * dx_[i, 0], sx[i, W] * dx_[i, W]
        for j in range(1, W):
            ux[i, j] = cx[i, j] * (wx[i, j] + a * sx[i, j] * dx_[i, j])
    for j in range(W):
        uy[0, j], uy[H, j] = sy[0, j] * dy_[0, j], sy[H, j] * dy_[H, j]
    for i in range(1, H):
        for j in range(W):
            uy[i, j] = cy[i, j] * (wy[i, j] + a * sy[i, j] * dy_[i, j])
    f = np.empty_like(phi)
    for i in range(H):
        for j in range(W):
            f[i, j] = (ux[i, j] - ux[i, j + 1] + uy[i, j] - uy[i + 1, j]) * inv_dx
    f -= f.mean()
    phi -= phi.mean()
    _pcg_sample(cx, cy, f, phi, inv_dx * inv_dx, pivots, pdx, cells, band, width, perm, inverse, local, tol, max_iter)
    phi -= phi.mean()
    vx, vy = ux.copy(), uy.copy()
    for i in range(H):
        for j in range(1, W):
            g = (phi[i, j] - phi[i, j - 1]) * inv_dx
            vx[i, j] -= cx[i, j] * g
            px[i, j] += g
    for i in range(1, H):
        for j in range(W):
            g = (phi[i, j] - phi[i - 1, j]) * inv_dx
            vy[i, j] -= cy[i, j] * g
            py[i, j] += g
    px += vx - wx
    py += vy - wy
    return vx, vy


@jit(inline="always")
def _immerse_adjoint_faces(gt, gp, lam_in, lam_out, phi_in, phi_out, w, s, d, c, a, inv_dx, interior):
    """One face's part of ``_immerse_adjoint_sample``: (dL/dw, dL/ds, dL/dv_d) for dL/dv + dL/dpen
    = gt, dL/dpen = gp, the adjoint potential lam and the potential phi on the face's two cells
    (``_in`` the cell the face's normal points into; 0 outside the box)."""
    gu = gt + (lam_in - lam_out) * inv_dx                   # -div^T lam (grad lam inside)
    if not interior:
        return -gp, gu * d, gu * s
    gc = -(phi_in - phi_out) * inv_dx * gu
    acc = a * c * c
    return gu * c - gp, gu * acc * (d - w) - gc * acc, gu * c * a * s


@jit
def _immerse_adjoint_sample(gvx, gvy, gphi, gpx, gpy, wx, wy, phi, sx, sy, dx_, dy_, cx, cy, a, inv_dx, pivots, pdx,
                            cells, band, width, perm, inverse, local, tol, max_iter, gsx, gsy, gdx, gdy):
    """dL/dw of ``_immerse_sample`` (input w, solution phi) for dL/d(v, phi, increment) = (gv,
    gphi, gp); adds dL/d(s, v_d) into the g*. With gt = gv + gp: lam = A^+ (gphi + grad^T(gp - c
    gt)) (A = -div(c grad .), symmetric: the same PCG, from 0), dL/du = gt - div^T lam, dL/dc =
    -grad phi (gt + grad lam) (``fluid.pressure.WeightedPoisson``), then through u = c (w + a s
    v_d), c = 1 / (1 + a s)."""
    H, W = phi.shape
    zero, a, inv_dx = wx.dtype.type(0.0), wx.dtype.type(a), wx.dtype.type(inv_dx)
    gtx, gty = gvx + gpx, gvy + gpy
    rhs = gphi.copy()
    _gradient_adjoint_sample(cx * gtx - gpx, cy * gty - gpy, inv_dx, rhs)
    rhs -= rhs.mean()
    lam = np.zeros_like(rhs)
    _pcg_sample(cx, cy, rhs, lam, inv_dx * inv_dx, pivots, pdx, cells, band, width, perm, inverse, local, tol,
                max_iter)
    lam -= lam.mean()
    gwx, gwy = np.empty_like(wx), np.empty_like(wy)
    for i in range(H):
        for j in range(W + 1):
            l_in, p_in = (lam[i, j], phi[i, j]) if j < W else (zero, zero)
            l_out, p_out = (lam[i, j - 1], phi[i, j - 1]) if j > 0 else (zero, zero)
            gwx[i, j], gs, gd = _immerse_adjoint_faces(gtx[i, j], gpx[i, j], l_in, l_out, p_in, p_out, wx[i, j],
                                                       sx[i, j], dx_[i, j], cx[i, j], a, inv_dx, 0 < j < W)
            gsx[i, j] += gs
            gdx[i, j] += gd
    for i in range(H + 1):
        for j in range(W):
            l_in, p_in = (lam[i, j], phi[i, j]) if i < H else (zero, zero)
            l_out, p_out = (lam[i - 1, j], phi[i - 1, j]) if i > 0 else (zero, zero)
            gwy[i, j], gs, gd = _immerse_adjoint_faces(gty[i, j], gpy[i, j], l_in, l_out, p_in, p_out, wy[i, j],
                                                       sy[i, j], dy_[i, j], cy[i, j], a, inv_dx, 0 < i < H)
            gsy[i, j] += gs
            gdy[i, j] += gd
    return gwx, gwy


@jit
def _sample_immersed_steps(vx, vy, sx, sy, dx_, dy_, cx, cy, a, nu, dt, count, inv_dx, walls, pivots, pdx, cells, band,
                           width, perm, inverse, local, tol, max_iter, guess, keep, tx, ty, tphi, phi_sum, pen_x,
                           pen_y):
    """One sample's ``count`` Heun sub-steps with the joint stage I = ``_immerse_sample`` (v1 =
    I(P(v)), v' = I((v + P(v1)) / 2); each solve starts from the one before, the first from 0, or
    with a ``guess`` [2 count, H, W] (else [0, H, W]) solve k from guess[k]), in one compiled call;
    returns v'. tphi[2 s + ...] receives sub-step s's phi1, phi2; phi_sum and (pen_x, pen_y)
    (zeros on entry) the sums of phi1/2 + phi2 and of pen1/2 + pen2. With ``keep``, sub-step s
    fills the tape (tx, ty)[4 s + ...] = v, v1, the stages' inputs w1, w2."""
    half = _constants(vx).half
    phi = np.zeros_like(phi_sum)
    replay = guess.shape[0] > 0
    for s in range(count):
        w1x, w1y = np.empty_like(vx), np.empty_like(vy)
        _sample_forward(vx, vy, nu, dt, inv_dx, walls, w1x, w1y)
        p1x, p1y = np.zeros_like(vx), np.zeros_like(vy)
        if replay:
            phi[:] = guess[2 * s]
        v1x, v1y = _immerse_sample(w1x, w1y, sx, sy, dx_, dy_, cx, cy, a, inv_dx, pivots, pdx, cells, band, width,
                                   perm, inverse, local, tol, max_iter, phi, p1x, p1y)
        tphi[2 * s] = phi
        w2x, w2y = np.empty_like(vx), np.empty_like(vy)
        _sample_forward(v1x, v1y, nu, dt, inv_dx, walls, w2x, w2y)
        w2x, w2y = half * (vx + w2x), half * (vy + w2y)
        if keep:
            tx[4 * s], ty[4 * s], tx[4 * s + 1], ty[4 * s + 1] = vx, vy, v1x, v1y
            tx[4 * s + 2], ty[4 * s + 2], tx[4 * s + 3], ty[4 * s + 3] = w1x, w1y, w2x, w2y
        p2x, p2y = np.zeros_like(vx), np.zeros_like(vy)
        if replay:
            phi[:] = guess[2 * s + 1]
        vx, vy = _immerse_sample(w2x, w2y, sx, sy, dx_, dy_, cx, cy, a, inv_dx, pivots, pdx, cells, band, width,
                                 perm, inverse, local, tol, max_iter, phi, p2x, p2y)
        tphi[2 * s + 1] = phi
        phi_sum += half * tphi[2 * s] + phi
        pen_x += half * p1x + p2x
        pen_y += half * p1y + p2y
    return vx, vy


@jit
def _sample_immersed_steps_adjoint(tx, ty, tphi, gvx, gvy, gphi, gpx, gpy, sx, sy, dx_, dy_, cx, cy, a, nu, dt, count,
                                   inv_dx, walls, pivots, pdx, cells, band, width, perm, inverse, local, tol, max_iter,
                                   need_nu, gsx, gsy, gdx, gdy):
    """The adjoint of ``_sample_immersed_steps`` from its tape for dL/d(v', phi sum, pen sum) =
    (gv, gphi, gp): returns (dL/dv_x, dL/dv_y, dL/dnu) and adds dL/d(s_x, s_y, v_d,x, v_d,y) into
    the g*."""
    half = _constants(gvx).half
    g_nu = 0.0
    gvx, gvy = gvx.copy(), gvy.copy()
    for s in range(count - 1, -1, -1):
        g2x, g2y = _immerse_adjoint_sample(gvx, gvy, gphi, gpx, gpy, tx[4 * s + 3], ty[4 * s + 3], tphi[2 * s + 1],
                                           sx, sy, dx_, dy_, cx, cy, a, inv_dx, pivots, pdx, cells, band, width, perm,
                                           inverse, local, tol, max_iter, gsx, gsy, gdx, gdy)
        g1x, g1y = np.zeros_like(g2x), np.zeros_like(g2y)
        g_nu += _sample_backward(tx[4 * s + 1], ty[4 * s + 1], nu, dt, inv_dx, walls, half * g2x, half * g2y, g1x,
                                 g1y, need_nu, False)[0]
        g1x, g1y = _immerse_adjoint_sample(g1x, g1y, half * gphi, half * gpx, half * gpy, tx[4 * s + 2],
                                           ty[4 * s + 2], tphi[2 * s], sx, sy, dx_, dy_, cx, cy, a, inv_dx, pivots,
                                           pdx, cells, band, width, perm, inverse, local, tol, max_iter, gsx, gsy,
                                           gdx, gdy)
        gvx, gvy = half * g2x, half * g2y
        g_nu += _sample_backward(tx[4 * s], ty[4 * s], nu, dt, inv_dx, walls, g1x, g1y, gvx, gvy, need_nu, False)[0]
    return gvx, gvy, g_nu


def _immersion_weights(masks, n: int, immersion: Immersion, dt_n) -> tuple:
    """(a, c) of sample n: a = lambda dt and the face weights c = 1 / (1 + a s) in the masks'
    dtype (s = masks[0:2])."""
    a = immersion.stiffness * dt_n[n]
    return a, tuple(1 / (1 + s.dtype.type(a) * s[n]) for s in masks[:2])


def _immersed_steps(v, masks, nu_n, dt_n, counts, inv_dx, walls, inverse, immersion, keep, guesses, solves):
    """``_steps`` with the joint stage (``Immersion``): per sample the weights c
    (``_immersion_weights``), the Schwarz preconditioner's subdomain factor of c
    (``fluid.pressure.subdomain``, once a step), then ``_sample_immersed_steps``, its solves
    started from ``guesses`` [N, 2 n_max, H, W] (None: each from the one before) and written to
    ``solves`` (alike). The tapes hold (tape, the factor's arrays) a sample."""
    N, H, W = v[1].shape[0], v[0].shape[1], v[1].shape[2]
    out = (np.empty_like(v[0]), np.empty_like(v[1]))
    phi_sum, pen = np.zeros((N, H, W), v[0].dtype), (np.zeros_like(v[0]), np.zeros_like(v[1]))
    none = np.empty((0, H, W), v[0].dtype)
    tapes = []
    for n in range(N):
        a, c = _immersion_weights(masks, n, immersion, dt_n)
        solver = local_solver(*subdomain(*(w.astype(np.float64) for w in c), 1 / inv_dx))
        count = int(counts[n])
        size = count if keep else 0
        tape = (np.empty((4 * size, H, W + 1), v[0].dtype), np.empty((4 * size, H + 1, W), v[0].dtype),
                solves[n, :2 * count])
        guess = none if guesses is None else guesses[n, :2 * count]
        out[0][n], out[1][n] = _sample_immersed_steps(
            v[0][n], v[1][n], *(m[n] for m in masks), *c, a, nu_n[n], dt_n[n], count, inv_dx, walls,
            inverse.pivots, inverse.dx, *solver, immersion.tol, immersion.max_iter, guess, keep, *tape, phi_sum[n],
            pen[0][n], pen[1][n])
        if keep:
            tapes.append((tape, solver))
    return out, phi_sum, pen, tapes


def _immersed_steps_adjoint(tapes, gv, gphi_all, gpen_all, masks, counts, nu_n, dt_n, inv_dx, walls, inverse,
                            immersion, need_nu):
    """The adjoint of ``_immersed_steps`` (``_steps_adjoint``'s contract)."""
    gmasks = tuple(np.zeros_like(m) for m in masks)
    g_nu = np.zeros(len(nu_n))
    out = (np.empty_like(gv[0]), np.empty_like(gv[1]))
    for n, (tape, solver) in enumerate(tapes):
        a, c = _immersion_weights(masks, n, immersion, dt_n)
        out[0][n], out[1][n], g_nu[n] = _sample_immersed_steps_adjoint(
            *tape, gv[0][n], gv[1][n], gphi_all[n], gpen_all[0][n], gpen_all[1][n], *(m[n] for m in masks), *c, a,
            nu_n[n], dt_n[n], int(counts[n]), inv_dx, walls, inverse.pivots, inverse.dx, *solver,
            immersion.adjoint_tol, immersion.max_iter, need_nu, *(m[n] for m in gmasks))
    return out, gmasks, g_nu


def _joined(parts: list):
    """The chunks' results put back together along the samples: arrays concatenated, lists and
    tuples element-wise; one chunk's as it is."""
    if len(parts) == 1:
        return parts[0]
    if isinstance(parts[0], (list, tuple)):
        return type(parts[0])(_joined(list(p)) for p in zip(*parts))
    return np.concatenate(parts)


class SplitStep(torch.autograd.Function):
    """The sub-steps of one step (``NumericalFluid``'s loop over ``_substep`` and ``_constrain``),
    compiled loops with hand-written adjoints, in one call: per sub-step v1 = C(P(v)), v' = C((v +
    P(v1)) / 2), P the predictor (``Predict``'s loops), C the stage: the split scheme's K penalise
    -> project passes (``stage`` = K, an int), or the joint penalisation + projection solve
    (``stage`` an ``Immersion``; ``numerical.immerse``); sample b keeps its state after its own n_b
    sub-steps.

    Inputs: v = (v_x [B, C, H, W+1], v_y [B, C, H+1, W]) in m/s, the face masks b (the joint
    stage's weight s) and body velocities v_d (broadcast to v's shapes), nu [m^2/s] and dt [s]
    (scalars or [B, 1, 1, 1]; dt is not differentiated), n [B] (int64 tensor), inverse
    (``dct.neumann_inverse``, v's dtype), dx [m], walls (grid.WallBC), stage, guess (the joint
    stage's starts, a former call's ``solves`` from the same inputs, or None). Returns (v'_x,
    v'_y, sum over the sub-steps of phi1/2 + phi2 [m^2/s], of the penalisation's increments
    pen1/2 + pen2 (x, y) [m/s], solves: the joint stages' potentials [B, C, 2 max(n), H, W], phi1
    and phi2 of each sub-step, zeros past a sample's own; [B, C, 0, H, W] with the passes, not
    differentiable). CPU tensors; differentiable in v, b, v_d and nu. When a gradient is wanted
    the forward keeps what the adjoints read (each sub-step's v and v1 and the stages' inputs: 4 +
    4 K fields a sub-step with the passes, 8 and the two potentials with the joint stage, whose
    preconditioner factors serve the backward's solves too), in place of the ~100 taped ops and
    autograd nodes a step costs the torch loop."""

    @staticmethod
    def forward(ctx, vx, vy, bx, by, dx_, dy_, nu, dt, n, inverse, dx: float, walls, stage, guess=None):
        shapes = (vx.shape, vy.shape)
        wall_args = (bool(walls.slip), float(walls.u_bottom), float(walls.u_top), float(walls.v_left),
                     float(walls.v_right))
        masks = tuple(_flat(t.expand_as(w)) for t, w in ((bx, vx), (by, vy), (dx_, vx), (dy_, vy)))
        nu_n, dt_n = _per_sample(nu, vx), _per_sample(dt, vx)
        counts = np.repeat(n.numpy(), vx.shape[1])                       # per flattened sample
        args = (1.0 / dx, wall_args, inverse, stage)
        chunks = sample_chunks(len(counts))
        steps, ctx.adjoint = (_steps, _steps_adjoint) if isinstance(stage, int) else \
            (_immersed_steps, _immersed_steps_adjoint)
        N, H, W = len(counts), vy.shape[-2] - 1, vy.shape[-1]
        solves = np.zeros((N, 0 if isinstance(stage, int) else 2 * int(counts.max()), H, W), _flat(vx).dtype)
        guesses = None if guess is None else np.ascontiguousarray(guess.detach().reshape(solves.shape).numpy(),
                                                                  solves.dtype)
        out = in_sample_chunks(steps, chunks, (_flat(vx), _flat(vy)), masks, nu_n, dt_n, counts, *args,
                               any(ctx.needs_input_grad), guesses, solves)
        v, phi_sum, pen_sum = (_joined([o[k] for o in out]) for k in range(3))
        ctx.save_for_backward(vx, vy, bx, by, dx_, dy_)
        ctx.tapes, ctx.chunks, ctx.counts = [o[3] for o in out], chunks, counts
        ctx.args = (nu_n, dt_n, *args)
        ctx.nu_shape = (torch.as_tensor(nu).shape, isinstance(nu, torch.Tensor))
        phi_shape = (*vx.shape[:-1], vx.shape[-1] - 1)
        solves = torch.from_numpy(solves).reshape(*vx.shape[:2], -1, H, W)
        ctx.mark_non_differentiable(solves)
        return (*(torch.from_numpy(a).reshape(shape) for a, shape in zip(v, shapes)),
                torch.from_numpy(phi_sum).reshape(phi_shape),
                *(torch.from_numpy(a).reshape(shape) for a, shape in zip(pen_sum, shapes)), solves)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, gvx, gvy, gphi, gpx, gpy, _gsolves):
        vx, vy, *inputs = ctx.saved_tensors
        masks = tuple(_flat(t.expand_as(w)) for t, w in zip(inputs, (vx, vy, vx, vy)))
        out = in_sample_chunks(ctx.adjoint, ctx.chunks, [_flat(g) for g in (gvx, gvy)], _flat(gphi),
                               (_flat(gpx), _flat(gpy)), masks, ctx.counts, *ctx.args,
                               bool(ctx.needs_input_grad[6]), each=ctx.tapes)
        gv, gmasks, g_nu = (_joined([o[k] for o in out]) for k in range(3))
        shapes = (vx.shape, vy.shape, vx.shape, vy.shape)
        grads = [torch.from_numpy(g).reshape(like).sum_to_size(t.shape) if t.requires_grad else None
                 for g, like, t in zip(gmasks, shapes, inputs)]
        shape, is_tensor = ctx.nu_shape
        g_nu_t = None
        if is_tensor and ctx.needs_input_grad[6]:
            per_sample = torch.from_numpy(g_nu).to(vx.dtype).reshape(*vx.shape[:2], 1, 1)
            g_nu_t = per_sample.sum_to_size(shape) if len(shape) else per_sample.sum()
        return (torch.from_numpy(gv[0]).reshape(vx.shape), torch.from_numpy(gv[1]).reshape(vy.shape), *grads,
                g_nu_t, None, None, None, None, None, None, None)
