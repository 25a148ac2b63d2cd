"""The element physics of the compiled PD solve, written once for one sample (floats) and for a
pack of eight (simd.Vec): the deformation gradient's parts, the co-rotated and muscle energies
with their stresses, and the stresses' differentials that make the Newton matrix
(docs/physics.md section 3; elastic.py is the numpy reference the tests compare against).

Per element, F = G_e X (2 x 2, fiber direction along column j = 0) in conformal coordinates,

    alpha = (F00 + F11) / 2,  beta = (F10 - F01) / 2,  gamma = (F00 - F11) / 2,  delta = (F01 + F10) / 2,

R the rotation closest to F: c = sqrt(alpha^2 + beta^2), (alpha_R, beta_R) = (alpha, beta) / c;

    co-rotated:  psi = w |F - R|^2 = w ((alpha - alpha_R)^2 + (beta - beta_R)^2 + gamma^2 + delta^2),
                 S = w (F - R)          (w = area 2 mu_s; S = dpsi/dF up to the factor 2 in w),
    muscle:      psi = w_m / 2 |F m - a F m / |F m||^2,  S m^T = w_m (F m - a F m / |F m|),

with m = e_0 the fiber, a = 1 - u the target stretch (u the contraction) and w_m = k_m area.
The Newton matrix's element block is G_e^T (dS/dF) G_e; ``stress_differential`` gives dS for a
unit dF. The projected variant (``projected``) clamps c >= 1 and |F m| >= a, which makes dS/dF
positive semi-definite (elastic.stress_differential).

Every function here is inlined into its caller (kernels.py, packed.py) and works on floats or
Vecs alike through simd's operators and generic sqrt / maximum / select.
"""

from __future__ import annotations

from fishsim.compiled import jit
from fishsim.linalg.simd import absolute, lanes_set, mask, maximum, select, sqrt, width
from fishsim.solid.energies import _TINY

_TINY_STEP = 1e-15          # volume_multiplier's convergence: the numpy reference's step


@jit(inline="always")
def deformation_gradient(x0, y0, x1, y1, x2, y2, grad, e):
    """F = G_e X of element e from its three nodes' positions (x_k, y_k): (F00, F01, F10, F11),
    F_aj = sum_k X_ka grad[e, k, j] (grad [T, 3, 2] the shape-function gradients)."""
    return (x0 * grad[e, 0, 0] + x1 * grad[e, 1, 0] + x2 * grad[e, 2, 0],
            x0 * grad[e, 0, 1] + x1 * grad[e, 1, 1] + x2 * grad[e, 2, 1],
            y0 * grad[e, 0, 0] + y1 * grad[e, 1, 0] + y2 * grad[e, 2, 0],
            y0 * grad[e, 0, 1] + y1 * grad[e, 1, 1] + y2 * grad[e, 2, 1])


@jit(inline="always")
def conformal(F00, F01, F10, F11):
    """(alpha, beta, gamma, delta) of F (module doc)."""
    return (F00 + F11) * 0.5, (F10 - F01) * 0.5, (F00 - F11) * 0.5, (F01 + F10) * 0.5


@jit(inline="always")
def rotation(alpha, beta):
    """(alpha_R, beta_R, c): the closest rotation's conformal parts and c = |(alpha, beta)|."""
    c = maximum(sqrt(alpha * alpha + beta * beta), _TINY)
    return alpha / c, beta / c, c


@jit(inline="always")
def corotated_stress(F00, F01, F10, F11, w):
    """(psi, S00, S01, S10, S11): the co-rotated energy w |F - R|^2 and its stress w (F - R)."""
    alpha, beta, gamma, delta = conformal(F00, F01, F10, F11)
    alpha_R, beta_R, _ = rotation(alpha, beta)
    ra, rb = alpha - alpha_R, beta - beta_R                     # F - R, conformal coordinates
    psi = w * (ra * ra + rb * rb + gamma * gamma + delta * delta)
    return psi, w * (ra + gamma), w * (delta - rb), w * (rb + delta), w * (ra - gamma)


@jit(inline="always")
def fiber_length(F00, F10):
    """|F m| (floored at _TINY), the fiber's stretch."""
    return maximum(sqrt(F00 * F00 + F10 * F10), _TINY)


@jit(inline="always")
def muscle_stress(F00, F10, a, w_m):
    """(psi, S00, S10): the muscle energy w_m / 2 |F m - a F m / |F m||^2 and its stress's fiber
    column (the other column is 0)."""
    length = fiber_length(F00, F10)
    m0, m1 = F00 - a * F00 / length, F10 - a * F10 / length
    return w_m / 2 * (m0 * m0 + m1 * m1), w_m * m0, w_m * m1


@jit(inline="always")
def unit_strain(col):
    """The unit dF with entry col = 2 a + j set: (dF00, dF01, dF10, dF11)."""
    return (1.0 if col == 0 else 0.0, 1.0 if col == 1 else 0.0,
            1.0 if col == 2 else 0.0, 1.0 if col == 3 else 0.0)


@jit(inline="always")
def clamped(x, floor, projected):
    """max(x, floor) where ``projected`` (a bool, or a lane mask), else x: the projected Newton
    matrix's c (floor 1) and fiber length (floor a)."""
    return select(projected, maximum(x, floor), x)


