"""Prefactorised approximate inverse Hessians H0 ~ (M/h^2 - df_int/dq)^-1 for the solves.

- 'lagged_newton' (forward default): per sample, the Newton matrix of elastic.newton_matrix
  (the exact Hessian of Phi; its positive definite projection where the exact one is indefinite,
  under strong compression), factorised at the start of a step and reused by later steps until
  one needs more than options.refresh_iterations iterations (kept in the SolverCache; the batch size
  changing rebuilds them). The batch's factors are assembled and factorised in parallel over
  the samples, straight into their bands (packed.factor, packs of width 1). It follows the body's local
  rotations, which the two fixed matrices below cannot. The exact Hessian, where positive
  definite, saves ~1.2 of ~12 L-BFGS iterations per step on the default fish over the
  projected one.

The next two are constant in time and affine in E, so each is factorised once per distinct E
(cached in the SolverCache) and reused every step. Every factorisation is a banded Cholesky after
RCM reordering (fishsim.linalg.banded; SuperLU if a matrix is not positive definite):

- 'pd': DiffPD's global matrix A(E) = M/h^2 + G^T W(E) G, the same [N, N] matrix for x and y.
- 'rest_newton': K0(E) = M/h^2 - df_int/dq at the rest shape, [2N, 2N]. Since
  f_int(R q) = R f_int(q) for a rigid rotation R, the Newton matrix of a rotated rest shape is
  R K0 R^T; each sample is therefore preconditioned in its best-fit rigid frame,
  H0 r = R_b K0^-1 R_b^T r, with R_b the rotation that best maps the rest shape onto the
  sample's current shape (mass-weighted Procrustes fit; 2D closed form).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from fishsim.linalg.banded import BandedCholesky, spd_factor
from fishsim.solid import elastic, packed
from fishsim.solid.model import SolidModel, SolverCache
from fishsim.solid.packed import aligned_empty, kernel_arrays

_CACHE_SIZE = 64


def pd_matrix(model: SolidModel, E: float) -> sp.csc_matrix:
    """A(E) = M/h^2 + K_muscle + E K0, [N, N]."""
    return (sp.diags(model.mass_h2) + model.K_muscle + E * model.K0).tocsc()


def rest_newton_matrix(model: SolidModel, E: float) -> sp.csc_matrix:
    """Newton matrix M/h^2 - df_int/dq at the rest shape with relaxed muscles, [2N, 2N]."""
    X = elastic.to_columns(np.asarray(model.mesh.points, np.float64)[None])
    p = elastic.project(model, elastic.deformation_gradients(model, X), np.zeros((model.n_muscles, 1)),
                        np.array([E]))
    return elastic.newton_matrix(model, p, 0)


def factor(model: SolidModel, E: float, kind: str, cache: SolverCache):
    """Factorisation of the 'rest_newton' or 'pd' matrix for Young's modulus E, kept in
    ``cache.factors``."""
    key, factors = (kind, float(E)), cache.factors
    if key not in factors:
        if len(factors) >= _CACHE_SIZE:
            factors.pop(next(iter(factors)))
        build = rest_newton_matrix if kind == "rest_newton" else pd_matrix
        factors[key] = spd_factor(build(model, float(E)))
    return factors[key]


def best_fit_rotation(model: SolidModel, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(cos, sin) [B] of the rotation R_b minimising sum_i m_i |R (X_i - Xbar) - (x_i - xbar)|^2
    for the current positions X [N, 2B]: the angle of the conformal part of
    sum_i m_i (x_i - xbar)(X_i - Xbar)^T."""
    m = model.mass
    rest = np.asarray(model.mesh.points)
    Xc = (rest - m @ rest / m.sum()) * m[:, None]              # mass-weighted, centred rest shape
    C = Xc.T @ X                                                 # [2 (j), 2B]: sum_i m_i X_ij x_ia
    B = X.shape[1] // 2
    angle = np.arctan2(C[0, B:] - C[1, :B], C[0, :B] + C[1, B:])
    return np.cos(angle), np.sin(angle)


def _rotate(R: np.ndarray, cos: np.ndarray, sin: np.ndarray) -> np.ndarray:
    """Rotate every node's vector of sample b by the angle (cos_b, sin_b); R [N, 2B]."""
    B = R.shape[1] // 2
    x, y = R[:, :B], R[:, B:]
    return np.concatenate([cos * x - sin * y, sin * x + cos * y], axis=1)


