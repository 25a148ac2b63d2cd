"""Surface geometry of the ccw polyline: l_k, n_k, area vectors, area."""

import math

import torch

from fishsim.coupling import area_vectors, polygon_area, surface_geometry
from tests.coupling.shapes import ellipse, fish_outline


def test_circle_lengths_and_outward_normals():
    n, r = 64, 0.03
    qs = ellipse(n, centre=(0.1, 0.1), axes=(r, r))
    l_k, n_k = surface_geometry(qs)
    edge = 2 * r * math.sin(math.pi / n)
    assert torch.allclose(l_k, torch.full_like(l_k, edge), rtol=1e-12)
    radial = (qs - torch.tensor([0.1, 0.1], dtype=qs.dtype)) / r
    assert torch.allclose(n_k, radial, atol=1e-12)


def test_area_vectors_close_and_point_along_normals():
    qs = fish_outline(200)
    a_k = area_vectors(qs)
    l_k, n_k = surface_geometry(qs)
    assert a_k.sum(1).abs().max() < 1e-15
    assert torch.allclose(a_k / a_k.norm(dim=-1, keepdim=True), n_k, atol=1e-12)
    assert (a_k.norm(dim=-1) <= l_k + 1e-15).all()


def test_polygon_area_ccw_positive():
    qs = ellipse(400, axes=(0.05, 0.02))
    assert abs(polygon_area(qs).item() / (math.pi * 0.05 * 0.02) - 1) < 1e-3
    assert polygon_area(qs.flip(1)).item() < 0