@jit(inline="always")
def corotated_differential(col, alpha_R, beta_R, ce, w):
    """dS (dS00, dS01, dS10, dS11) of the co-rotated stress for the unit dF ``col`` at the
    rotation (alpha_R, beta_R) of F, with ce = c or, projected, clamped(c, 1.0, True)."""
    dF00, dF01, dF10, dF11 = unit_strain(col)
    d_alpha, d_beta, d_gamma, d_delta = conformal(dF00, dF01, dF10, dF11)
    radial = alpha_R * d_alpha + beta_R * d_beta
    c0 = w * (d_alpha - (d_alpha - radial * alpha_R) / ce)
    c1 = w * (d_beta - (d_beta - radial * beta_R) / ce)
    c2, c3 = w * d_gamma, w * d_delta
    return c0 + c2, c3 - c1, c1 + c3, c0 - c2


@jit(inline="always")
def muscle_differential(col, n0, n1, L, a, w_m):
    """(dS00, dS10) of the muscle stress for the unit dF ``col``, at the fiber's direction
    (n0, n1) = F m / |F m|, with L = |F m| or, projected, clamped(|F m|, a, True)."""
    dF00, _, dF10, _ = unit_strain(col)
    rad = n0 * dF00 + n1 * dF10
    return w_m * (dF00 - a * (dF00 - rad * n0) / L), w_m * (dF10 - a * (dF10 - rad * n1) / L)


@jit(inline="always")
def volume_multiplier(c2, s2):
    """The Lagrange multiplier t in (-1, 1) of the closest det-1 matrix D = F_c / (1 + t) +
    F_a / (1 - t) (energies.volume_multiplier: the root of the strictly decreasing
    c^2 / (1 + t)^2 - s^2 / (1 - t)^2 - 1), per lane: safeguarded Newton, bisection on the
    bracket, until every lane's step is <= 1e-15 (at most 60 iterations)."""
    t = c2 * 0.0
    lo, hi = t - 1.0, t + 1.0
    for _ in range(60):
        p, m = 1.0 / (1.0 + t), 1.0 / (1.0 - t)
        r = c2 * p * p - s2 * m * m - 1.0
        above = mask(r > 0.0)
        lo, hi = select(above, t, lo), select(above, hi, t)
        slope = -2.0 * c2 * p * p * p - 2.0 * s2 * m * m * m
        newton = t + r / maximum(-slope, _TINY)
        inside = mask(newton > lo) * mask(hi > newton)
        t_new = select(inside, newton, (lo + hi) * 0.5)
        done = lanes_set(mask(_TINY_STEP >= absolute(t_new - t))) == width(t)
        t = t_new
        if done:
            break
    return t


@jit(inline="always")
def volume_stress(F00, F01, F10, F11, w):
    """(psi, S00, S01, S10, S11): DiffPD's volume energy w |F - D|^2 (w = area lambda_s, D the
    closest det-1 matrix) and its stress w (F - D)."""
    alpha, beta, gamma, delta = conformal(F00, F01, F10, F11)
    t = volume_multiplier(alpha * alpha + beta * beta, gamma * gamma + delta * delta)
    p, m = 1.0 / (1.0 + t), 1.0 / (1.0 - t)
    ra, rb, rg, rd = alpha - alpha * p, beta - beta * p, gamma - gamma * m, delta - delta * m
    psi = w * (ra * ra + rb * rb + rg * rg + rd * rd)
    return psi, w * (ra + rg), w * (rd - rb), w * (rb + rd), w * (ra - rg)


@jit(inline="always")
def volume_differential(col, alpha, beta, gamma, delta, t, w, projected):
    """dS (dS00, dS01, dS10, dS11) of the volume stress for the unit dF ``col``: w (dF - dD) with
    dD by implicit differentiation (energies.volume_projection_differential); where
    ``projected`` (a bool or a lane mask), the Gauss-Newton w n (n . dF) / |n|^2 with
    n = (alpha, beta, -gamma, -delta) ~ cof F (elastic.stress_differential)."""
    dF00, dF01, dF10, dF11 = unit_strain(col)
    da, db, dg, dd = conformal(dF00, dF01, dF10, dF11)
    p, m = 1.0 / (1.0 + t), 1.0 / (1.0 - t)
    c2, s2 = alpha * alpha + beta * beta, gamma * gamma + delta * delta
    phi_t = -maximum(2.0 * c2 * p * p * p + 2.0 * s2 * m * m * m, _TINY)
    dt = -2.0 * (p * p * (alpha * da + beta * db) - m * m * (gamma * dg + delta * dd)) / phi_t
    ea = w * (da - (da * p - alpha * p * p * dt))
    eb = w * (db - (db * p - beta * p * p * dt))
    eg = w * (dg - (dg * m + gamma * m * m * dt))
    ed = w * (dd - (dd * m + delta * m * m * dt))
    scale = w * (alpha * da + beta * db - gamma * dg - delta * dd) / maximum(c2 + s2, _TINY)
    ca, cb = select(projected, scale * alpha, ea), select(projected, scale * beta, eb)
    cg, cd = select(projected, -scale * gamma, eg), select(projected, -scale * delta, ed)
    return ca + cg, cd - cb, cb + cd, ca - cg
