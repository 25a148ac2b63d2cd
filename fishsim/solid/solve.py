"""Forward and adjoint solves of one implicit-Euler PD step, batched over samples (numpy, CPU).

Forward (docs/physics.md section 3): q+ = argmin Phi(q),

    Phi(q) = 1/(2 h^2) ||q - y||_M^2 + E_int(q),   y = q_t + h qdot_t + h^2 M^-1 f_ext,
    grad Phi = M/h^2 (q - y) - f_int(q)            (the force residual, N per unit depth),

by L-BFGS (DiffPD's solver) with a prefactorised initial inverse Hessian (preconditioner.py: the
lagged Newton matrix by default; the rotated rest-shape Newton matrix; or DiffPD's PD matrix
A(E), with which the first iteration is exactly one local-global step), backtracking to
Armijo's test or, near the minimiser where Phi's decrease is below its round-off, the
approximate Wolfe test on Phi' (_line_search), until the residual's largest nodal norm is
<= atol. With the default preconditioner the whole solve is compiled (packed.lbfgs, one code
for both widths): from PACK_MIN samples on, eight samples per pack in the SIMD lanes, in lock
step, each with the Newton matrix factorised afresh at the step's start; below that, one sample
per thread with its lagged factor. Otherwise the batched numpy iteration (_lbfgs) runs, with the
objective and two-loop recursion compiled where possible. All take the same steps for the same
H0 up to the dot products' round-off. The net residual sum_i g_i is then removed by a rigid
translation of q+ (exact: f_int is translation invariant), so linear momentum is conserved to
round-off whatever atol is.

Adjoint: (A - dA) x = b with A - dA = M/h^2 - df_int/dq, the Newton matrix at q+ (symmetric,
indefinite only under strong compression): by default a direct solve per sample of the assembled
2N x 2N matrix (packed.newton_solve: banded Cholesky, eight samples per pack from PACK_MIN on;
sparse LU if indefinite); or ('auto' / 'pcg') batched CG
preconditioned with the rotated rest-shape Newton matrix, direct for samples where CG fails.

Layout: nodal vectors are [B, N, 2] arrays, one sample contiguous (packed.py's packs of width 1
as they are; to_packs deals them into packs of eight); elastic.py's operators take the [N, 2B]
column layout (elastic.to_columns), which the numpy paths convert to at their boundaries.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numba
import numpy as np
import torch

from fishsim.linalg.banded import lu_factor
from fishsim.linalg.pcg import pcg
from fishsim.solid import elastic, kernels, packed
from fishsim.solid.model import SolidModel, SolverCache
from fishsim.solid.packed import LANES, kernel_arrays
from fishsim.solid.preconditioner import LaggedNewton, Preconditioner, lagged_factors


@dataclass(frozen=True)
class ForwardInfo:
    """iterations [B]: L-BFGS iterations per sample; residual [B]: final max nodal force
    residual (N); converged [B] bool."""

    iterations: np.ndarray
    residual: np.ndarray
    converged: np.ndarray


def sample_dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Per-sample inner product [B] of two [B, N, 2] arrays."""
    return np.einsum("bij,bij->b", u, v)


def per_sample(s: np.ndarray) -> np.ndarray:
    """Per-sample scalars [B] -> [B, 1, 1] for broadcasting against [B, N, 2]."""
    return s[:, None, None]


def max_nodal_norm(g: np.ndarray) -> np.ndarray:
    """max_i |g_i| per sample [B] of a [B, N, 2] nodal vector field."""
    return np.sqrt(g[:, :, 0] ** 2 + g[:, :, 1] ** 2).max(1)


