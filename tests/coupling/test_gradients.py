"""Gradients of b, v_d and f against central finite differences (float64, small grid).

gradcheck in fast mode: the Jacobian is compared along random directions (u^T J v), which
keeps the file at a few seconds on 2 cores.
"""

import math

import pytest
import torch
from torch.autograd import gradcheck

from fishsim.coupling import CouplingConfig, boundary_velocity, fluid_to_solid, ibm_force, soft_mask
from fishsim.fields import Boundary, Grid

GRID = Grid(H=14, W=20, dx=2.5e-3)


def small_body(n=10, seed=0):
    """A jittered ccw ellipse of n nodes (10 mm x 6 mm semi-axes) inside the small grid."""
    g = torch.Generator().manual_seed(seed)
    t = 2 * math.pi * (torch.arange(n, dtype=torch.float64) + 0.3 * torch.rand(n, generator=g, dtype=torch.float64)) / n
    r = 1 + 0.05 * torch.rand(n, generator=g, dtype=torch.float64)
    q = torch.stack([0.0251 + 0.010 * r * torch.cos(t), 0.0173 + 0.006 * r * torch.sin(t)], -1)
    return q[None].requires_grad_(True)


@pytest.mark.parametrize("distance, mean", [("segment", "harmonic"), ("segment", "arithmetic"), ("node", "arithmetic")])
def test_mask_gradient(distance, mean):
    qs = small_body()
    fn = lambda q: soft_mask(q, GRID, distance=distance, mean=mean, dtype=torch.float64)
    assert gradcheck(fn, (qs,), eps=1e-7, atol=1e-6, rtol=1e-4, fast_mode=True)


@pytest.mark.parametrize("distance", ["segment", "node"])
def test_boundary_velocity_gradient(distance):
    qs = small_body()
    qdots = torch.randn(1, qs.shape[1], 2, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    qdots.requires_grad_(True)

    def fn(q, qd):
        return boundary_velocity(q, qd, soft_mask(q, GRID, distance=distance, dtype=torch.float64),
                                 GRID, distance=distance)

    assert gradcheck(fn, (qs, qdots), eps=1e-7, atol=1e-6, rtol=1e-4, fast_mode=True)


@pytest.mark.parametrize("weight, fit", [("fluid", "linear"), ("body", "mean")])
def test_ibm_force_gradient(weight, fit):
    qs = small_body()
    g = torch.Generator().manual_seed(2)
    p = (100 * torch.randn(1, 1, GRID.H, GRID.W, dtype=torch.float64, generator=g)).requires_grad_(True)

    def fn(q, pressure):
        mask = soft_mask(q, GRID, dtype=torch.float64)
        return ibm_force(q, pressure, mask, GRID, weight=weight, fit=fit)

    assert gradcheck(fn, (qs, p), eps=1e-7, atol=1e-6, rtol=1e-4, fast_mode=True)


def test_ibm_force_gradient_with_the_wall_fit():
    """``fit="wall"``: differentiable in the node positions, the pressure and the accelerations
    whose slope -rho a.n it imposes."""
    qs = small_body()
    g = torch.Generator().manual_seed(4)
    p = (100 * torch.randn(1, 1, GRID.H, GRID.W, dtype=torch.float64, generator=g)).requires_grad_(True)
    a = torch.randn(qs.shape, dtype=torch.float64, generator=g).requires_grad_(True)

    def fn(q, pressure, acceleration):
        mask = soft_mask(q, GRID, dtype=torch.float64)
        return ibm_force(q, pressure, mask, GRID, fit="wall", wall=(acceleration, 50.0))

    assert gradcheck(fn, (qs, p, a), eps=1e-7, atol=1e-6, rtol=1e-4, fast_mode=True)


def test_layer_gradient_through_a_fixed_boundary():
    """fluid_to_solid w.r.t. node positions and pressure, average mode with burn-in."""
    qs = small_body()
    mask = soft_mask(qs.detach(), GRID, dtype=torch.float64)
    boundary = Boundary(mask, torch.zeros(1, 2, GRID.H, GRID.W, dtype=torch.float64))
    p = torch.randn(1, 1, GRID.H, GRID.W, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    cfg = CouplingConfig(force_mode="average", n_burn_in=4)
    surface = torch.arange(qs.shape[1])
    fn = lambda q, pr: fluid_to_solid(q, pr, boundary, surface, GRID, cfg, step=3)
    assert gradcheck(fn, (qs, p.requires_grad_(True)), eps=1e-7, atol=1e-6, rtol=1e-4, fast_mode=True)
