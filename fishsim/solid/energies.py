"""Projective-dynamics energies of one element: projections P(F) and their differentials dP[dF].

Every PD energy is E_i = w_i / 2 ||G_i q - P_i(G_i q)||^2 (docs/physics.md section 3). In 2D a
[2, 2] matrix splits into a conformal part (a scaled rotation) and an anticonformal part
(a scaled reflection), which makes both the polar rotation and the closest det-1 matrix closed
forms. With F = [[F00, F01], [F10, F11]]:

    alpha = (F00 + F11) / 2,  beta  = (F10 - F01) / 2     F_c = [[alpha, -beta], [beta, alpha]]
    gamma = (F00 - F11) / 2,  delta = (F01 + F10) / 2     F_a = [[gamma, delta], [delta, -gamma]]

F = F_c + F_a, ||F||^2 = 2 (alpha^2 + beta^2 + gamma^2 + delta^2), det F = c^2 - s^2 with
c^2 = alpha^2 + beta^2 and s^2 = gamma^2 + delta^2; the singular values are c + s and c - s.
Functions below take and return these coordinates as tuples of same-shaped arrays (any shape,
e.g. [T, B]); they are formulas only, mapped over elements and samples by the caller.
"""

from __future__ import annotations

import numpy as np

# Smallest conformal magnitude c (an element collapsed to a line or a point has no rotation).
_TINY = 1e-12


def conformal_parts(F00, F01, F10, F11):
    """(alpha, beta, gamma, delta) of F, see the module docstring."""
    return (F00 + F11) / 2, (F10 - F01) / 2, (F00 - F11) / 2, (F01 + F10) / 2


def from_conformal(alpha, beta, gamma, delta):
    """(F00, F01, F10, F11) of F_c + F_a; inverse of `conformal_parts`."""
    return alpha + gamma, delta - beta, beta + delta, alpha - gamma


def corotated_projection(alpha, beta):
    """Polar rotation R of F: conformal coordinates (alpha, beta) / c, c = sqrt(alpha^2 + beta^2).
    R's anticonformal part is zero. Returns (alpha_R, beta_R, c)."""
    c = np.maximum(np.sqrt(alpha * alpha + beta * beta), _TINY)
    return alpha / c, beta / c, c


def corotated_projection_differential(alpha_R, beta_R, c, d_alpha, d_beta):
    """dR[dF] in conformal coordinates: (I - r r^T)(d_alpha, d_beta) / c with r = (alpha_R, beta_R)
    (derivative of the normalisation); dR has no anticonformal part."""
    radial = alpha_R * d_alpha + beta_R * d_beta
    return (d_alpha - radial * alpha_R) / c, (d_beta - radial * beta_R) / c


def _det_residual(t, c2, s2):
    """phi(t) - 1 with phi(t) = det(F_c / (1 + t) + F_a / (1 - t)) = c^2/(1+t)^2 - s^2/(1-t)^2."""
    return c2 / (1 + t) ** 2 - s2 / (1 - t) ** 2 - 1


def volume_multiplier(c2, s2, iterations: int = 60):
    """Lagrange multiplier t in (-1, 1) of the closest det-1 matrix D = F_c/(1+t) + F_a/(1-t).

    Stationarity of ||D - F||^2 + 2 t (det D - 1) gives D + t cof(D) = F, and cof acts as +1 on
    conformal and -1 on anticonformal matrices; det D = 1 picks the unique root of the strictly
    decreasing phi(t) - 1. Safeguarded Newton (bisection on the bracket) to machine precision."""
    lo, hi = np.full_like(c2, -1.0), np.full_like(c2, 1.0)
    t = np.zeros_like(c2)
    for _ in range(iterations):
        r = _det_residual(t, c2, s2)
        lo, hi = np.where(r > 0, t, lo), np.where(r > 0, hi, t)
        slope = -2 * c2 / (1 + t) ** 3 - 2 * s2 / (1 - t) ** 3
        newton = t - r / np.minimum(slope, -_TINY)
        bad = ~((newton > lo) & (newton < hi))
        t_new = np.where(bad, (lo + hi) / 2, newton)
        if np.all(np.abs(t_new - t) <= 1e-15):
            return t_new
        t = t_new
    return t


def volume_projection(alpha, beta, gamma, delta):
    """Closest det-1 matrix D to F (Frobenius norm): (alpha, beta)/(1+t), (gamma, delta)/(1-t).
    Returns (alpha_D, beta_D, gamma_D, delta_D, t)."""
    t = volume_multiplier(alpha * alpha + beta * beta, gamma * gamma + delta * delta)
    return alpha / (1 + t), beta / (1 + t), gamma / (1 - t), delta / (1 - t), t


def volume_projection_differential(alpha, beta, gamma, delta, t, d_alpha, d_beta, d_gamma, d_delta):
    """dD[dF] by implicit differentiation of det D(F, t) = 1:

        dt = -<phi_F, dF> / phi_t,  phi_F = F_c/(1+t)^2 - F_a/(1-t)^2,
        phi_t = -2 c^2/(1+t)^3 - 2 s^2/(1-t)^3,
        dD = dF_c/(1+t) + dF_a/(1-t) - (F_c/(1+t)^2 - F_a/(1-t)^2) dt.

    (<X, dF> = 2 x . dx in conformal coordinates; the factor 2 cancels against
    d(c^2) = 2 (alpha d_alpha + beta d_beta).)"""
    p, m = 1 / (1 + t), 1 / (1 - t)
    c2, s2 = alpha * alpha + beta * beta, gamma * gamma + delta * delta
    phi_t = -2 * c2 * p**3 - 2 * s2 * m**3
    phi_dF = 2 * (p * p * (alpha * d_alpha + beta * d_beta) - m * m * (gamma * d_gamma + delta * d_delta))
    dt = -phi_dF / phi_t
    return (d_alpha * p - alpha * p * p * dt, d_beta * p - beta * p * p * dt,
            d_gamma * m + gamma * m * m * dt, d_delta * m + delta * m * m * dt)


def muscle_projection(f0, f1, a):
    """Muscle target p = a n, n = F m / |F m|, for the stretched fiber F m = (f0, f1) and target
    stretch a = 1 - contraction. Returns (p0, p1, n0, n1, |F m|)."""
    length = np.maximum(np.sqrt(f0 * f0 + f1 * f1), _TINY)
    n0, n1 = f0 / length, f1 / length
    return a * n0, a * n1, n0, n1, length


def muscle_projection_differential(n0, n1, length, a, d0, d1):
    """dp[d(F m)] = a / |F m| (I - n n^T) d(F m)."""
    radial = n0 * d0 + n1 * d1
    return a * (d0 - radial * n0) / length, a * (d1 - radial * n1) / length