class Objective:
    """Phi and grad Phi of one step for a batch (y [B, N, 2], contraction [n_act, B], E [B]): the
    compiled packed.objective; with ``fused`` set False, the numpy local step (elastic.py, the
    tests' independent reference)."""

    def __init__(self, model: SolidModel, Y: np.ndarray, contraction: np.ndarray, E: np.ndarray):
        self.model, self.Y, self.contraction, self.E = model, Y, contraction, E
        self.fused = True
        if self.fused:
            self.kernel_arrays = kernel_arrays(model, contraction, E)

    def __call__(self, X: np.ndarray, samples: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(Phi [B] in J per unit depth, grad Phi [B, N, 2] in N per unit depth); with a [B] mask
        `samples`, only those samples' entries are needed (the compiled path computes only
        them and leaves the others unspecified)."""
        model = self.model
        if self.fused:
            g = np.empty_like(X)
            which = np.arange(len(self.E)) if samples is None else np.flatnonzero(samples)
            phi = np.zeros((len(X), 1))
            packed.objective(X, self.Y, self.kernel_arrays, which, g, phi)
            return phi[:, 0], g
        Xc = elastic.to_columns(X)
        p = elastic.project(model, elastic.deformation_gradients(model, Xc), self.contraction, self.E)
        energy, S = elastic.energy_and_stress(model, p)
        MD = model.mass_h2[None, :, None] * (X - self.Y)
        grad = MD + elastic.from_columns(model.fem.G.T @ S.reshape(-1, Xc.shape[1]))
        return sample_dot(X - self.Y, MD) / 2 + energy, grad


class History:
    """L-BFGS memory: the last m pairs s = X_k+1 - X_k, y = g_k+1 - g_k ([m, B, N, 2] ring
    buffers) and rho = 1 / s.y per sample ([m, B]; 0 marks a pair a sample does not use)."""

    def __init__(self, m: int, like: np.ndarray):
        self.S, self.Y = np.zeros((m, *like.shape)), np.zeros((m, *like.shape))
        self.rho = np.zeros((m, like.shape[0]))
        self.count, self.head = 0, 0

    def push(self, X_new: np.ndarray, X: np.ndarray, g_new: np.ndarray, g: np.ndarray) -> None:
        """Store s = X_new - X, y = g_new - g and rho = 1 / s.y (0 where s.y <= 0: not used)."""
        s = np.subtract(X_new, X, out=self.S[self.head])
        y = np.subtract(g_new, g, out=self.Y[self.head])
        sy = sample_dot(s, y)
        self.rho[self.head] = np.where(sy > 1e-300, 1.0 / np.where(sy > 1e-300, sy, 1.0), 0.0)
        self.head = (self.head + 1) % len(self.S)
        self.count = min(self.count + 1, len(self.S))

    def forget(self, samples: np.ndarray) -> None:
        """Drop every pair of the samples marked in the [B] mask."""
        self.rho[:, samples] = 0.0

    def newest_first(self) -> np.ndarray:
        return (self.head - 1 - np.arange(self.count)) % len(self.S)


def _two_loop(g: np.ndarray, history: History, precondition, active: np.ndarray) -> np.ndarray:
    """L-BFGS direction -H g with H_0 = A^-1 (compiled two-loop recursion, kernels.py); only the
    `active` [B] samples are computed (the others are 0)."""
    q = np.array(g, order="C")                           # the kernels need C order
    order = history.newest_first()
    alphas = np.zeros((len(order), len(active)))
    samples = np.flatnonzero(active)
    kernels.lbfgs_first_loop(q, history.S, history.Y, history.rho, order, samples, alphas)
    r = np.ascontiguousarray(precondition(q, active))
    kernels.lbfgs_second_loop(r, history.S, history.Y, history.rho, order, samples, alphas)
    return -r * per_sample(active)


def pd_solve(model: SolidModel, Y: np.ndarray, X0: np.ndarray, contraction: np.ndarray,
             E: np.ndarray, cache: SolverCache) -> tuple[np.ndarray, ForwardInfo]:
    """q+ = argmin Phi for every sample. Y, X0: [B, N, 2]; contraction [n_act, B]; E [B];
    cache: the preconditioner's factors kept between steps (read and updated).
    Returns (X [B, N, 2], ForwardInfo). The preconditioner is built only if some sample needs an
    iteration (a start that is already converged, e.g. a checkpoint recomputation's, costs one
    residual evaluation). With the default preconditioner the samples run their whole solve
    compiled (_solve_compiled); a sample whose Newton matrix
    has no banded Cholesky factor goes to the batched numpy iteration (_lbfgs) with a sparse LU.
    A sample still above atol after max_iter iterations with a Newton-type H0 continues, for up
    to max_iter more, with the PD matrix A(E) as H0, positive definite whatever the shape.
    (Measured: a uniform 0.5 N per node on the coarse fish, 560 m/s^2, stalled at 4e-5 N with
    either Newton H0 even after 2000 iterations; with A(E) it converges in ~300.)"""
    opts = model.options
    objective = Objective(model, Y, contraction, E)
    X = X0.copy()
    phi, g = objective(X)
    iterations = np.zeros(len(X), np.int64)
    need = max_nodal_norm(g) > opts.atol
    lagged = opts.preconditioner == "lagged_newton"
    if objective.fused and lagged and need.any():
        need = need & ~_solve_compiled(objective, cache, X, g, need, iterations)
    if need.any():
        X, g = _lbfgs(objective, _preconditioner(model, cache, X0, contraction, E), X, phi, g, need, iterations)
    stuck = max_nodal_norm(g) > opts.atol
    if stuck.any() and opts.preconditioner != "pd":          # a Newton H0 failed: DiffPD's A(E)
        phi, g_stuck = objective(X, stuck)                    # the converged samples keep their g
        g = np.where(per_sample(stuck), g_stuck, g)
        X, g = _lbfgs(objective, Preconditioner(model, cache, E, None, "pd"), X, phi, g, stuck, iterations)
    if lagged and cache.lagged is not None:
        cache.lagged.refresh(model, iterations)
    X, g = _remove_net_residual(model, X, g)
    residual = max_nodal_norm(g)
    converged = residual <= opts.atol
    if not converged.all():
        warnings.warn(f"PD step did not converge in {opts.max_iter} iterations "
                      f"(max residual {residual.max():.3g} N > atol {opts.atol:g} N)", RuntimeWarning, stacklevel=3)
    return X, ForwardInfo(iterations, residual, converged)


# Fewest samples to solve in lanes of packs (packed.py) rather than one per thread. Default fish,
# 2 cores, forward / backward ms per step, packs against one sample per thread: B = 4 11-13 /
# 3.3-4.9 against 12-13 / 4.5-5.4; B = 8 10.5 / 3.9-4.2 against 21 / 6.4-7.9.
PACK_MIN = 4


def packs_of(samples: np.ndarray) -> np.ndarray:
    """The samples (indices) dealt into packs [P, LANES] in order, the last pack padded with
    copies of its last sample (their results are the same and are dropped)."""
    P = -(-len(samples) // LANES)
    lanes = np.full(P * LANES, samples[-1], np.int64)
    lanes[:len(samples)] = samples
    return lanes.reshape(P, LANES)


def to_packs(a: np.ndarray, lanes: np.ndarray) -> np.ndarray:
    """Per-sample arrays [B, ...] -> the packs' [P, ..., LANES] (lanes [P, LANES] of packs_of)."""
    return np.ascontiguousarray(np.moveaxis(a[lanes], 1, -1))


