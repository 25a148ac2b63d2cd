"""Soft mask b: values inside/outside/on the surface, band truncation, sub-cell smoothness."""

import math
from itertools import pairwise

import pytest
import torch

from fishsim.coupling import polygon_area, soft_mask
from fishsim.coupling.mask import SIGMA
from fishsim.fields import Grid
from tests.coupling.shapes import ellipse, fish_outline, polyline_signed_distance

GRID = Grid()
DX = GRID.dx


def signed_distance_grid(qs):
    return polyline_signed_distance(GRID.cell_centres(dtype=qs.dtype).view(-1, 2), qs[0]).view(GRID.H, GRID.W)


@pytest.mark.parametrize("shape", [ellipse(200), fish_outline(200)])
def test_inside_outside_values(shape):
    b = soft_mask(shape, GRID)[0, 0]
    s = signed_distance_grid(shape)
    # |s| >= dx: |d| >= dx^2 = 12.5 sigma -> b within 4e-6 of 0 or 1
    assert b[s <= -DX].min() > 1 - 1e-5
    assert b[s >= DX].max() < 1e-5
    assert b[s >= 3 * DX].max() < 1e-30  # beyond the band: exactly 0
    assert ((b > 0.5) == (s < 0))[s.abs() > 0.05 * DX].all()


def test_half_on_the_surface():
    # a rectangle whose bottom and top edges run through rows of cell centres
    y0, y1, x0, x1 = 40.5 * DX, 52.5 * DX, 100.2 * DX, 160.3 * DX
    xs = torch.linspace(x0, x1, 40, dtype=torch.float64)[:-1]
    ys = torch.linspace(y0, y1, 10, dtype=torch.float64)[:-1]
    qs = torch.cat([
        torch.stack([xs, torch.full_like(xs, y0)], -1), torch.stack([torch.full_like(ys, x1), ys], -1),
        torch.stack([xs.flip(0) + (x1 - x0) / 39, torch.full_like(xs, y1)], -1),
        torch.stack([torch.full_like(ys, x0), ys.flip(0) + (y1 - y0) / 9], -1),
    ])[None]
    b = soft_mask(qs, GRID)[0, 0]
    on_edges = b[[40, 52], 102:158]
    assert (on_edges - 0.5).abs().max() < 1e-6  # harmonic soft-min: d = 0 on the polyline
    b_paper = soft_mask(qs, GRID, mean="arithmetic")[0, 0]
    assert (b_paper[[40, 52], 102:158] - 0.5).abs().max() < 0.1  # ~0.28 xi offset at vertices


def max_slope(sigma=SIGMA):
    """max_s d/ds sigmoid(s |s| / sigma), per metre, for the exact signed distance s."""
    s = torch.linspace(0, 3 * math.sqrt(sigma), 10001, dtype=torch.float64)
    u = s * s / sigma
    return (torch.sigmoid(u) * (1 - torch.sigmoid(u)) * 2 * s / sigma).max().item()


@pytest.mark.parametrize("shape, area_tol", [(ellipse(200), 2e-3), (fish_outline(200), 5e-3)])
def test_subcell_translation_is_smooth(shape, area_tol):
    area = polygon_area(shape).item()
    step = torch.tensor([0.1 * DX, 0.037 * DX], dtype=torch.float64)
    xy = GRID.cell_centres(dtype=torch.float64)
    masks = [soft_mask(shape + k * step, GRID, dtype=torch.float64)[0, 0] for k in range(11)]
    areas = torch.stack([b.sum() * DX ** 2 for b in masks])
    centroids = torch.stack([(b[..., None] * xy).sum((0, 1)) / b.sum() for b in masks])
    assert ((areas / area) - 1).abs().max() < area_tol
    moved = centroids - centroids[0] - torch.arange(11, dtype=torch.float64)[:, None] * step
    assert moved.abs().max() < 0.1 * DX
    # continuous: no cell changes faster than the exact-distance profile allows (+10 %)
    jumps = torch.stack([(b1 - b0).abs().max() for b0, b1 in pairwise(masks)])
    assert jumps.max() < 1.1 * max_slope() * step.norm().item()


def test_paper_node_distance_scallops():
    """The node formula is also a valid mask, but with visible scallops (documented)."""
    qs = fish_outline(200)
    b = soft_mask(qs, GRID, distance="node")[0, 0]
    s = signed_distance_grid(qs)
    assert b[s <= -1.5 * DX].min() > 0.999 and b[s >= 2 * DX].max() < 1e-6


def test_batch_and_dtype():
    qs = torch.cat([ellipse(100), ellipse(100, centre=(0.5, 0.1), axes=(0.02, 0.03))])
    b = soft_mask(qs, GRID, dtype=torch.float32)
    assert b.shape == (2, 1, GRID.H, GRID.W) and b.dtype == torch.float32
    for i in range(2):
        assert torch.allclose(b[i], soft_mask(qs[i:i + 1], GRID, dtype=torch.float32)[0], atol=1e-6)
    areas = b.double().sum((1, 2, 3)) * DX ** 2
    assert torch.allclose(areas, polygon_area(qs), rtol=3e-3)
