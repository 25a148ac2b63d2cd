"""The band of grid cells around the body where the mask and v_d are computed.

Computing b_ij for all 100 x 300 cells against all ~250 surface segments of B fish needs
B x 30,000 x 250 distances; almost all of them are far from the body, where b = 0 to machine
precision.  ``surface_band`` therefore picks, without gradient (the choice is piecewise constant):

* a window of h x w cells per fish: its bounding box plus ``margin`` cells, one common size for
  the batch (each fish has its own origin), clipped to the grid;
* per window cell, whether it is inside the body (even-odd crossing rule, all segments, counted
  per row with a sorted list of crossings);
* per window cell, its K + 1 nearest segments (or nodes): the K nearest and, as the reference of
  the truncated softmin (``mask.softmin_weights``), the (K + 1)-th.  A segment's weight falls
  to zero as it becomes the (K + 1)-th, so a change of the K nearest is continuous (a plain
  softmin over the K nearest jumped by the weight of the segment that left: at the graded
  mesh's fine tail tip, segments ~0.5 mm long, that weight was a few per cent).

The differentiable quantities are then recomputed from ``qs`` on [B, P, K] only, so the autograd
memory is O(B P K) instead of O(B H W S).  The all-segment pass runs in chunks of cells.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from fishsim.coupling.config import NODE, SEGMENT
from fishsim.coupling.geometry import next_nodes
from fishsim.fields import Grid

_CHUNK_ELEMENTS = 1 << 22  # cells x segments x batch per chunk of the no-grad pass (16 MB fp32)


@dataclass(frozen=True)
class SurfaceBand:
    """Cells near the body, chosen without gradient.

    flat: [B, P] long, flat grid index i * W + j of each band cell (P = h * w).
    origin: [B, 1, 2] a point of each fish's bounding box (its centre), m, dtype of qs.
    centres: [B, P, 2] cell-centre coordinates x_ij - origin (x, y) in m, dtype of qs; geometry
        relative to the origin can run in float32 without losing sub-micrometre precision.
    inside: [B, P] bool, cell centre inside the closed polyline.
    nearest: [B, P, K'] long, indices of the K' = min(K + 1, S) nearest segments (segment
        k = q^k -> q^{k+1}) or nodes, according to ``distance`` (0..K'-1, unranked, for the cells
        left out as negligibly far by ``surface_band(sigma=...)``).
    distance: "segment" or "node".
    truncated: the cells see fewer elements than the surface has (K' < S), so their soft-mins
        are tapered at the K'-th (``mask.softmin_weights``).
    unranked: [B, P] bool, the cells left out as negligibly far (their mask is 0), or None where
        every cell was ranked.
    """

    flat: Tensor
    origin: Tensor
    centres: Tensor
    inside: Tensor
    nearest: Tensor
    distance: str
    truncated: bool
    unranked: Tensor | None = None


def band_margin(sigma: float, dx: float, decades: float = 40.0) -> int:
    """Cells beyond the bounding box so that b < sigmoid(-decades) outside the band.

    Every cell beyond the margin is at squared distance d >= (margin dx)^2 from the surface,
    so b <= sigmoid(-(margin dx)^2 / sigma); default 40 gives b < 5e-18.
    """
    return math.ceil(math.sqrt(decades * sigma) / dx) + 1


def _window(lo: Tensor, hi: Tensor, n: int, margin: int) -> tuple[Tensor, int]:
    """Origin [B] and common size of a 1D cell window covering [lo, hi] (cell units) + margin."""
    first = torch.floor(lo).long() - margin
    last = torch.floor(hi).long() + margin
    size = min(int((last - first).max()) + 1, n)
    return first.clamp(0, n - size), size


def _band_cells(qs: Tensor, grid: Grid, margin: int) -> tuple[Tensor, Tensor, tuple[int, int]]:
    """Flat indices [B, P], centres [B, P, 2] and size (h, w) of each fish's window of cells."""
    cells = qs.detach() / grid.dx
    i0, h = _window(cells[..., 1].amin(1), cells[..., 1].amax(1), grid.H, margin)
    j0, w = _window(cells[..., 0].amin(1), cells[..., 0].amax(1), grid.W, margin)
    i = i0[:, None, None] + torch.arange(h, device=qs.device)[None, :, None]
    j = j0[:, None, None] + torch.arange(w, device=qs.device)[None, None, :]
    i, j = torch.broadcast_tensors(i, j)
    flat = (i * grid.W + j).flatten(1)
    i, j = i.to(qs.dtype), j.to(qs.dtype)
    centres = torch.stack([(j + 0.5) * grid.dx, (i + 0.5) * grid.dx], dim=-1).flatten(1, 2)
    return flat, centres, (h, w)


def _all_squared_distances(x: Tensor, qs: Tensor, distance: str) -> Tensor:
    """|x - q^l|^2 to every node or segment l: x [B, P, 2], qs [B, S, 2] -> [B, P, S].

    Written with batched matrix products (|x - a|^2 = |x|^2 + |a|^2 - 2 x.a, u = (x - a).(b - a),
    t = clamp(u / |b - a|^2, 0, 1), e = |x - a|^2 - t (2u - t |b - a|^2)): a few passes over
    [B, P, S].  The cancellation error is ~eps |x|^2, so x and qs should be centred on the body.
    """
    x2 = (x * x).sum(-1, keepdim=True)
    e_node = torch.baddbmm(x2 + (qs * qs).sum(-1).unsqueeze(1), x, qs.transpose(1, 2), alpha=-2.0)
    if distance == NODE:
        return e_node
    ab = next_nodes(qs) - qs
    ab2 = (ab * ab).sum(-1).unsqueeze(1)
    u = torch.baddbmm(-(qs * ab).sum(-1).unsqueeze(1), x, ab.transpose(1, 2))
    t = (u / ab2).clamp_(0.0, 1.0)
    return e_node.sub_(t * (2.0 * u - t * ab2)).clamp_(min=0.0)


def _inside(centres: Tensor, qs: Tensor, h: int, w: int) -> Tensor:
    """Even-odd inside test of the window cells [B, P = h w] against the polyline qs [B, S, 2].

    Cells of one row share y, so each row's crossings with the segments are computed once,
    sorted, and counted right of each cell with searchsorted: O(B h S log S + B P log S).
    """
    row_y = centres.view(-1, h, w, 2)[:, :, 0, 1]  # [B, h]
    a, b = qs.unsqueeze(1), next_nodes(qs).unsqueeze(1)
    y = row_y.unsqueeze(-1)
    straddles = (a[..., 1] > y) != (b[..., 1] > y)  # [B, h, S]
    dy = torch.where(straddles, b[..., 1] - a[..., 1], torch.ones_like(straddles, dtype=qs.dtype))
    x_cross = a[..., 0] + (y - a[..., 1]) * (b[..., 0] - a[..., 0]) / dy
    x_cross = torch.where(straddles, x_cross, torch.full_like(x_cross, -torch.inf)).sort(-1).values
    x = centres.view(-1, h, w, 2)[..., 0].contiguous()
    right = qs.shape[1] - torch.searchsorted(x_cross, x, right=True)
    return (right % 2 == 1).flatten(1)


def nearest_count(k_nearest: int, S: int) -> tuple[int, bool]:
    """(K', truncated): the K' = min(K + 1, S) elements a band cell ranks for K = ``k_nearest``
    of the surface's S, and whether that leaves some out (its soft-mins are then tapered)."""
    return min(k_nearest + 1, S), k_nearest + 1 < S


@torch.no_grad()
def surface_band(qs: Tensor, grid: Grid, margin: int, k_nearest: int = 24,
                 distance: str = SEGMENT, sigma: float | None = None) -> SurfaceBand:
    """Band cells, inside flags and K + 1 nearest segments/nodes of the surface ``qs`` [B, S, 2].

    The selection runs relative to each fish's centre, compiled in float64 on the CPU
    (fishsim.coupling.kernels), else in float32 (|x| < 0.15 m: the squared distances are off by
    < 1e-9 m^2 = xi / 500); it only selects, it is never differentiated.  With the mask's
    softness ``sigma`` [m^2], the compiled selection leaves unranked the cells outside the body
    whose mask is below 4e-18 (farther than sqrt(40 sigma), 1.8 cells at the default), to which
    the compiled mask then gives b = v_d = 0 (kernels._far); the torch formulas (soft_mask,
    boundary_velocity) need ranked cells: leave sigma None for them.
    """
    if distance not in (SEGMENT, NODE):
        raise ValueError(f"distance must be 'segment' or 'node', got {distance!r}")
    k, truncated = nearest_count(k_nearest, qs.shape[1])
    if qs.device.type == "cpu":                      # compiled, in float64 (fishsim.coupling.kernels)
        from fishsim.coupling.kernels import NEGLIGIBLE, band_selection

        far = math.inf if sigma is None else NEGLIGIBLE * sigma
        flat, centres, origin, nearest, inside, unranked, _ = band_selection(
            qs, grid.dx, grid.H, grid.W, margin, k, distance == SEGMENT, far)
        if sigma is None:
            unranked = None
    else:
        flat, centres, (h, w) = _band_cells(qs, grid, margin)
        origin = 0.5 * (qs.amin(1, keepdim=True) + qs.amax(1, keepdim=True))
        centres = centres - origin
        (nearest, inside), unranked = torch_nearest_and_inside(qs - origin, centres, k, distance, (h, w)), None
    return SurfaceBand(flat, origin, centres, inside, nearest, distance, truncated, unranked)


def torch_nearest_and_inside(qs: Tensor, centres: Tensor, k: int, distance: str,
                             window: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """The k nearest elements [B, P, k] (long) and inside flags [B, P] of the window's cells
    ``centres`` [B, P = h w, 2] for the polylines ``qs`` [B, S, 2] (both relative to the band's
    origin), in float32 torch operations (CUDA; the reference of the compiled CPU version)."""
    q32, x32 = qs.float(), centres.float()
    B, P, S = centres.shape[0], centres.shape[1], qs.shape[1]
    chunk = max(1, _CHUNK_ELEMENTS // (B * S))
    nearest = [  # blocks of cells, bounded memory
        _all_squared_distances(x32[:, i:i + chunk], q32, distance).topk(k, dim=-1, largest=False).indices
        for i in range(0, P, chunk)
    ]
    return torch.cat(nearest, 1), _inside(x32, q32, *window)


def scatter_band(values: Tensor, band: SurfaceBand, grid: Grid) -> Tensor:
    """Put band values [B, C, P] into a zero grid field [B, C, H, W] (differentiable; in place
    into the fresh zeros, not into a copy of them)."""
    B, C, _ = values.shape
    out = values.new_zeros(B, C, grid.H * grid.W)
    index = band.flat.unsqueeze(1).expand(B, C, -1)
    return out.scatter_(2, index, values).view(B, C, grid.H, grid.W)


def gather_nodes(field: Tensor, index: Tensor) -> Tensor:
    """field [B, S, C] gathered at index [B, ...] -> [B, ..., C]."""
    B, C = field.shape[0], field.shape[-1]
    flat = index.reshape(B, -1, 1).expand(-1, -1, C)
    return field.gather(1, flat).view(*index.shape, C)
