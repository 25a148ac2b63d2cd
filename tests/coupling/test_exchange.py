"""The momentum-exchange force (fishsim/coupling/exchange.py): spreading keeps every cell's force,
and on a towed disc the spread node forces add up to the force the numerical fluid's penalization
exchanged with the disc (the hydrodynamic force its validation tests compare with published
drag and added mass)."""

import math

import torch

from fishsim.coupling.exchange import spread_to_surface
from fishsim.fields import Boundary, FluidParams, Grid
from fishsim.fluid import grid as G
from fishsim.fluid.cases import disc_mask, disc_polyline, moving
from fishsim.fluid.numerical import NumericalFluid, StepDiagnostics

D = torch.float64


def test_spreading_keeps_the_total_force_and_reports_what_no_node_reaches():
    g = Grid(40, 60, 2.5e-3)
    qs = disc_polyline(0.07, 0.05, 0.01, 31)
    cells = torch.randn(1, 2, g.H, g.W, dtype=D, generator=torch.Generator().manual_seed(0))
    near = disc_mask(g, 0.07, 0.05, 0.014)                   # cells within 4 mm outside the disc
    f, lost = spread_to_surface(qs, cells * near, g)
    torch.testing.assert_close(f.sum(1), (cells * near).sum((-2, -1)), rtol=1e-12, atol=1e-15)
    assert float(lost) < 1e-12
    far = torch.zeros_like(near)
    far[..., 0:4, 0:4] = 1.0                                 # 12 cells from every node: unreachable
    f, lost = spread_to_surface(qs, cells * (near + far), g)
    assert float(lost) > 1e-3


def test_body_share_is_one_away_from_the_walls_and_excludes_them():
    diag = StepDiagnostics(substeps=1, penalty=(None, None), dx=1.0, refinement=1)
    b_fish = torch.tensor([0.0, 0.3, 1.0, 0.5], dtype=D).view(1, 1, 1, 4)
    b_wall = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=D).view(1, 1, 1, 4)
    sx, _ = diag.body_share(b_fish, 1 - (1 - b_fish) * (1 - b_wall))
    # faces: wall | 0 / 0.3 | 0.3 / 1 | 1 / (0.5 fish + wall) | wall
    expected = torch.tensor([0.0, 1.0, 1.0, 1.5 / 2.0, 0.5], dtype=D).view(1, 1, 1, 5)
    torch.testing.assert_close(sx, expected)


def test_body_share_gradient_is_finite_where_the_masks_are_subnormal():
    """Far from the body the soft mask is tiny (1e-300) or subnormal; b / b_total there must keep a
    finite gradient (the quotient's derivative ~ 1 / b_total overflows under any sizeable upstream
    gradient, and inf - inf = NaN)."""
    diag = StepDiagnostics(substeps=1, penalty=(None, None), dx=1.0, refinement=1)
    b_fish = torch.tensor([1e-300, 1e-310, 0.5, 1.0], dtype=D).view(1, 1, 1, 4).requires_grad_()
    sx, sy = diag.body_share(b_fish, b_fish)
    (grad,) = torch.autograd.grad(1e10 * (sx.sum() + sy.sum()), b_fish)
    assert torch.isfinite(grad).all()
    torch.testing.assert_close(sx[..., 2:4].detach(), torch.ones(1, 1, 1, 2, dtype=D))


def test_towed_disc_node_forces_add_up_to_the_exchanged_momentum():
    """A disc of radius 4 cells towed at 0.1 m/s and heaving (A = 5 mm, 2 Hz) in a closed tank:
    every step the 31 node forces sum to the penalization's reaction on the disc plus the momentum
    of the fluid it carries, rho (V dv/dt) (tests/fluid/test_validation.py's hydrodynamic force)."""
    g = Grid(48, 120, 2.5e-3)
    rho, R, U, A, w = 50.0, 0.01, 0.1, 0.005, 2 * math.pi * 2.0
    tank = G.closed_tank(g, 2, 2, dtype=D)
    fluid = NumericalFluid(g, substeps=4)
    params = FluidParams(torch.tensor([rho], dtype=D), torch.tensor([1e-3], dtype=D), 0.01)
    region = torch.zeros(1, 1, g.H, g.W, dtype=D)
    region[..., 8:40, 16:80] = 1
    s = fluid.initial_state(1, dtype=D)
    for k in range(12):
        t = k * params.h
        xc, yc = 0.07 + U * t, 0.06 - A * math.cos(w * t)
        body = disc_mask(g, xc, yc, R)
        fish = Boundary(body, moving(body, U, A * w * math.sin(w * t)))
        both = G.union(tank, fish)
        s1, diag = fluid.step_with_diagnostics(s, both, params)
        f, lost = spread_to_surface(disc_polyline(xc, yc, R, 31),
                                    diag.cell_forces(rho, diag.body_share(fish.mask, both.mask)), g)
        reference = (diag.cell_forces(rho) * region).sum((-2, -1))[0]
        torch.testing.assert_close(f.sum(1)[0], reference, rtol=1e-6, atol=1e-9)
        assert float(lost) < 1e-9
        s = s1
