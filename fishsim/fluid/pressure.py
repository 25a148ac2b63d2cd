"""Pressure recovered from a step's velocities: the pressure that best satisfies the momentum
equation on the fluid faces (used for HydroNet's forces, ``HydroNetFluid(pressure="recovered")``).

Why. HydroNet's loss constrains its pressure output only through grad p in the fluid residual, and
the shipped network's pressure lags its own velocities: on the 5 Hz fish scene the L_p-optimal
pressure for the network's velocities gives ~3x the thrust and ~4x the lateral force of the
network's own pressure (close to the numerical solver's) and a 40 % lower L_p. The velocities are
the better half of the surrogate, so the pressure is recovered from them.

What. With R(p) the IMEX momentum residual (``fishsim.fluid.residual``, central advection) of
v_t -> v_t+1 in Pa/m and w_f = 1 - b_f the fluid face weights (zero on the box-wall faces),

    p = argmin_p  1/2 sum_f [ w_f (R(0)_f + (grad p)_f)^2 + eps (grad p)_f^2 ]

(R(p) = R(0) + grad p), i.e. the weighted least-squares fit of grad p to -R(0) on the fluid
faces, with a small weight eps on every face (target grad p = 0) so that the body interior,
where w ~ 0, is determined. Normal equations (grad^T = -div):

    A p = f,   A p = -div((w + eps) grad p),   f = div(w R(0))              (mean-free p)

solved by conjugate gradients preconditioned with the DCT Neumann Poisson solve (exact for
w = const). eps trades conditioning for bias: the solid faces' grad p = 0 target pulls the
pressure jump across a thin tail down. Measured on the 5 Hz fish scene (mean thrust / lateral
force amplitude, numerical solver 98.6 / 1005 mN/m; the network's own pressure 31 / 233):
eps 1e-2: 49 / 656, 37 iterations; eps 1e-3: 60 / 924; eps 1e-4: 62 / 957, 178 iterations.
The force is converged at a relative residual of 1e-2 (60.0 / 913 vs 60.2 / 923 at 1e-3, 23 vs
56 iterations), hence the defaults eps = 1e-3, tol = 1e-2.

Differentiable by implicit differentiation (``WeightedPoisson``): with lambda = A^+ dL/dp,
dL/df = lambda and dL/dw_f = -(grad lambda)_f (grad p)_f; one more solve per backward.
The gradient is the exact gradient of the converged solve (use a tight ``tol`` where it must
match finite differences, e.g. in float64 tests).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from fishsim.fluid.base import Grid
from fishsim.fluid.dct import neumann_inverse, solve_neumann_poisson
from fishsim.fluid.grid import Faces, divergence, gradient
from fishsim.fluid.residual import fluid_face_masks, momentum_residual

RECOVERED, NETWORK = "recovered", "network"
PRESSURES = (RECOVERED, NETWORK)


@dataclass(frozen=True)
class RecoveryConfig:
    """eps: weight of the solid faces (relative to 1 in the fluid); tol: relative residual
    |f - A p| / |f| at which PCG stops; max_iter: PCG iteration cap."""

    eps: float = 1e-3
    tol: float = 1e-2
    max_iter: int = 500


def _dot(a: Tensor, b: Tensor) -> Tensor:
    """Per-sample inner product [B, 1, 1, 1]."""
    return (a * b).flatten(1).sum(1).view(-1, 1, 1, 1)


def _mean_free(x: Tensor) -> Tensor:
    return x - x.mean(dim=(-2, -1), keepdim=True)


def solve_weighted_poisson(weights: Faces, f: Tensor, dx: float, tol: float,
                           max_iter: int) -> tuple[Tensor, int]:
    """Mean-free p [B, 1, H, W] with -div(weights grad p) = f - mean(f), by PCG with the DCT
    Poisson preconditioner; returns (p, iterations). weights: positive face weights (x, y)."""
    inverse = neumann_inverse(f.shape[-2], f.shape[-1], dx, f.device, f.dtype)

    def A(p: Tensor) -> Tensor:
        return -divergence(tuple(w * g for w, g in zip(weights, gradient(p, dx))), dx)

    def M(r: Tensor) -> Tensor:
        return -solve_neumann_poisson(r, dx, inverse)

    f = _mean_free(f)
    p, r = torch.zeros_like(f), f
    stop = tol * f.flatten(1).norm(dim=1)
    z = M(r)
    d, rz = z, _dot(r, z)
    it = 0
    while it < max_iter and (r.flatten(1).norm(dim=1) > stop).any():
        Ad = A(d)
        alpha = rz / _dot(d, Ad).clamp_min(torch.finfo(f.dtype).tiny)
        p, r = p + alpha * d, r - alpha * Ad
        z = M(r)
        rz_new = _dot(r, z)
        d, rz = z + rz_new / rz.clamp_min(torch.finfo(f.dtype).tiny) * d, rz_new
        it += 1
    return _mean_free(p), it


class WeightedPoisson(torch.autograd.Function):
    """p = A(w)^+ f with A(w) p = -div(w grad p), differentiable in w (faces) and f (module
    docstring); forward and backward are PCG solves to ``tol``."""

    @staticmethod
    def forward(ctx, wx: Tensor, wy: Tensor, f: Tensor, dx: float, tol: float, max_iter: int) -> Tensor:
        p, _ = solve_weighted_poisson((wx, wy), f, dx, tol, max_iter)
        ctx.save_for_backward(wx, wy, p)
        ctx.settings = (dx, tol, max_iter)
        return p

    @staticmethod
    def backward(ctx, grad_p: Tensor):
        wx, wy, p = ctx.saved_tensors
        dx, tol, max_iter = ctx.settings
        lam, _ = solve_weighted_poisson((wx, wy), grad_p, dx, tol, max_iter)
        (gl_x, gl_y), (gp_x, gp_y) = gradient(lam, dx), gradient(p, dx)
        return -gl_x * gp_x, -gl_y * gp_y, _mean_free(lam), None, None, None


def recover_pressure(v_old: Faces, v_new: Faces, mask: Tensor, rho: Tensor | float, mu: Tensor | float,
                     h: float, grid: Grid, cfg: RecoveryConfig = RecoveryConfig()) -> Tensor:
    """The pressure [B, 1, H, W] (Pa, mean free) of the module docstring for the step
    v_old -> v_new (face velocities, m/s) with the soft mask ``mask`` [B, 1, H, W]."""
    r0 = momentum_residual(v_old, v_new, torch.zeros_like(mask), rho, mu, h, grid)
    w = fluid_face_masks(mask)
    f = divergence(tuple(wi * ri for wi, ri in zip(w, r0)), grid.dx)
    wx, wy = (wi + cfg.eps for wi in w)
    return WeightedPoisson.apply(wx, wy, f, grid.dx, cfg.tol, cfg.max_iter)
