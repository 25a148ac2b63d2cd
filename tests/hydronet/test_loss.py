"""The unsupervised loss: zero on exact steady states, positive otherwise, scaled to grid units."""

import math

import torch

from fishsim.fields import Boundary, FluidParams, FluidState
from fishsim.fluid.grid import closed_tank, stream_function, vector_to_faces
from fishsim.fluid.hydronet.loss import (
    ENERGY_FLOOR,
    LossConfig,
    boundary_loss,
    energy_loss,
    hydronet_loss,
    momentum_loss,
    teacher_loss,
)
from fishsim.fluid.residual import boundary_face_masks, fluid_face_masks

from .conftest import paper_params


def _rest(grid, batch=2):
    return FluidState(torch.zeros(batch, 1, grid.H + 1, grid.W + 1), torch.zeros(batch, 1, grid.H, grid.W))


def test_zero_for_fluid_at_rest(grid):
    """a = p = 0 in a closed tank at rest solves the equations exactly: L_p = L_b = 0."""
    rest = _rest(grid)
    terms = hydronet_loss(rest, rest, closed_tank(grid, 2, 3, 2), paper_params(2), grid)
    assert terms.momentum.abs().max() == 0 and terms.boundary.abs().max() == 0
    assert terms.objective < math.log(2e-12)


def test_zero_for_uniform_stream(grid):
    """A uniform stream U (a = U y), constant in time, p = 0, with solid bands over the two rows
    next to the top/bottom box walls: steady Euler and Navier-Stokes flow, so L_p = 0."""
    U = 0.3
    y = torch.arange(grid.H + 1, dtype=torch.float64) * grid.dx
    a = (U * y)[None, None, :, None].expand(1, 1, grid.H + 1, grid.W + 1)
    state = FluidState(a, torch.zeros(1, 1, grid.H, grid.W, dtype=torch.float64))
    mask = closed_tank(grid, 2, 0, 1, dtype=torch.float64).mask
    bd = Boundary(mask, torch.zeros(1, 2, grid.H, grid.W, dtype=torch.float64))
    params = FluidParams(torch.tensor([50.0], dtype=torch.float64), torch.tensor([1.25e-4], dtype=torch.float64))
    assert momentum_loss(state, state, bd, params, grid).item() < 1e-20


def test_positive_and_grid_unit_scaling(grid):
    """A uniform pressure gradient G on fluid at rest: R = G on the interior x-faces, so
    L_p = (G / R*)^2 (fluid x-faces / all faces), R* = rho (dx/h) / h."""
    G, rho, h = 80.0, 50.0, 0.01
    x = (torch.arange(grid.W) + 0.5) * grid.dx
    p = (G * x)[None, None, None, :].expand(1, 1, grid.H, grid.W).clone()
    rest = _rest(grid, 1)
    bd = Boundary(torch.zeros(1, 1, grid.H, grid.W), torch.zeros(1, 2, grid.H, grid.W))
    lp = momentum_loss(rest, FluidState(rest.a, p), bd, paper_params(1), grid)
    fx, fy = fluid_face_masks(bd.mask)
    frac = fx.sum() / (fx.numel() + fy.numel())
    r_star = rho * (grid.dx / h) / h
    torch.testing.assert_close(lp, (G / r_star) ** 2 * frac.reshape(1), rtol=1e-5, atol=0)


def test_boundary_term_in_cells_per_step(grid):
    """Fluid at rest, walls moving at U: L_b = sum b_f (v_d,f h / dx)^2 / N, the error in cells
    per step averaged over all N faces (v_d averaged onto the faces; y-faces carry no x-velocity)."""
    U = 0.1
    tank = closed_tank(grid, 3, 3, 1)
    vd = torch.zeros(1, 2, grid.H, grid.W)
    vd[:, 0] = U * tank.mask[:, 0]
    lb = boundary_loss(_rest(grid, 1), Boundary(tank.mask, vd), paper_params(1), grid)
    bx, by = boundary_face_masks(tank.mask)
    vdx = vector_to_faces(vd)[0]
    expected = (bx * (vdx * 0.01 / grid.dx) ** 2).sum() / (bx.numel() + by.numel())
    torch.testing.assert_close(lb, expected.reshape(1))
    assert 0.0 < lb.item() < 0.5 * (U * 0.01 / grid.dx) ** 2


