"""Geometry of the fish's surface polyline (docs/physics.md section 7).

The surface is the closed counter-clockwise polyline ``qs`` [B, S, 2] (x, y) in metres,
node k joined to node k+1 (indices mod S).  Segment k runs from ``q^k`` to ``q^{k+1}``.
All functions are pure, batched over B and vectorised over nodes, segments and query points.
"""

from __future__ import annotations

import torch
from torch import Tensor


def next_nodes(qs: Tensor) -> Tensor:
    """``q^{k+1}`` for every k (closed polyline), [B, S, 2]."""
    return torch.roll(qs, shifts=-1, dims=1)


def outward_edge_normals(qs: Tensor) -> tuple[Tensor, Tensor]:
    """Length and outward unit normal of every segment of the ccw polyline.

    For a ccw curve the outward normal of the edge e = q^{k+1} - q^k is (e_y, -e_x) / |e|.
    Returns (length [B, S] in m, normal [B, S, 2]).
    """
    e = next_nodes(qs) - qs
    length = e.norm(dim=-1)
    normal = torch.stack([e[..., 1], -e[..., 0]], dim=-1) / length.unsqueeze(-1)
    return length, normal


def surface_geometry(qs: Tensor) -> tuple[Tensor, Tensor]:
    """Per-node surface length ``l_k`` and outward unit normal ``n_k`` (paper Sec. 3.3).

    l_k = (|q^{k-1} - q^k| + |q^k - q^{k+1}|) / 2                                   [B, S], m
    n_k = normalise(|e_{k-1}| n_{k-1} + |e_k| n_k)  (edge normals weighted by length)  [B, S, 2]

    The length-weighted average equals the normal of the chord q^{k+1} - q^{k-1}, so
    sum_k (|e_{k-1}| n_{k-1} + |e_k| n_k) / 2 = 0 exactly for a closed polyline; l_k n_k
    differs from it only by O(turning angle^2) per node.
    """
    length, normal = outward_edge_normals(qs)
    prev_length = torch.roll(length, shifts=1, dims=1)
    prev_normal = torch.roll(normal, shifts=1, dims=1)
    l_k = 0.5 * (prev_length + length)
    n_k = prev_length.unsqueeze(-1) * prev_normal + length.unsqueeze(-1) * normal
    return l_k, n_k / n_k.norm(dim=-1, keepdim=True)


def area_vectors(qs: Tensor) -> Tensor:
    """Outward area vector of each node's piece of surface, a_k = J (q^{k+1} - q^{k-1}) / 2.

    J rotates by -90 degrees ((x, y) -> (y, -x)), so a_k = (|e_{k-1}| n_{k-1} + |e_k| n_k) / 2:
    half of each adjacent edge's length times its outward normal; |a_k| <= l_k, equal on
    straight stretches, and a_k = |a_k| n_k.  [B, S, 2] in m.  Telescoping gives
    sum_k a_k = 0 exactly, and sum_k -p(q^k) a_k = -(integral of p n over the polygon) exactly for
    linear p: a uniform pressure exerts no net force, and the divergence theorem holds.
    """
    chord = torch.roll(qs, shifts=-1, dims=1) - torch.roll(qs, shifts=1, dims=1)
    return 0.5 * torch.stack([chord[..., 1], -chord[..., 0]], dim=-1)


def polygon_area(qs: Tensor) -> Tensor:
    """Signed (positive for ccw) area of the closed polyline, shoelace formula, [B] in m^2."""
    q1 = next_nodes(qs)
    return 0.5 * (qs[..., 0] * q1[..., 1] - q1[..., 0] * qs[..., 1]).sum(dim=-1)


def segment_closest_point(x: Tensor, a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """Closest point on the segments [a, b] to the points x (all broadcast, last dim 2).

    t = clamp((x - a).(b - a) / |b - a|^2, 0, 1),  c = a + t (b - a)
    Returns (t [...] without the last dim, squared distance |x - c|^2 [...] in m^2).
    The squared distance is C^1 in x, a and b.
    """
    ab = b - a
    t = ((x - a) * ab).sum(-1) / (ab * ab).sum(-1)
    t = t.clamp(0.0, 1.0)
    c = a + t.unsqueeze(-1) * ab
    return t, ((x - c) ** 2).sum(-1)
