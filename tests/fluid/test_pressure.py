"""Pressure recovery (fishsim/fluid/pressure.py): the weighted Poisson solve is exact, its implicit
gradient matches finite differences, and on a flow whose pressure is known (the numerical solver's
own steps) the recovered pressure is that pressure."""

import torch

from fishsim.fluid import grid as G
from fishsim.fluid.base import FluidParams, FluidState, Grid
from fishsim.fluid.numerical import NumericalFluid
from fishsim.fluid.pressure import RecoveryConfig, WeightedPoisson, recover_pressure, solve_weighted_poisson

D = torch.float64


def _weights(g: Grid, low: float):
    torch.manual_seed(0)
    return (low + torch.rand(1, 1, g.H, g.W + 1, dtype=D), low + torch.rand(1, 1, g.H + 1, g.W, dtype=D))


def test_weighted_poisson_solve_recovers_a_known_pressure():
    """-div(w grad p) = f with f built from a random p and weights spanning 1e-3..1: p back to round-off."""
    g = Grid(12, 20, 0.01)
    w = _weights(g, 1e-3)
    p_true = torch.randn(1, 1, g.H, g.W, dtype=D)
    p_true -= p_true.mean()
    f = -G.divergence(tuple(wi * gi for wi, gi in zip(w, G.gradient(p_true, g.dx))), g.dx)
    p, iterations = solve_weighted_poisson(w, f, g.dx, 1e-12, 500)
    assert (p - p_true).abs().max() < 1e-9 * p_true.abs().max()
    assert iterations < 200


def test_weighted_poisson_gradient_matches_finite_differences():
    g = Grid(8, 12, 0.01)
    wx, wy = (x.requires_grad_() for x in _weights(g, 0.05))
    f = torch.randn(1, 1, g.H, g.W, dtype=D, requires_grad=True)
    solve = lambda a, b, c: WeightedPoisson.apply(a, b, c, g.dx, 1e-13, 1000)
    assert torch.autograd.gradcheck(solve, (wx, wy, f), eps=1e-6, atol=1e-7, rtol=1e-5)


def test_recovered_pressure_is_the_solvers_pressure():
    """A vortex in a closed box without bodies: on the numerical solver's step (central advection,
    as in the recovery) the recovered pressure gradient equals the solver's to time-truncation
    error (the IMEX residual vs the solver's Heun sub-steps; measured 0.1 %)."""
    g = Grid(24, 40, 0.01)
    y = torch.arange(g.H + 1, dtype=D)[:, None] / g.H
    x = torch.arange(g.W + 1, dtype=D)[None, :] / g.W
    a0 = 2e-3 * (torch.sin(torch.pi * x) * torch.sin(torch.pi * y)) ** 2  # m^2/s, max |v| ~ 0.04 m/s
    bd = G.closed_tank(g, 0, 0, 1, dtype=D)
    m = NumericalFluid(g, scheme="central")
    pr = FluidParams(torch.tensor([50.0], dtype=D), torch.tensor([0.02], dtype=D), 0.01)
    s = FluidState(a0[None, None], torch.zeros(1, 1, g.H, g.W, dtype=D))
    s2 = m.step(s, bd, pr)
    p = recover_pressure(G.curl(s.a, g.dx), G.curl(s2.a, g.dx), bd.mask, pr.rho, pr.mu, pr.h, g,
                         RecoveryConfig(tol=1e-10))
    err = max((a - b).abs().max() for a, b in zip(G.gradient(p, g.dx), G.gradient(s2.p, g.dx)))
    scale = max(b.abs().max() for b in G.gradient(s2.p, g.dx))
    assert err < 0.02 * scale
