"""Boundary velocity v_d for rigid motions."""

import torch

from fishsim.coupling import boundary_velocity, soft_mask, surface_band
from fishsim.coupling.band import band_margin
from fishsim.coupling.mask import SIGMA
from fishsim.fields import Grid
from tests.coupling.shapes import fish_outline, polyline_signed_distance

GRID = Grid()
DX = GRID.dx


def field(qs, qdots, dtype=torch.float64):
    band = surface_band(qs, GRID, band_margin(SIGMA, DX))
    b = soft_mask(qs, GRID, band=band, dtype=dtype)
    return b, boundary_velocity(qs, qdots, b, GRID, band=band)


def test_rigid_translation_is_exact():
    qs = fish_outline(200)
    u = torch.tensor([0.31, -0.12], dtype=torch.float64)
    b, v = field(qs, u.expand_as(qs), torch.float32)
    assert v.dtype == torch.float32 and v.shape == (1, 2, GRID.H, GRID.W)
    expected = u.float()[None, :, None, None] * b
    assert (v - expected).abs().max() < 1e-6 * u.norm()  # float32 rounding only


def test_rigid_rotation_near_the_surface():
    qs = fish_outline(200)
    centre = qs.mean(1, keepdim=True)
    omega = 5.0  # rad/s
    rel = qs - centre
    qdots = omega * torch.stack([-rel[..., 1], rel[..., 0]], -1)
    b, v = field(qs, qdots)
    x = GRID.cell_centres(dtype=torch.float64) - centre[0, 0]
    rigid = omega * torch.stack([-x[..., 1], x[..., 0]], 0)
    s = polyline_signed_distance(GRID.cell_centres(dtype=torch.float64).view(-1, 2), qs[0]).view(GRID.H, GRID.W)
    seen = b[0, 0] > 1e-3
    err = (v[0] / b[0, 0].clamp_min(1e-300) - rigid).norm(dim=0)[seen]
    # exact on the surface; a cell takes the velocity of its nearest surface point, so the
    # error is omega * (distance to it): tolerance omega (|s| + 0.05 dx)
    assert (err <= omega * (s[seen].abs() + 0.05 * DX)).all()
    near = s[seen].abs() < 0.5 * DX
    assert err[near].max() < omega * 0.55 * DX


def test_mask_and_velocity_are_continuous_when_the_nearest_elements_change():
    """A soft-min over each cell's K nearest segments, tapered to zero at the (K + 1)-th: sliding
    a finely resolved outline (0.7 mm segments, so a cell's soft-min spans more than K of them)
    across the grid in 20 nm steps changes b and v_d by steps of one size, not by jumps where a
    cell's K nearest change (the plain K-softmin jumped by the leaving segment's weight)."""
    qs0 = fish_outline(600)
    qdots = torch.randn(qs0.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    steps = []
    prev = None
    for k in range(40):
        qs = qs0 + torch.tensor([2e-8 * k, 1e-8 * k], dtype=torch.float64)
        band = surface_band(qs, GRID, band_margin(SIGMA, DX), k_nearest=4)
        b = soft_mask(qs, GRID, band=band)
        v = boundary_velocity(qs, qdots, b, GRID, band=band)   # b v_d: what the fluid sees
        now = torch.cat([b, v], 1)
        if prev is not None:
            steps.append(float((now - prev).abs().max()))
        prev = now
    steps = torch.tensor(steps)
    assert steps.max() < 3 * steps.median(), steps
