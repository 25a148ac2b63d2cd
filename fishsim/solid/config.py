"""The solid's settings: its material (paper Sec. 4.1) and the PD solver's options. Plain
values, no numpy or torch, so the CLI's config (``fishsim.config``) imports them for a command's
help without the solver; ``SolidModel`` (model.py) takes both.
"""

from __future__ import annotations

from dataclasses import dataclass

from fishsim.errors import ConfigError


@dataclass(frozen=True)
class SolidMaterial:
    """Material of the fish (paper Sec. 4.1), SI units.

    youngs_modulus: E in Pa (default per sample; a step may pass its own E, shape [B]).
    poisson_ratio: nu, dimensionless.
    density: rho_s in kg/m^3 (per unit area in 2D).
    muscle_stiffness: k_m in Pa; a muscle element's PD weight is k_m * area. Default = E: an
        isolated element then reaches k_m / (k_m + 2 mu_s) = 59 % of its target contraction,
        so the muscles are neither a weak perturbation nor a constraint that dominates the
        tissue (DiffAqua uses 0.4 E, the DiffPD water snake 0.1 E); the controller's amplitude
        C is calibrated on top of this value.
    volume_term: add the lambda_s area / 2 ||F - closest det-1 matrix||^2 energy (DiffPD's
        'volume'). Off by default, like DiffPD's underwater examples (co-rotated only), and about
        half the cost (default fish, B = 1, one thread: 7 against 15 ms a step forward). Measured on the default fish at the calibrated 5 Hz stroke (vacuum): with it
        the tail's peak-to-peak excursion drops from 30.1 to 22.4 mm and the largest element
        area change from 29 % (contracting muscle elements) to 10 %; so it matters for
        nu = 0.45 and is worth switching on when area conservation is important.
    """

    youngs_modulus: float = 6e5
    poisson_ratio: float = 0.45
    density: float = 100.0
    muscle_stiffness: float = 6e5
    volume_term: bool = False

    def __post_init__(self):
        if not self.youngs_modulus > 0 or not self.density > 0 or not self.muscle_stiffness >= 0:
            raise ConfigError("solid material needs youngs_modulus > 0, density > 0, muscle_stiffness >= 0")
        if not -1 < self.poisson_ratio < 0.5:
            raise ConfigError(f"poisson_ratio must lie in (-1, 0.5), got {self.poisson_ratio}")

    @property
    def corotated_per_E(self) -> float:
        """2 mu_s / E = 1 / (1 + nu)."""
        return 1.0 / (1.0 + self.poisson_ratio)

    @property
    def volume_per_E(self) -> float:
        """lambda_s / E = nu / ((1 + nu)(1 - 2 nu)) if the volume term is on, else 0."""
        nu = self.poisson_ratio
        return nu / ((1 + nu) * (1 - 2 * nu)) if self.volume_term else 0.0


@dataclass(frozen=True)
class PDOptions:
    """Solver settings.

    atol: forward stopping rule, max over nodes of |M/h^2 (q+ - y) - f_int(q+)| <= atol, in N
        (per unit depth). Absolute, so it does not depend on where the fish is (DiffPD's
        relative rule scales with |q|). 1e-8 N is ~1e-10 of the largest nodal muscle forces of
        the default fish (~100 N) and ~1e-6 of the nodal inertial forces at 5 Hz; the net
        residual is removed exactly (solve.py), so momentum does not drift with atol. Measured
        (100 frames, default fish and tank, numerical fluid, one thread, 2026-11-28): the solid
        takes 1.2-1.4 s at 1e-5 N, 1.5 s at 1e-8 N, 1.8 s at 1e-10 N; the mean x of the fish
        differs from the 1e-10 N one by 8e-8 m at 1e-5 N and 2e-9 m at 1e-8 N, and HydroNet's
        d(distance)/d(frequency) by -1.5 % at 1e-5 N and 0.02 % at 1e-8 N. (1e-5 N was the
        default while tighter solves stalled in the line search; docs/physics.md section 3.)
    max_iter: forward L-BFGS iterations before giving up (a warning, and info.converged False).
    history: L-BFGS memory (pairs kept).
    backward_rtol: adjoint stopping rule, |(A - dA) x - b|_max <= backward_rtol |b|_max.
    backward_max_iter: preconditioned CG iterations before a direct sparse solve takes over.
    backward_method: 'direct' (default: per sample, the assembled Newton matrix factorised by
        banded Cholesky, in parallel over the samples, eight per SIMD pack from 4 samples on, LU
        if it is indefinite; bench_solid on the default fish, 2 cores: B = 1 1.3-2.5 ms per
        step, B = 16 3.5-5.6 ms), 'auto' (batched PCG
        preconditioned with 'rest_newton', direct for samples where it fails; ~41 iterations,
        16.8 ms and 248 ms when last measured) or 'pcg'.
    preconditioner: initial inverse Hessian H0 of the forward L-BFGS:
        'lagged_newton' (default): per sample, the Newton matrix (exact where positive definite,
        else its projection) factorised at the start of a step and kept for the following steps
        until a step needs more than `refresh_iterations` iterations (then refactorised at the
        next step's start); batches of 4 or more samples (solved eight per SIMD pack, in lock
        step) refactorise at every step's start instead, which costs a pack little;
        'rest_newton': the Newton matrix of the rest shape, M/h^2 + K(rest), rotated per sample
        into the best-fit rigid frame of the current shape, factorised once per E;
        'pd': DiffPD's per-axis PD matrix A(E), factorised once per E.
        Measured on the default fish (5 Hz controller, atol 1e-5 N): 'pd' ~150 iterations per
        step (A penalises the element rotations of bending as much as stretching), 'rest_newton'
        ~10 at small amplitude but 20-80 at the calibrated amplitude, 'lagged_newton' a few.
        The adjoint CG is always preconditioned with 'rest_newton' (shared by the batch).
    refresh_iterations: see 'lagged_newton'. 8: a refactorisation costs less than the
        iterations a staler factor adds; with the rollout's predicted start B = 1 takes ~10
        iterations per step (B >= 4 runs in packs, which refactorise every step). On the default
        fish (1803 nodes, half-bandwidth 41) a refactorisation assembles (0.4 ms) and factorises
        (1.2 ms) the exact Newton matrix, and again its projection where that is indefinite (at
        35 of a 5 Hz episode's first 150 steps): 1.6-3.5 ms, as much as 5-10 iterations.
        Measured (a 90-frame 5 Hz episode, the solid's ms a frame, two runs each): 8: 10.1-11.3,
        16: 9.1-10.3, 32: 13.7-13.9, never: 133-143.
    """

    atol: float = 1e-8
    max_iter: int = 500
    history: int = 8
    backward_rtol: float = 1e-8
    backward_max_iter: int = 200
    backward_method: str = "direct"
    preconditioner: str = "lagged_newton"
    refresh_iterations: int = 8

    def __post_init__(self):
        if self.preconditioner not in ("lagged_newton", "rest_newton", "pd"):
            raise ConfigError(f"preconditioner must be lagged_newton, rest_newton or pd, got {self.preconditioner!r}")
        if self.backward_method not in ("auto", "pcg", "direct"):
            raise ConfigError(f"backward_method must be auto, pcg or direct, got {self.backward_method!r}")
        if not (self.atol > 0 and self.backward_rtol > 0 and self.max_iter > 0 and self.history > 0):
            raise ConfigError("PD solver tolerances and iteration limits must be positive")