class Preconditioner:
    """r -> H0 r for [B, N, 2] arrays (solved in elastic's [N, 2B] column layout), one
    factorisation per distinct E among the samples; `X_frame` [B, N, 2] (rest_newton only) sets
    each sample's rigid frame. Every sample is solved (the `active` argument of the call is
    accepted for LaggedNewton's interface)."""

    def __init__(self, model: SolidModel, cache: SolverCache, E: np.ndarray, X_frame: np.ndarray | None = None,
                 kind: str = "rest_newton"):
        values, inverse = np.unique(E, return_inverse=True)
        self.groups = [(factor(model, v, kind, cache), np.flatnonzero(inverse.ravel() == i)) for i, v in enumerate(values)]
        self.rotated = kind == "rest_newton"
        if self.rotated:
            self.cos, self.sin = best_fit_rotation(model, elastic.to_columns(X_frame))

    def __call__(self, R: np.ndarray, active: np.ndarray | None = None) -> np.ndarray:
        R = elastic.to_columns(R)
        if self.rotated:
            R = _rotate(R, self.cos, -self.sin)
        if len(self.groups) == 1:
            Z = self._solve(self.groups[0][0], R)
        else:
            Z = np.empty_like(R)
            B = R.shape[1] // 2
            for lu, samples in self.groups:
                cols = np.concatenate([samples, B + samples])
                Z[:, cols] = self._solve(lu, R[:, cols])
        return elastic.from_columns(_rotate(Z, self.cos, self.sin) if self.rotated else Z)

    def _solve(self, lu, R: np.ndarray) -> np.ndarray:
        if not self.rotated:                                   # per-axis [N, N] matrix
            return lu.solve(np.asfortranarray(R))
        N, B = R.shape[0], R.shape[1] // 2                     # as [2N, B] with DOF 2i + a
        return lu.solve(R.reshape(2 * N, B)).reshape(N, 2 * B)


class LaggedFactors:
    """The lagged Newton factors of a batch of B samples, kept between steps (SolverCache.lagged):
    banded factors L [B, rows, w + 4, 1] (packed.PackBand's layout, packs of width 1) where
    ok [B, 1] is 1.0, else a factorisation in `other` (a sample whose banded Cholesky failed); `valid` [B] False marks samples to refactorise at the
    next step's start; `iterations` [B] the last step's L-BFGS iterations (the next step's cost
    estimate)."""

    def __init__(self, model: SolidModel, B: int):
        self.L = aligned_empty(model.pack_band.shape(B, 1))
        self.ok = np.zeros((B, 1))
        self.valid = np.zeros(B, bool)
        self.other: dict[int, object] = {}
        self.iterations = np.zeros(B, np.int64)

    @property
    def banded(self) -> np.ndarray:
        """[B] bool: the sample's factor is in L."""
        return self.ok[:, 0] > 0

    def refactorise(self, model: SolidModel, X: np.ndarray, contraction: np.ndarray, E: np.ndarray) -> None:
        """Factorise the Newton matrix at positions X [B, N, 2] of every invalid sample: the exact
        one where positive definite, else its positive definite projection; compiled into L
        (packed.factor), and where that fails banded Cholesky or sparse LU of the assembled
        matrix."""
        stale = np.flatnonzero(~self.valid)
        if not len(stale):
            return
        self.ok[stale] = 0.0
        for b in stale:
            self.other.pop(int(b), None)
        packed.factor(np.ascontiguousarray(X, np.float64), kernel_arrays(model, contraction, E),
                      model.pack_band.arrays, self.L, stale, self.ok)
        failed = stale[~self.banded[stale]]
        if len(failed):
            p = elastic.projections_at(model, X, contraction, E)
            for b in failed:
                exact = BandedCholesky.of(elastic.newton_matrix(model, p, int(b)))
                self.other[int(b)] = exact or spd_factor(elastic.newton_matrix(model, p, int(b), projected=True))
        self.valid[stale] = True

    def refresh(self, model: SolidModel, iterations: np.ndarray) -> None:
        """Mark samples whose step needed more than refresh_iterations for refactorisation, and
        keep the step's iterations as the next step's cost estimate."""
        self.valid &= iterations <= model.options.refresh_iterations
        self.iterations = iterations.copy()


def lagged_factors(model: SolidModel, cache: SolverCache, B: int) -> LaggedFactors:
    """The cache's lagged factors for a batch of B samples (new, all stale, if it had none for B)."""
    if cache.lagged is None or len(cache.lagged.valid) != B:
        cache.lagged = LaggedFactors(model, B)
    return cache.lagged


class LaggedNewton:
    """r -> K_b^-1 r per sample with the lagged Newton factors of `cache.lagged`, refactorised
    where stale at X [B, N, 2]; with `active` [B] only those samples are solved (the others
    are 0)."""

    def __init__(self, model: SolidModel, cache: SolverCache, X: np.ndarray, contraction: np.ndarray,
                 E: np.ndarray):
        self.lagged, self.model = lagged_factors(model, cache, len(X)), model
        self.lagged.refactorise(model, X, contraction, E)

    def __call__(self, R: np.ndarray, active: np.ndarray | None = None) -> np.ndarray:
        R = np.ascontiguousarray(R, dtype=np.float64)
        samples = np.arange(len(R)) if active is None else np.flatnonzero(active)
        lagged = self.lagged
        Z = np.zeros(R.shape)
        banded = samples[lagged.banded[samples]]
        if len(banded):
            packed.solve(lagged.L, self.model.pack_band.arrays, R, banded, Z)
        for b in samples[~lagged.banded[samples]]:
            Z[b] = lagged.other[int(b)].solve(R[b].reshape(-1)).reshape(-1, 2)
        return Z
