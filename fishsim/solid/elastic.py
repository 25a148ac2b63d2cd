"""The PD local step: per-element projections, internal energy, stress and their differentials.

Internal layout (numpy, float64). Positions of a batch are X [N, 2B], column a B + b holding axis
a of sample b, so that one sparse product G @ X gives every deformation gradient at once:
Z = (G @ X).reshape(2, T, 2, B) with Z[j, e, a, b] = F_aj of element e in sample b (each
component a [T, B] block, contiguous in b).
"Stress" S (same layout) is sum_i w_i (F - P_i(F)), so that

    E_int = sum_i w_i / 2 ||F - P_i||^2,   dE_int / dX = G^T S,   f_int = -G^T S.

Energies: co-rotated (w = 2 mu_s area), optional volume (w = lambda_s area), muscle on the
fiber column j = 0 of actuated elements (w = k_m area, target stretch a = 1 - contraction).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from fishsim.solid import energies as en
from fishsim.solid.model import SolidModel


@dataclass(frozen=True)
class Projections:
    """Result of the local step at one configuration; arrays [T, B] (muscle ones [n_act, B]).

    F: conformal coordinates (alpha, beta, gamma, delta) of F.
    rotation: (alpha_R, beta_R, c) of the polar rotation.
    volume: (alpha_D, beta_D, gamma_D, delta_D, t) of the closest det-1 matrix, or None.
    fiber: (f0, f1) = F m;  muscle: (p0, p1, n0, n1, |F m|, a).
    w_corotated, w_volume: [T, B] PD weights (Pa m^2); w_muscle: [n_act, 1].
    """

    F: tuple
    rotation: tuple
    volume: tuple | None
    fiber: tuple
    muscle: tuple
    w_corotated: np.ndarray
    w_volume: np.ndarray
    w_muscle: np.ndarray


def to_columns(x: np.ndarray) -> np.ndarray:
    """[B, N, 2] -> [N, 2B] (column a B + b)."""
    B, N, _ = x.shape
    return np.ascontiguousarray(x.transpose(1, 2, 0)).reshape(N, 2 * B)


def from_columns(X: np.ndarray) -> np.ndarray:
    """[N, 2B] -> [B, N, 2]."""
    N = X.shape[0]
    return np.ascontiguousarray(X.reshape(N, 2, -1).transpose(2, 0, 1))


def deformation_gradients(model: SolidModel, X: np.ndarray) -> np.ndarray:
    """Z [2, T, 2, B] = F of every element and sample (Z[j, e, a, b] = F_aj)."""
    return (model.fem.G @ X).reshape(2, model.fem.n_elements, 2, -1)


def _components(Z: np.ndarray):
    """(F00, F01, F10, F11) views [T, B] of a Z-layout array."""
    return Z[0, :, 0], Z[1, :, 0], Z[0, :, 1], Z[1, :, 1]


def _assemble_conformal(alpha, beta, gamma, delta, out: np.ndarray | None = None) -> np.ndarray:
    """Z-layout array [2, T, 2, B] of F_c + F_a from conformal coordinates [T, B], written into
    `out` if given (reusing a buffer avoids re-faulting MB-sized pages on every call)."""
    Z = np.empty((2, alpha.shape[0], 2, alpha.shape[1])) if out is None else out
    np.add(alpha, gamma, out=Z[0, :, 0])
    np.subtract(delta, beta, out=Z[1, :, 0])
    np.add(beta, delta, out=Z[0, :, 1])
    np.subtract(alpha, gamma, out=Z[1, :, 1])
    return Z


def project(model: SolidModel, Z: np.ndarray, contraction: np.ndarray, E: np.ndarray) -> Projections:
    """Local step: P_i(F) of every energy. contraction [n_act, B] in [0, 1), E [B] in Pa."""
    F00, F01, F10, F11 = _components(Z)
    F = en.conformal_parts(F00, F01, F10, F11)
    rotation = en.corotated_projection(F[0], F[1])
    volume = en.volume_projection(*F) if model.material.volume_term else None
    area = model.fem.area[:, None]
    fiber = (F00[model.muscles], F10[model.muscles])
    muscle = en.muscle_projection(*fiber, 1.0 - contraction) + (1.0 - contraction,)
    return Projections(F, rotation, volume, fiber, muscle,
                       area * (model.material.corotated_per_E * E)[None, :],
                       area * (model.material.volume_per_E * E)[None, :],
                       model.muscle_weight[:, None])


def projections_at(model: SolidModel, X: np.ndarray, contraction: np.ndarray, E: np.ndarray) -> Projections:
    """project() at positions X [B, N, 2]."""
    return project(model, deformation_gradients(model, to_columns(X)), contraction, E)


def _elastic_residuals(p: Projections):
    """Conformal coordinates of F - R and F - D (None without the volume term)."""
    al, be, ga, de = p.F
    rot = (al - p.rotation[0], be - p.rotation[1], ga, de)
    vol = None if p.volume is None else tuple(f - d for f, d in zip(p.F, p.volume[:4]))
    return rot, vol


def _muscle_residual(p: Projections):
    """(F m - p) components, [n_act, B] each."""
    return p.fiber[0] - p.muscle[0], p.fiber[1] - p.muscle[1]


def internal_energy(p: Projections) -> np.ndarray:
    """E_int per sample [B] in J (per unit depth); ||X||^2 = 2 |conformal coords|^2."""
    rot, vol = _elastic_residuals(p)
    energy = (p.w_corotated * sum(r * r for r in rot)).sum(0)
    if vol is not None:
        energy = energy + (p.w_volume * sum(r * r for r in vol)).sum(0)
    m0, m1 = _muscle_residual(p)
    return energy + (p.w_muscle / 2 * (m0 * m0 + m1 * m1)).sum(0)


def _add_muscle(model: SolidModel, S: np.ndarray, s0: np.ndarray, s1: np.ndarray) -> np.ndarray:
    """Add a fiber-column term (s0, s1) [n_act, B] of the muscles into S (Z layout)."""
    S[0, model.muscles, 0] += s0
    S[0, model.muscles, 1] += s1
    return S


def energy_and_stress(model: SolidModel, p: Projections, out: np.ndarray | None = None):
    """(E_int [B], S) in one pass over the residuals (see internal_energy);
    S is written into `out` [2, T, 2, B] if given."""
    rot, vol = _elastic_residuals(p)
    coords = [p.w_corotated * r for r in rot]
    energy = sum(c * r for c, r in zip(coords, rot)).sum(0)
    if vol is not None:
        wv = [p.w_volume * v for v in vol]
        energy = energy + sum(c * v for c, v in zip(wv, vol)).sum(0)
        coords = [c + w for c, w in zip(coords, wv)]
    m0, m1 = _muscle_residual(p)
    s0, s1 = p.w_muscle * m0, p.w_muscle * m1
    energy = energy + ((s0 * m0 + s1 * m1) / 2).sum(0)
    return energy, _add_muscle(model, _assemble_conformal(*coords, out=out), s0, s1)


def stress_differential(model: SolidModel, p: Projections, dZ: np.ndarray, out: np.ndarray | None = None,
                        projected: bool = False):
    """dS[dF] = sum_i w_i (dF - dP_i[dF]) in Z layout: the element Hessians of E_int applied to
    dF; G^T dS[G dX] is the tangent stiffness -df_int/dq applied to dX. `projected` clamps the
    two indefinite eigenvalues (co-rotated rotation mode 1 - 1/c under compression c < 1, muscle
    transverse mode 1 - a/|F m|) at zero and replaces the volume term's Hessian by its
    Gauss-Newton part w n n^T (n = cof F / |cof F|, the normal of det F = 1): a positive
    semi-definite approximation for preconditioning."""
    dF00, dF01, dF10, dF11 = _components(dZ)
    d = en.conformal_parts(dF00, dF01, dF10, dF11)
    alpha_R, beta_R, c = p.rotation
    dR = en.corotated_projection_differential(alpha_R, beta_R, np.maximum(c, 1.0) if projected else c, d[0], d[1])
    coords = [p.w_corotated * (d[0] - dR[0]), p.w_corotated * (d[1] - dR[1]),
              p.w_corotated * d[2], p.w_corotated * d[3]]
    if p.volume is not None and projected:                 # Gauss-Newton: w n n^T, n ~ cof F
        n = (p.F[0], p.F[1], -p.F[2], -p.F[3])
        scale = p.w_volume * sum(x * y for x, y in zip(n, d)) / sum(x * x for x in n)
        coords = [c + scale * x for c, x in zip(coords, n)]
    elif p.volume is not None:
        dD = en.volume_projection_differential(*p.F, p.volume[4], *d)
        coords = [c + p.w_volume * (x - y) for c, x, y in zip(coords, d, dD)]
    df0, df1 = dF00[model.muscles], dF10[model.muscles]
    n0, n1, length, a = p.muscle[2:6]
    dp = en.muscle_projection_differential(n0, n1, np.maximum(length, a) if projected else length, a, df0, df1)
    return _add_muscle(model, _assemble_conformal(*coords, out=out), p.w_muscle * (df0 - dp[0]),
                       p.w_muscle * (df1 - dp[1]))


def stress_per_E(model: SolidModel, p: Projections) -> np.ndarray:
    """dS/dE in Z layout (1/Pa times S's units): area (F - R)/(1 + nu) + area nu (F - D)/(...)."""
    rot, vol = _elastic_residuals(p)
    area = model.fem.area[:, None]
    coords = [area * model.material.corotated_per_E * r for r in rot]
    if vol is not None:
        coords = [c + area * model.material.volume_per_E * v for c, v in zip(coords, vol)]
    return _assemble_conformal(*coords)


def fiber_stress_per_contraction(p: Projections) -> tuple[np.ndarray, np.ndarray]:
    """dS/d(contraction) on the fiber column of each muscle: S_fiber = w (F m - (1 - u) n), so
    dS/du = w n. Returns two [n_act, B] arrays."""
    return p.w_muscle * p.muscle[2], p.w_muscle * p.muscle[3]


def element_hessians(model: SolidModel, p: Projections, sample: int, projected: bool = False) -> np.ndarray:
    """H [T, 4, 4]: d vec(S) / d vec(F) of one sample, vec index 2a + j (columns of dS[dF])."""
    T = model.fem.n_elements
    p1 = select_sample(p, sample)
    H = np.empty((T, 4, 4))
    for col in range(4):
        a, j = divmod(col, 2)
        dZ = np.zeros((2, T, 2, 1))
        dZ[j, :, a, 0] = 1.0
        dS = stress_differential(model, p1, dZ, projected=projected)
        H[:, :, col] = dS[:, :, :, 0].transpose(1, 2, 0).reshape(T, 4)
    return H


def newton_matrix(model: SolidModel, p: Projections, sample: int, projected: bool = False) -> sp.csc_matrix:
    """Assembled Newton matrix M/h^2 - df_int/dq = M/h^2 + sum_e G_e^T H_e G_e of one sample,
    sparse [2N, 2N] over DOFs 2i + a (x and y coupled, unlike the per-axis PD matrix);
    `projected`: the positive definite approximation of stress_differential."""
    Ge = model.fem.element_G
    Ke = Ge.transpose(0, 2, 1) @ element_hessians(model, p, sample, projected) @ Ge
    return model.fem.pattern.assemble(Ke, np.repeat(model.mass_h2, 2))


def select_sample(p: Projections, b: int) -> Projections:
    """Projections of sample b only (arrays [., 1]); arrays shared by the batch pass through."""
    def pick(x):
        return x[:, b:b + 1] if np.ndim(x) == 2 and x.shape[1] > 1 else x

    group = lambda t: None if t is None else tuple(pick(x) for x in t)
    return Projections(group(p.F), group(p.rotation), group(p.volume), group(p.fiber), group(p.muscle),
                       pick(p.w_corotated), pick(p.w_volume), p.w_muscle)