def from_packs(a: np.ndarray, lanes: np.ndarray, out: np.ndarray) -> None:
    """out[lanes] = the packs' a [P, ..., LANES] (inverse of to_packs)."""
    out[lanes] = np.moveaxis(a, -1, 1)


def pack_arrays(arrays: tuple, lanes: np.ndarray) -> tuple:
    """packed.kernel_arrays' per-sample arrays (w_corotated, stretch: [B, .]) dealt into packs
    [P, ., LANES]."""
    mass_h2, triangles, grad, w_corotated, w_volume, muscle_of, w_muscle, stretch = arrays
    return (mass_h2, triangles, grad, to_packs(w_corotated, lanes), to_packs(w_volume, lanes), muscle_of, w_muscle,
            to_packs(stretch, lanes))


def _solve_compiled(objective: Objective, cache: SolverCache, X: np.ndarray, g: np.ndarray, need: np.ndarray,
                    iterations: np.ndarray) -> np.ndarray:
    """The `need` [B] samples' whole forward solves compiled (packed.lbfgs), in place on X, g
    and iterations: from PACK_MIN samples on in packs of eight lanes, each lane's Newton matrix
    factorised at the start X; below that one sample per thread, with its lagged factor
    (cache.lagged), refactorised only where stale. Returns the [B] mask of samples solved; the
    others (neither their exact nor their projected Newton matrix banded-Cholesky factorisable)
    have not moved, and are marked for the numpy iteration's sparse LU."""
    model, opts = objective.model, objective.model.options
    samples, band, B = np.flatnonzero(need), model.pack_band, len(X)
    solved = np.zeros(B, bool)
    if len(samples) >= PACK_MIN:
        lanes = packs_of(samples)
        P = len(lanes)
        Xp, gp = to_packs(X, lanes), np.empty((P, *X.shape[1:], LANES))
        its, ok = np.zeros(lanes.shape), np.zeros(lanes.shape)
        packed.lbfgs(Xp, to_packs(objective.Y, lanes), pack_arrays(objective.kernel_arrays, lanes), band.arrays,
                     band.empty(P), np.ones(P, bool), np.arange(P), opts.atol, opts.max_iter, opts.history, gp, its, ok)
        from_packs(Xp, lanes, X)                          # lanes not solved have not moved
        from_packs(gp, lanes, g)
        iterations[lanes] = its
        solved[lanes[ok > 0]] = True
    else:
        lagged = lagged_factors(model, cache, B)
        stale = need & ~lagged.valid
        its = np.zeros((B, 1))
        order = balanced_order(samples, (lagged.iterations + _FACTOR_COST * stale)[need], numba.get_num_threads())
        packed.lbfgs(X, objective.Y, objective.kernel_arrays, band.arrays, lagged.L, stale, order, opts.atol,
                     opts.max_iter, opts.history, g, its, lagged.ok)
        lagged.valid |= stale
        iterations[samples] = its[samples, 0]
        solved = need & lagged.banded
    if (need & ~solved).any():
        lagged_factors(model, cache, B).valid[need & ~solved] = False
    return solved