def test_dimensionless_in_rho():
    """Same velocities, p proportional to rho and mu proportional to rho: identical loss."""
    from fishsim.fields import Grid

    grid = Grid(12, 20)
    g = torch.Generator().manual_seed(1)
    old = FluidState(1e-4 * torch.randn(1, 1, 13, 21, generator=g), torch.zeros(1, 1, 12, 20))
    a_new = old.a + 1e-5 * torch.randn(1, 1, 13, 21, generator=g)
    p = torch.randn(1, 1, 12, 20, generator=g)
    bd = closed_tank(grid, 2, 2, 1)
    t1 = hydronet_loss(old, FluidState(a_new, p), bd, paper_params(1, 10.0, 2e-4), grid)
    t5 = hydronet_loss(old, FluidState(a_new, 5 * p), bd, paper_params(1, 50.0, 1e-3), grid)
    torch.testing.assert_close(t1.total, t5.total, rtol=1e-4, atol=0)


def test_weights_and_log_objective(grid):
    """L = beta L_p + gamma L_b per sample, objective = mean log L."""
    g = torch.Generator().manual_seed(0)
    old = _rest(grid)
    new = FluidState(1e-4 * torch.randn(2, 1, grid.H + 1, grid.W + 1, generator=g),
                     torch.randn(2, 1, grid.H, grid.W, generator=g))
    bd = closed_tank(grid, 2, 3, 2)
    t = hydronet_loss(old, new, bd, paper_params(2), grid, LossConfig(2.0, 5.0, 0.0))
    assert (t.momentum > 0).all() and (t.boundary > 0).all()
    torch.testing.assert_close(t.total, 2 * t.momentum + 5 * t.boundary)
    torch.testing.assert_close(t.objective, torch.log(t.total).mean())


def test_stream_function_flow_has_zero_boundary_error(grid):
    """v_d equal to the fluid's own velocity on the mask (a rigid translation of everything)
    gives L_b = 0."""
    U = (0.2, -0.1)
    v = (torch.full((1, 1, grid.H, grid.W + 1), U[0]), torch.full((1, 1, grid.H + 1, grid.W), U[1]))
    a = stream_function(v, grid.dx)
    vd = torch.tensor(U).reshape(1, 2, 1, 1).expand(1, 2, grid.H, grid.W)
    tank = closed_tank(grid, 2, 2, 1)
    lb = boundary_loss(FluidState(a, torch.zeros(1, 1, grid.H, grid.W)), Boundary(tank.mask, vd),
                       paper_params(1), grid)
    assert lb.item() < 1e-10


def test_koren_residual_sees_checkerboard_noise(grid):
    """A steady uniform stream carrying a 2-cell checkerboard in a: central differences barely
    see it (only through the small viscosity), Koren's upwind interpolation does (>= 100x)."""
    U, eps = 0.25, 2e-6  # m/s; checkerboard of 0.13 A* in the potential
    i = torch.arange(grid.H + 1, dtype=torch.float64)[:, None]
    j = torch.arange(grid.W + 1, dtype=torch.float64)[None, :]
    a = (U * i * grid.dx + eps * (-1.0) ** (i + j))[None, None]
    state = FluidState(a, torch.zeros(1, 1, grid.H, grid.W, dtype=torch.float64))
    bd = Boundary(closed_tank(grid, 3, 0, 1, dtype=torch.float64).mask,
                  torch.zeros(1, 2, grid.H, grid.W, dtype=torch.float64))
    params = FluidParams(torch.tensor([50.0], dtype=torch.float64), torch.tensor([1.25e-4], dtype=torch.float64))
    central = momentum_loss(state, state, bd, params, grid, "central")
    koren = momentum_loss(state, state, bd, params, grid, "koren")
    assert koren > 100 * central


def test_teacher_term_is_zero_on_the_solvers_own_step_and_counts_cells_per_step(grid):
    """L_t vanishes when the network's step is the numerical solver's (a moving body in the
    tank), and a uniform velocity error of one cell per step on every face gives L_t = 1."""
    from fishsim.fluid.grid import union
    from fishsim.fluid.numerical import NumericalFluid

    tank = closed_tank(grid, 2, 3, 1)
    yy, xx = torch.meshgrid(torch.arange(grid.H), torch.arange(grid.W), indexing="ij")
    disc = (((xx - grid.W / 2) ** 2 + (yy - grid.H / 2) ** 2) < 9).float()[None, None]
    body = Boundary(disc, torch.stack([0.1 * disc[:, 0], 0.05 * disc[:, 0]], 1))
    boundary = union(tank, body)
    params = paper_params(1)
    start = _rest(grid, 1)
    target = NumericalFluid(grid).step(start, boundary, params)
    assert teacher_loss(target, target, params, grid).abs().max() == 0
    assert teacher_loss(start, target, params, grid).min() > 0
    u = grid.dx / params.h  # a = U* y is a uniform x-velocity of one cell per step
    y = torch.arange(grid.H + 1, dtype=torch.float32)[:, None] * grid.dx
    shifted = FluidState(target.a + u * y.expand(grid.H + 1, grid.W + 1)[None, None], target.p)
    nx, ny = (grid.H * (grid.W + 1)), ((grid.H + 1) * grid.W)
    assert torch.allclose(teacher_loss(shifted, target, params, grid), torch.tensor([nx / (nx + ny)]),
                          rtol=1e-4)


