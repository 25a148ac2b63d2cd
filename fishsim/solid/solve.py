"""Forward and adjoint solves of one implicit-Euler PD step, batched over samples (numpy, CPU).

Forward (PHYSICS.md section 3): q+ = argmin Phi(q),

    Phi(q) = 1/(2 h^2) ||q - y||_M^2 + E_int(q),   y = q_t + h qdot_t + h^2 M^-1 f_ext,
    grad Phi = M/h^2 (q - y) - f_int(q)            (the force residual, N per unit depth),

by L-BFGS (DiffPD's solver) with a prefactorised initial inverse Hessian (preconditioner.py: the
lagged Newton matrix by default; the rotated rest-shape Newton matrix; or DiffPD's PD matrix
A(E), with which the first iteration is exactly one local-global step), Armijo backtracking,
until the residual's largest nodal norm is <= atol. The objective and the two-loop recursion run
compiled (kernels.py). The net residual sum_i g_i is then removed by a rigid translation of q+
(exact: f_int is translation invariant), so linear momentum is conserved to round-off whatever
atol is.

Adjoint: (A - dA) x = b with A - dA = M/h^2 - df_int/dq, the Newton matrix at q+ (symmetric,
indefinite only under strong compression): by default a direct solve per sample of the assembled
2N x 2N matrix (banded Cholesky, sparse LU if indefinite); or ('auto' / 'pcg') batched CG
preconditioned with the rotated rest-shape Newton matrix, direct for samples where CG fails.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from fishsim.solid import elastic, kernels
from fishsim.solid.banded import spd_factor
from fishsim.solid.model import SolidModel
from fishsim.solid.preconditioner import LaggedNewton, Preconditioner


@dataclass(frozen=True)
class ForwardInfo:
    """iterations [B]: L-BFGS iterations per sample; residual [B]: final max nodal force
    residual (N); converged [B] bool."""

    iterations: np.ndarray
    residual: np.ndarray
    converged: np.ndarray


def sample_dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Per-sample inner product [B] of two [N, 2B] arrays (column a B + b)."""
    if u.shape[1] == 2:                                   # B = 1: one BLAS dot (the hot path)
        return np.array([np.dot(u.ravel(), v.ravel())])
    d = np.einsum("ij,ij->j", u, v)
    B = len(d) // 2
    return d[:B] + d[B:]


def per_column(s: np.ndarray) -> np.ndarray:
    """Per-sample scalars [B] -> [1, 2B] for broadcasting against [N, 2B] (B = 1: s itself)."""
    return s if len(s) == 1 else np.concatenate([s, s])[None, :]


def sample_columns(samples: np.ndarray, B: int) -> np.ndarray:
    """Columns of [N, 2B] arrays that hold the given samples."""
    return np.concatenate([samples, B + samples])


def max_nodal_norm(g: np.ndarray) -> np.ndarray:
    """max_i |g_i| per sample [B] of a [N, 2B] nodal vector field."""
    B = g.shape[1] // 2
    return np.sqrt(g[:, :B] ** 2 + g[:, B:] ** 2).max(0)


