"""Fluid -> solid by momentum exchange: the force the numerical fluid's penalization exerts on
the body, spread from the cells onto the surface nodes (``coupling.force=exchange``).

The numerical fluid enforces the body by Brinkman penalization: every sub-step it moves the
velocity of the cells the body covers (volume fraction b) towards the body's velocity. The
momentum it adds to the fluid is, by Newton's third law, taken from the body, so the body feels

    F_c = rho dx^2 (b (v' - v) / h - penalty_c)          [N per unit depth, per cell c]

(``StepDiagnostics.cell_forces``: the reaction to the penalization minus the inertia of the
fluid carried inside the body). Unlike the sampled pressure (fishsim.coupling.ibm) it holds
the viscous stress, and its total is exactly what the fluid exchanged with the body, so the
coupled system conserves momentum. Its values depend on the penalization's fixed point, not on
where a kernel samples a pressure jump.

Spreading. Each cell's force is shared among the surface nodes near it with normalised Gaussian
weights g_kc = exp(-|x_c - q^k|^2 / (2 sigma_s)) (tapered to 0 at the window's edge, as the IBM
kernel):

    f_k = sum_c share_c F_c g_kc / Z_c,     Z_c = sum_k' g_k'c

so every cell's force goes entirely to the nodes (the total force is kept; the moment to within
the kernel's width). The cell forces hold the fish's share of each face's penalization only
(``NumericalFluid`` diagnostics' ``body_share``: b_fish / b_total per face), so the tank walls'
force stays out. A cell further than the window from every node would lose its force; with
sigma_s = (1.5 dx)^2 the window reaches 6 cells (15 mm), beyond the default fish's half-width
(8 mm), and `spread_to_surface` reports the fraction lost.
"""

from __future__ import annotations

import torch
from torch import Tensor

from fishsim.coupling.config import NONE
from fishsim.coupling.ibm import kernel_cells, kernel_radius, sample_weights
from fishsim.fields import Grid

#: Variance of the spreading kernel in cell units squared (standard deviation 1.5 cells).
SPREAD_CELLS2 = 2.25


def spread_to_surface(qs: Tensor, cell_force: Tensor, grid: Grid,
                      sigma_s: float | None = None) -> tuple[Tensor, Tensor]:
    """Forces on the surface nodes [B, S, 2] N/m from the fish's cell forces [B, 2, H, W] N/m
    (module doc). qs: surface polyline [B, S, 2] (m); sigma_s: kernel variance, m^2 (default
    (1.5 dx)^2). Returns (f_k in qs.dtype, the fraction of the total force |sum_c F_c| that
    reached no node, [B]). Differentiable in qs and cell_force.
    """
    sigma_s = SPREAD_CELLS2 * grid.dx**2 if sigma_s is None else sigma_s
    radius = kernel_radius(sigma_s, grid.dx)
    flat, valid, ox, oy = kernel_cells(qs, grid, radius)
    B, S, M = flat.shape
    dtype = cell_force.dtype
    g = sample_weights(ox.to(dtype), oy.to(dtype), None, valid, sigma_s, NONE, grid.dx, radius)   # [B, S, M]
    Z = torch.zeros(B, grid.H * grid.W, dtype=dtype, device=qs.device).scatter_add(1, flat.reshape(B, -1),
                                                                                  g.reshape(B, -1))
    fish = cell_force                                                                     # [B, 2, H, W]
    per_weight = fish.reshape(B, 2, -1) / Z.clamp_min(torch.finfo(dtype).tiny).unsqueeze(1)
    gathered = per_weight.gather(2, flat.reshape(B, 1, -1).expand(B, 2, -1)).view(B, 2, S, M)
    f = (gathered * g.unsqueeze(1)).sum(-1).transpose(1, 2)                               # [B, S, 2]
    total = fish.sum(dim=(-2, -1))
    reached = f.sum(1)
    lost = (total - reached).norm(dim=-1) / total.norm(dim=-1).clamp_min(torch.finfo(dtype).tiny)
    return f.to(qs.dtype), lost.detach()