def _moving_disc_step(grid):
    """A disc of radius 3 cells moving at (0.1, 0.05) m/s in the closed tank: its boundary, the
    paper's fluid and the numerical solver's first step from rest."""
    from fishsim.fluid.grid import union
    from fishsim.fluid.numerical import NumericalFluid

    tank = closed_tank(grid, 2, 3, 1)
    yy, xx = torch.meshgrid(torch.arange(grid.H), torch.arange(grid.W), indexing="ij")
    disc = (((xx - grid.W / 2) ** 2 + (yy - grid.H / 2) ** 2) < 9).float()[None, None]
    boundary = union(tank, Boundary(disc, torch.stack([0.1 * disc[:, 0], 0.05 * disc[:, 0]], 1)))
    params = paper_params(1)
    return boundary, params, NumericalFluid(grid).step(_rest(grid, 1), boundary, params)


def test_pressure_value_term_sees_a_large_scale_error_the_gradient_term_hardly_does(grid):
    """L_P: zero on the solver's own step and for a constant offset of p (a pressure is defined up
    to one); for p* + P* s with s a ramp from -1 to 1 across the tank (mean-free on the fluid
    cells) it is sum w s^2 / (sum w p~*^2 + P_0 sum w), the squared relative error, while the
    gradient term sees only the ramp's slope, 2 / W per cell: under 5 % of it."""
    from fishsim.fluid.hydronet.loss import pressure_value_loss

    boundary, params, target = _moving_disc_step(grid)
    xx = torch.arange(grid.W)[None, :].expand(grid.H, grid.W)
    p_star = 50.0 * (grid.dx / params.h) ** 2
    assert pressure_value_loss(target, target, boundary, params, grid).abs().max() == 0
    offset = FluidState(target.a, target.p + 7.0 * p_star)
    assert pressure_value_loss(offset, target, boundary, params, grid).abs().max() < 1e-10
    w = 1 - boundary.mask
    sign = (2 * xx / (grid.W - 1) - 1).float()[None, None]
    sign = sign - (w * sign).sum() / w.sum()           # mean-free on the fluid cells
    step = FluidState(target.a, target.p + p_star * sign)
    ref = target.p / p_star
    ref = ref - (w * ref).sum() / w.sum()
    expected = (w * sign**2).sum() / ((w * ref**2).sum() + 1e-4 * w.sum())
    assert torch.allclose(pressure_value_loss(step, target, boundary, params, grid), expected.reshape(1), rtol=1e-4)
    with_value = teacher_loss(step, target, params, grid, boundary, pressure=10.0)
    assert torch.allclose(with_value - teacher_loss(step, target, params, grid), 10 * expected.reshape(1), rtol=1e-4)
    absolute = (w * sign**2).mean()                     # L_P without the normalisation
    assert teacher_loss(step, target, params, grid) < 0.05 * absolute


def test_energy_term_is_the_relative_kinetic_energy_error_of_the_step(grid):
    """L_E vanishes on the solver's own step (a moving body in the tank); the same flow 1 % faster
    everywhere has (1.01^2 - 1)^2 / (1 + E_0 / E*)^2 with E* its fluid faces' mean (v / U*)^2, a
    sign-blind squared gain; a still target leaves only the floor."""
    from fishsim.fluid.grid import curl

    boundary, params, target = _moving_disc_step(grid)
    assert energy_loss(target, target, boundary, params, grid).abs().max() == 0
    u = grid.dx / params.h
    w = fluid_face_masks(boundary.mask)
    e = sum(((c / u) ** 2 * wi).sum() for c, wi in zip(curl(target.a, grid.dx), w)) / sum(
        c[0].numel() for c in curl(target.a, grid.dx))
    for gain in (1.01, 0.99):
        faster = FluidState(gain * target.a, target.p)
        expected = ((gain**2 - 1) * e / (e + ENERGY_FLOOR)) ** 2
        assert torch.allclose(energy_loss(faster, target, boundary, params, grid), expected[None], rtol=1e-4)
    still = _rest(grid, 1)
    assert torch.allclose(energy_loss(target, still, boundary, params, grid), (e / ENERGY_FLOOR)[None] ** 2, rtol=1e-4)