# A Newton factorisation's cost in L-BFGS iterations (default fish: ~1 ms against ~0.2 ms).
_FACTOR_COST = 5


def balanced_order(samples: np.ndarray, cost: np.ndarray, threads: int) -> np.ndarray:
    """The samples reordered so that numba's static prange schedule (the index list cut into
    `threads` equal contiguous chunks) gives each thread a similar total estimated cost: sorted
    by cost, dealt to the threads in a snake (0, 1, ..., t-1, t-1, ..., 0, 0, ...)."""
    chunks = [[] for _ in range(threads)]
    for rank, k in enumerate(np.argsort(-cost, kind="stable")):
        lap, seat = divmod(rank, threads)
        chunks[seat if lap % 2 == 0 else threads - 1 - seat].append(samples[k])
    return np.array([s for chunk in chunks for s in chunk], np.int64)


def _lbfgs(objective: Objective, precondition, X: np.ndarray, phi: np.ndarray, g: np.ndarray,
           samples: np.ndarray, iterations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batched L-BFGS (numpy, with the compiled objective and two-loop recursion where available)
    for the samples of the [B] mask `samples`, from X (Phi phi [B], gradient g [B, N, 2]) until
    each sample's residual is <= atol or max_iter; converged samples stop moving while others
    iterate, the others in X and g are left as they are. Adds each sample's iterations to
    `iterations` [B]; returns (X, g)."""
    opts = objective.model.options
    history = History(opts.history, X)
    for _ in range(opts.max_iter):
        active = samples & (max_nodal_norm(g) > opts.atol)
        if not active.any():
            break
        iterations += active
        d = _two_loop(g, history, precondition, active)
        slope = sample_dot(g, d)
        uphill = (slope >= 0) & active
        if uphill.any():                                  # not a descent direction: restart
            history.forget(uphill)
            d = np.where(per_sample(uphill), -precondition(g, uphill), d)
            slope = sample_dot(g, d)
        X_new, phi_new, g_new = _line_search(objective, X, phi, g, d, slope, active)
        history.push(X_new, X, g_new, g)
        X, phi, g = X_new, phi_new, g_new
    return X, g


def _preconditioner(model: SolidModel, cache: SolverCache, X0: np.ndarray, contraction: np.ndarray, E: np.ndarray):
    """The forward's initial inverse Hessian (options.preconditioner) at the start X0."""
    if model.options.preconditioner == "lagged_newton":
        return LaggedNewton(model, cache, X0, contraction, E)
    return Preconditioner(model, cache, E, X0, model.options.preconditioner)


def _remove_net_residual(model: SolidModel, X: np.ndarray, g: np.ndarray):
    """Translate each sample by -sum_i g_i / sum_i (m_i / h^2): grad Phi changes by M/h^2 times
    the shift (f_int is translation invariant), so afterwards sum_i g_i = 0 exactly."""
    shift = g.sum(1, keepdims=True) / model.mass_h2.sum()
    return X - shift, g - model.mass_h2[None, :, None] * shift


def _line_search(objective, X, phi, g, d, slope, active, max_halvings: int = 30):
    """Backtracking per sample from t = 1, halving t until the step is accepted: by Armijo's
    test Phi(X + t d) <= Phi + c1 t slope (a change within round-off of Phi counts), or by the
    approximate Wolfe test (Hager & Zhang 2005) sigma slope <= Phi'(t) <= (2 c1 - 1) slope with
    Phi(X + t d) <= (1 + flat) Phi, where Phi'(t) = grad Phi(X + t d) . d (c1 = 1e-4,
    sigma = 0.9, flat = 1e-10: packed.ARMIJO_C1, WOLFE_SIGMA, WOLFE_FLAT, shared with the
    compiled solve). Near the minimiser the
    decrease of Phi falls below its round-off while Phi' stays exact to the gradient's: Armijo's
    test alone then rejected good steps at random, halving t to nothing, and tight tolerances
    stalled. Only the `active` [B] samples move (and are evaluated); the others keep X, phi and g."""
    t = np.ones_like(phi)
    X_new = X + d
    phi_new, g_new = objective(X_new, active)
    rest = ~active
    phi_new[rest], g_new[rest] = phi[rest], g[rest]
    for _ in range(max_halvings):
        dphi = sample_dot(g_new, d)
        armijo = phi_new - phi <= packed.ARMIJO_C1 * t * slope + packed.PHI_ROUND_OFF * np.abs(phi)
        wolfe = ((dphi <= (2 * packed.ARMIJO_C1 - 1) * slope) & (dphi >= packed.WOLFE_SIGMA * slope)
                 & (phi_new - phi <= packed.WOLFE_FLAT * np.abs(phi)))
        ok = rest | armijo | wolfe
        if ok.all():
            break
        redo = ~ok
        t[redo] /= 2
        X_new[redo] = X[redo] + per_sample(t[redo]) * d[redo]
        phi_try, g_try = objective(X_new, redo)
        phi_new[redo], g_new[redo] = phi_try[redo], g_try[redo]
    return X_new, phi_new, g_new


class NewtonOperator:
    """V -> (A - dA) V = M/h^2 V + G^T dS[G V], the Newton matrix at the projections p (V [B, N, 2])."""

    def __init__(self, model: SolidModel, p: elastic.Projections):
        self.model, self.p = model, p

    def __call__(self, V: np.ndarray) -> np.ndarray:
        Vc = elastic.to_columns(V)
        dS = elastic.stress_differential(self.model, self.p, elastic.deformation_gradients(self.model, Vc))
        KV = elastic.from_columns(self.model.fem.G.T @ dS.reshape(-1, Vc.shape[1]))
        return self.model.mass_h2[None, :, None] * V + KV


def newton_solve(model: SolidModel, X: np.ndarray, contraction: np.ndarray, E: np.ndarray, b: np.ndarray,
                 method: str | None = None, cache: SolverCache | None = None) -> tuple[np.ndarray, int, int]:
    """x = (A - dA)^-1 b for every sample (b, x: [B, N, 2]) with the Newton matrix at positions
    X [B, N, 2] (contraction [n_act, B], E [B]); cache: where CG's preconditioner factors are
    kept (default: a fresh one). Returns (x, CG iterations, number of samples solved directly)."""
    method = method or model.options.backward_method
    B = b.shape[0]
    if method == "direct":
        return _direct_solve(model, X, contraction, E, b, np.arange(B)), 0, B
    apply_K = NewtonOperator(model, elastic.projections_at(model, X, contraction, E))
    precondition = Preconditioner(model, cache or SolverCache(), E, X, "rest_newton")
    on_numpy = lambda f: lambda t: torch.from_numpy(np.ascontiguousarray(f(t.numpy())))
    x, ok, its = pcg(on_numpy(apply_K), on_numpy(precondition), torch.from_numpy(np.ascontiguousarray(b)),
                     lambda r: torch.from_numpy(max_nodal_norm(r.numpy())), model.options.backward_rtol,
                     model.options.backward_max_iter)
    x, ok = x.numpy(), ok.numpy()
    failed = np.flatnonzero(~ok)
    if len(failed) and method == "auto":
        x[failed] = _direct_solve(model, X, contraction, E, b, failed)[failed]
    elif len(failed):
        warnings.warn(f"adjoint PCG did not converge for {len(failed)} samples", RuntimeWarning, stacklevel=3)
    return x, its, len(failed) if method == "auto" else 0


def _direct_solve(model: SolidModel, X: np.ndarray, contraction: np.ndarray, E: np.ndarray, b: np.ndarray,
                  samples: np.ndarray) -> np.ndarray:
    """Direct solve of the assembled Newton matrix at X [B, N, 2] for the given samples of b
    [B, N, 2]: banded Cholesky when it is positive definite (_banded_solve), else sparse LU
    (banded.lu_factor)."""
    x = np.zeros(b.shape)
    rest = np.setdiff1d(samples, _banded_solve(model, X, contraction, E, b, samples, x))   # not positive definite
    if len(rest):
        p = elastic.projections_at(model, X, contraction, E)
        for s in rest:
            x[s] = lu_factor(elastic.newton_matrix(model, p, int(s))).solve(b[s].reshape(-1)).reshape(-1, 2)
    return x


def _banded_solve(model: SolidModel, X: np.ndarray, contraction: np.ndarray, E: np.ndarray, b: np.ndarray,
                  samples: np.ndarray, x: np.ndarray) -> np.ndarray:
    """x[s] = K_s^-1 b[s] for the samples whose Newton matrix K_s is positive definite, assembled,
    factorised and solved by banded Cholesky in parallel over the samples (packed.newton_solve;
    from PACK_MIN samples on, eight per pack). Returns the samples solved."""
    arrays, band = kernel_arrays(model, contraction, E), model.pack_band
    if len(samples) >= PACK_MIN:
        lanes = packs_of(samples)
        P = len(lanes)
        Z, ok = np.empty((P, *b.shape[1:], LANES)), np.zeros(lanes.shape)
        packed.newton_solve(to_packs(X, lanes), to_packs(b, lanes), pack_arrays(arrays, lanes), band.arrays,
                            band.empty(P), np.arange(P), Z, ok)
        from_packs(Z, lanes, x)
        return np.unique(lanes[ok > 0])
    ok = np.zeros((len(b), 1))
    packed.newton_solve(np.ascontiguousarray(X, np.float64), np.ascontiguousarray(b, np.float64), arrays,
                        band.arrays, band.empty(len(b), 1), samples, x, ok)
    return samples[ok[samples, 0] > 0]