class Objective:
    """Phi and grad Phi of one step for a batch (y [N, 2B], contraction [n_act, B], E [B]): the
    compiled kernels.objective, or the numpy local step for models with the volume term."""

    def __init__(self, model: SolidModel, Y: np.ndarray, contraction: np.ndarray, E: np.ndarray):
        self.model, self.Y, self.contraction, self.E = model, Y, contraction, E
        self.mass_h2 = model.mass_h2[:, None]
        self.buffer = np.empty((2, model.fem.n_elements, 2, Y.shape[1] // 2))
        self.fused = not model.material.volume_term
        if self.fused:
            self.w_corotated = np.ascontiguousarray(np.outer(model.fem.area * model.material.corotated_per_E, E))
            self.stretch = np.ascontiguousarray(1.0 - contraction)

    def __call__(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(Phi [B] in J per unit depth, grad Phi [N, 2B] in N per unit depth)."""
        if self.fused:
            model, g = self.model, np.empty_like(X)
            phi = kernels.objective(X, self.Y, model.mass_h2, model.mesh_triangles, model.fem.grad,
                                    self.w_corotated, model.muscle_of, model.muscle_weight, self.stretch, g)
            return phi, g
        p = elastic.project(self.model, elastic.deformation_gradients(self.model, X), self.contraction, self.E)
        energy, S = elastic.energy_and_stress(self.model, p, out=self.buffer)
        MD = self.mass_h2 * (X - self.Y)
        grad = self.model.fem.G.T @ S.reshape(-1, X.shape[1])
        grad += MD
        return sample_dot(X - self.Y, MD) / 2 + energy, grad


class History:
    """L-BFGS memory: the last m pairs s = X_k+1 - X_k, y = g_k+1 - g_k ([m, N, 2B] ring
    buffers) and rho = 1 / s.y per sample ([m, B]; 0 marks a pair a sample does not use)."""

    def __init__(self, m: int, like: np.ndarray):
        self.S, self.Y = np.zeros((m, *like.shape)), np.zeros((m, *like.shape))
        self.rho = np.zeros((m, like.shape[1] // 2))
        self.count, self.head = 0, 0

    def push(self, s: np.ndarray, y: np.ndarray, rho: np.ndarray) -> None:
        self.S[self.head], self.Y[self.head], self.rho[self.head] = s, y, rho
        self.head = (self.head + 1) % len(self.S)
        self.count = min(self.count + 1, len(self.S))

    def forget(self, samples: np.ndarray) -> None:
        """Drop every pair of the samples marked in the [B] mask."""
        self.rho[:, samples] = 0.0

    def newest_first(self) -> np.ndarray:
        return (self.head - 1 - np.arange(self.count)) % len(self.S)


def _two_loop(g: np.ndarray, history: History, precondition, active: np.ndarray) -> np.ndarray:
    """L-BFGS direction -H g with H_0 = A^-1 (compiled two-loop recursion, kernels.py); only the
    `active` [B] samples' columns are computed (the others are 0)."""
    q = np.array(g, order="C")                           # the kernels need C order
    order = history.newest_first()
    alphas = np.zeros((len(order), len(active)))
    kernels.lbfgs_first_loop(q, history.S, history.Y, history.rho, order, alphas)
    r = np.ascontiguousarray(precondition(q, active))
    kernels.lbfgs_second_loop(r, history.S, history.Y, history.rho, order, alphas)
    return -r * per_column(active)


def pd_solve(model: SolidModel, Y: np.ndarray, X0: np.ndarray, contraction: np.ndarray,
             E: np.ndarray) -> tuple[np.ndarray, ForwardInfo]:
    """q+ = argmin Phi for every sample. Y, X0: [N, 2B]; contraction [n_act, B]; E [B].
    Returns (X [N, 2B], ForwardInfo). Converged samples stop moving while others iterate; the
    preconditioner is built only if some sample needs an iteration (a start that is already
    converged, e.g. a checkpoint recomputation's, costs one residual evaluation)."""
    opts = model.options
    objective = Objective(model, Y, contraction, E)
    precondition = None
    B = Y.shape[1] // 2
    X = X0.copy()
    phi, g = objective(X)
    residual = max_nodal_norm(g)
    iterations = np.zeros(B, np.int64)
    history = History(opts.history, X)
    for _ in range(opts.max_iter):
        active = residual > opts.atol
        if not active.any():
            break
        iterations += active
        if precondition is None:
            precondition = _preconditioner(model, X0, contraction, E)
        d = _two_loop(g, history, precondition, active)
        slope = sample_dot(g, d)
        uphill = (slope >= 0) & active
        if uphill.any():                                  # not a descent direction: restart
            history.forget(uphill)
            d = np.where(per_column(uphill), -precondition(g, uphill), d)
            slope = sample_dot(g, d)
        X_new, phi_new, g_new = _line_search(objective, X, phi, d, slope)
        s, y = X_new - X, g_new - g
        sy = sample_dot(s, y)
        rho = np.where(sy > 1e-300, 1.0 / np.where(sy > 1e-300, sy, 1.0), 0.0)
        history.push(s, y, rho)
        X, phi, g = X_new, phi_new, g_new
        residual = max_nodal_norm(g)
    if isinstance(precondition, LaggedNewton):
        precondition.refresh(iterations)
    X, g = _remove_net_residual(model, X, g)
    residual = max_nodal_norm(g)
    converged = residual <= opts.atol
    if not converged.all():
        warnings.warn(f"PD step did not converge in {opts.max_iter} iterations "
                      f"(max residual {residual.max():.3g} N > atol {opts.atol:g} N)", RuntimeWarning, stacklevel=3)
    return X, ForwardInfo(iterations, residual, converged)


def _preconditioner(model: SolidModel, X0: np.ndarray, contraction: np.ndarray, E: np.ndarray):
    """The forward's initial inverse Hessian (options.preconditioner) at the start X0."""
    if model.options.preconditioner == "lagged_newton":
        return LaggedNewton(model, X0, contraction, E)
    return Preconditioner(model, E, X0, model.options.preconditioner)


def _remove_net_residual(model: SolidModel, X: np.ndarray, g: np.ndarray):
    """Translate each sample by -sum_i g_i / sum_i (m_i / h^2): grad Phi changes by M/h^2 times
    the shift (f_int is translation invariant), so afterwards sum_i g_i = 0 exactly."""
    shift = g.sum(0, keepdims=True) / model.mass_h2.sum()
    return X - shift, g - model.mass_h2[:, None] * shift


def _line_search(objective, X, phi, d, slope, c1: float = 1e-4, max_halvings: int = 30):
    """Armijo backtracking per sample: Phi(X + t d) <= Phi + c1 t slope, starting at t = 1; a
    change within round-off of Phi counts as sufficient (needed at tight tolerances)."""
    t = np.ones_like(phi)
    X_new = X + d
    phi_new, g_new = objective(X_new)
    for _ in range(max_halvings):
        ok = phi_new - phi <= c1 * t * slope + 64 * np.finfo(float).eps * np.abs(phi)
        if ok.all():
            break
        t = np.where(ok, t, t / 2)
        X_try = X + per_column(t) * d
        phi_try, g_try = objective(X_try)
        keep = per_column(ok)
        X_new, g_new = np.where(keep, X_new, X_try), np.where(keep, g_new, g_try)
        phi_new = np.where(ok, phi_new, phi_try)
    return X_new, phi_new, g_new


class NewtonOperator:
    """X -> (A - dA) X = M/h^2 X + G^T dS[G X], the Newton matrix at the projections p."""

    def __init__(self, model: SolidModel, p: elastic.Projections):
        self.model, self.p = model, p
        self.buffer = np.empty((2, model.fem.n_elements, 2, p.F[0].shape[1]))

    def __call__(self, V: np.ndarray) -> np.ndarray:
        dZ = elastic.deformation_gradients(self.model, V)
        dS = elastic.stress_differential(self.model, self.p, dZ, out=self.buffer)
        return self.model.mass_h2[:, None] * V + self.model.fem.G.T @ dS.reshape(-1, V.shape[1])


def newton_solve(model: SolidModel, p: elastic.Projections, X: np.ndarray, b: np.ndarray, E: np.ndarray,
                 method: str | None = None) -> tuple[np.ndarray, int, int]:
    """x = (A - dA)^-1 b for every sample (b, x: [N, 2B]) at positions X [N, 2B] with projections
    p. Returns (x, CG iterations, number of samples solved directly)."""
    method = method or model.options.backward_method
    B = b.shape[1] // 2
    if method == "direct":
        return _direct_solve(model, p, b, np.arange(B)), 0, B
    x, ok, its = _pcg(NewtonOperator(model, p), Preconditioner(model, E, X, "rest_newton"), b,
                      model.options.backward_rtol, model.options.backward_max_iter)
    failed = np.flatnonzero(~ok)
    if len(failed) and method == "auto":
        cols = sample_columns(failed, B)
        x[:, cols] = _direct_solve(model, p, b, failed)[:, cols]
    elif len(failed):
        warnings.warn(f"adjoint PCG did not converge for {len(failed)} samples", RuntimeWarning, stacklevel=3)
    return x, its, len(failed) if method == "auto" else 0


def _pcg(apply_K, precondition, b: np.ndarray, rtol: float, max_iter: int):
    """Batched preconditioned CG; a sample stops at |r|_max <= rtol |b|_max, fails on
    p^T K p <= 0 (indefinite) or after max_iter. Returns (x, converged [B], iterations)."""
    B = b.shape[1] // 2
    x = np.zeros_like(b)
    target = rtol * max_nodal_norm(b)
    r = b.copy()
    z = precondition(r)
    d = z.copy()
    rz = sample_dot(r, z)
    done = max_nodal_norm(r) <= target
    broken = np.zeros(B, bool)
    it = 0
    for it in range(1, max_iter + 1):
        active = ~(done | broken)
        if not active.any():
            break
        Kd = apply_K(d)
        dKd = sample_dot(d, Kd)
        broken |= active & (dKd <= 0)
        active &= ~broken
        step = np.where(active, rz / np.where(active, dKd, 1.0), 0.0)
        x += per_column(step) * d
        r -= per_column(step) * Kd
        done |= active & (max_nodal_norm(r) <= target)
        z = precondition(r)
        rz_new = sample_dot(r, z)
        d = z + per_column(np.where(active, rz_new / np.where(rz != 0, rz, 1.0), 0.0)) * d
        rz = rz_new
    return x, done, it


def _direct_solve(model: SolidModel, p: elastic.Projections, b: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """Direct solve of the assembled Newton matrix for the given samples (columns of b): banded
    Cholesky when it is positive definite, else sparse LU (banded.spd_factor)."""
    x = np.zeros_like(b)
    B = b.shape[1] // 2
    for s in samples:
        K = elastic.newton_matrix(model, p, int(s))
        cols = [s, B + s]
        x[:, cols] = spd_factor(K).solve(b[:, cols].reshape(-1)).reshape(-1, 2)
    return x
