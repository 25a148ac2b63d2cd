"""Solid -> fluid: the soft boundary mask b and the boundary velocity v_d (paper Sec. 3.3).

    b_ij    = sigmoid(delta_ij d_ij / sigma),   d_ij = soft-min over l of e_ij,l
    v_d,ij  = (sum_l softmin_l(e_ij / tau) qdot^l) b_ij

with e_ij,l the squared distance from the cell centre x_ij to surface element l, and
delta = +1 inside the body, -1 outside.  The soft-mins run over each cell's K nearest elements,
tapered to zero at the (K + 1)-th so that they stay continuous (``softmin_weights``).  Both are
computed on the band of cells around the body (``band.py``); every other cell gets b = 0 and
v_d = 0 exactly.

Surface elements (``distance``):

* ``"segment"`` (default): e = exact squared distance to the polyline segment q^l -> q^{l+1};
  the velocity of an element is the linear interpolation of its two end velocities at the
  closest point.  The zero level set of d is then the polyline itself, so b = 1/2 exactly on the
  surface and the mask has no scallops between nodes.
* ``"node"`` (the paper's literal formula): e = |x_ij - q^l|^2.  Between two nodes h apart the
  surface sits at d ~ (h/2)^2 from them, so with h = 2 mm and sigma = 5e-7 the mask jumps between
  ~0.12 and ~0.88 where a cell centre crosses the surface between nodes (scallops).

Soft-min of the squared distances (``mean``), with weights w_l = softmin_l(e_l / xi):

* ``"harmonic"`` (default): d = 1 / sum_l (w_l / e_l).  It is 0 wherever any e_l = 0, so d
  vanishes on the surface and b is continuous (C^1) where delta flips sign.
* ``"arithmetic"`` (the paper): d = sum_l w_l e_l.  Never 0 on the surface (neighbouring
  elements add up to ~0.28 xi), so b jumps by up to ~sigmoid(0.28 xi / sigma) - 1/2 on either
  side of the surface (0.43 <-> 0.57 at xi = sigma): a cell crossing the surface changes b
  discontinuously and its gradient misses the jump.

Both means lie in [min_l e_l, max_l e_l] and tend to the exact squared distance as xi -> 0.

Default values (grid dx = 2.5 mm, so one cell is dx^2 = 6.25e-6 m^2 in d):

* sigma = 5e-7 m^2 (the paper's middle value): with d ~ s^2 (s the signed distance) b goes
  from 0.05 to 0.95 over |s| < 0.49 dx, i.e. across one cell: sharp enough that the thin
  tail (half-width 1-2 mm) still reaches b ~ 0.9-1, smooth enough that sub-cell motion changes
  b continuously.  5e-9 is a binary raster (b jumps 0 -> 1 within 0.05 dx), 5e-5 blurs over
  ~3 cells (the body centre line only reaches b ~ 0.8).
* xi = 5e-7 m^2 (paper): sqrt(xi) = 0.7 mm, a third of a cell and of a 2 mm surface segment:
  the soft-min is the nearest element except where two elements tie (medial axis, tail tip).
* tau = 5e-7 m^2 (= xi): a cell takes the velocity of the nearest surface point, blended
  smoothly over 0.7 mm where two surface points tie (across the thin tail, at the tips).
"""

from __future__ import annotations

import torch
from torch import Tensor

from fishsim.coupling.band import SurfaceBand, band_margin, gather_nodes, scatter_band, surface_band
from fishsim.coupling.config import ARITHMETIC, HARMONIC, NODE, SEGMENT
from fishsim.coupling.geometry import segment_closest_point
from fishsim.fields import Grid

XI, SIGMA, TAU = 5e-7, 5e-7, 5e-7


def element_distances(qs: Tensor, band: SurfaceBand,
                      dtype: torch.dtype) -> tuple[Tensor, Tensor | None]:
    """Squared distances e [B, P, K] (m^2) from each band cell to its K nearest elements,
    differentiable in ``qs`` [B, S, 2]; also the closest-point parameter t [B, P, K] along
    each segment (None for nodes).  Computed in ``dtype`` relative to the band's origin."""
    qs = (qs - band.origin).to(dtype)
    x = band.centres.to(dtype).unsqueeze(2)
    a = gather_nodes(qs, band.nearest)
    if band.distance == NODE:
        return ((x - a) ** 2).sum(-1), None
    b = gather_nodes(qs, (band.nearest + 1) % qs.shape[1])
    return segment_closest_point(x, a, b)[::-1]


def softmin_weights(e: Tensor, temperature: float, truncated: bool) -> Tensor:
    """Weights w_l [..., K'] of the soft-min over a cell's nearest elements, e [..., K'] m^2.

    All elements (``truncated`` False): w_l = softmax_l(-e_l / T).
    The K + 1 nearest of more (``truncated``): the softmin tapered to zero at the farthest,

        w_l ~ exp(-e_l / T) - exp(-e_max / T),    e_max = max_l e_l,

    so an element's weight vanishes as it leaves the K nearest and the weights are a continuous
    function of the positions (band.py).  Both differ from the softmin over all elements by
    O(exp(-(e_max - e_min) / T)).
    """
    if not truncated:
        return torch.softmax(-e / temperature, dim=-1)
    shifted = e - e.amin(-1, keepdim=True)
    w = (torch.exp(-shifted / temperature) - torch.exp(-shifted.amax(-1, keepdim=True) / temperature)).clamp_min(0.0)
    return w / w.sum(-1, keepdim=True).clamp_min(torch.finfo(w.dtype).tiny)


def soft_distance(e: Tensor, xi: float, mean: str, truncated: bool) -> Tensor:
    """Soft-min d of the squared distances e [..., K] with weights softmin(e / xi), [...] m^2
    (``truncated``: e holds a cell's K + 1 nearest elements of more, ``softmin_weights``).

    harmonic:   d = 1 / sum_l (w_l / e_l)     (0 on the surface)
    arithmetic: d = sum_l w_l e_l             (paper)
    """
    w = softmin_weights(e, xi, truncated)
    if mean == ARITHMETIC:
        return (w * e).sum(-1)
    if mean == HARMONIC:
        floor = 1e-8 * xi  # |x - q| = 1e-4 sqrt(xi) = 0.07 um: keeps 1/e^2 finite in float32
        return 1.0 / (w / e.clamp_min(floor)).sum(-1)
    raise ValueError(f"mean must be 'harmonic' or 'arithmetic', got {mean!r}")


def soft_mask(qs: Tensor, grid: Grid, xi: float = XI, sigma: float = SIGMA,
              distance: str = SEGMENT, mean: str = HARMONIC, band: SurfaceBand | None = None,
              dtype: torch.dtype | None = None) -> Tensor:
    """Soft boundary mask b_ij = sigmoid(delta_ij d_ij / sigma), [B, 1, H, W] in [0, 1].

    qs: surface polyline [B, S, 2] (ccw, m), world frame; differentiable.
    xi, sigma: softness (m^2); distance: "segment" | "node"; mean: "harmonic" | "arithmetic"
    (see the module docstring for the choices and defaults).
    band: cells to evaluate (``surface_band``); built here with ``band_margin(sigma)`` if None.
    dtype: of the computation and the result (the fluid's, e.g. float32; default qs.dtype).

    Cost of these torch formulas (100 x 300 grid, 250 surface nodes, bent fish, float32, 2 CPU
    cores, unloaded): mask + v_d + IBM forward ~10 ms at B = 1 and ~110 ms at B = 16 (mostly the
    no-grad band pass), backward ~5 / ~40 ms; autograd keeps ~9 / ~90 MiB, peak RSS grows
    ~30 / ~280 MiB. The coupling runs them on CUDA; on the CPU it runs ``band_values`` (the
    same formulas compiled: mask + v_d 2.2 ms forward, 3.8 ms with the backward, B = 1, one thread).
    """
    if band is None:
        band = surface_band(qs, grid, band_margin(sigma, grid.dx), distance=distance)
    return scatter_band(_band_mask(qs, band, xi, sigma, mean, dtype or qs.dtype).unsqueeze(1), band, grid)


def _band_mask(qs: Tensor, band: SurfaceBand, xi: float, sigma: float, mean: str, dtype: torch.dtype) -> Tensor:
    """b [B, P] of the band's cells (``soft_mask``'s formulas)."""
    e, _ = element_distances(qs, band, dtype)
    d = soft_distance(e, xi, mean, band.truncated)
    delta = torch.where(band.inside, 1.0, -1.0).to(d.dtype)
    return torch.sigmoid(delta * d / sigma)


def band_values(qs: Tensor, qdots: Tensor, band: SurfaceBand, xi: float = XI, sigma: float = SIGMA,
                tau: float = TAU, mean: str = HARMONIC, dtype: torch.dtype | None = None) -> tuple[Tensor, Tensor]:
    """``soft_mask`` and ``boundary_velocity(weighted=False)`` on the band's cells only: (b [B, 1, P],
    v_d [B, 2, P]) in ``dtype`` (default qs.dtype), differentiable in qs and qdots [B, S, 2]; every
    other cell has b = v_d = 0 (``scatter_band`` makes them grid fields). On the CPU in one
    compiled pass over the band's cells (fishsim.coupling.kernels.BandBoundary, float64 inside);
    elsewhere the torch formulas."""
    dtype = dtype or qs.dtype
    if qs.device.type != "cpu":
        b = _band_mask(qs, band, xi, sigma, mean, dtype)
        return b.unsqueeze(1), _band_velocity(qs, qdots, band, tau, dtype).transpose(1, 2)
    from fishsim.coupling.kernels import BandBoundary

    if mean not in (HARMONIC, ARITHMETIC):
        raise ValueError(f"mean must be 'harmonic' or 'arithmetic', got {mean!r}")
    b, u = BandBoundary.apply(qs - band.origin, qdots, band.centres, band.nearest, band.inside, band.unranked, xi,
                              sigma, tau, mean == HARMONIC, band.distance == SEGMENT, band.truncated, dtype)
    return b.unsqueeze(1), u.transpose(1, 2)


def band_boundary(qs: Tensor, qdots: Tensor, band: SurfaceBand, grid: Grid, xi: float = XI, sigma: float = SIGMA,
                  tau: float = TAU, mean: str = HARMONIC, dtype: torch.dtype | None = None) -> tuple[Tensor, Tensor]:
    """``band_values`` as grid fields: (b [B, 1, H, W], v_d [B, 2, H, W])."""
    b, u = band_values(qs, qdots, band, xi, sigma, tau, mean, dtype)
    return scatter_band(b, band, grid), scatter_band(u, band, grid)


def element_velocities(qdots: Tensor, band: SurfaceBand, t: Tensor | None) -> Tensor:
    """Velocity [B, P, K, 2] of each band cell's K nearest elements: the node velocity, or
    (1 - t) qdot^l + t qdot^{l+1} at the closest point of segment l."""
    v_a = gather_nodes(qdots, band.nearest)
    if t is None:
        return v_a
    v_b = gather_nodes(qdots, (band.nearest + 1) % qdots.shape[1])
    t = t.unsqueeze(-1)
    return (1.0 - t) * v_a + t * v_b


def boundary_velocity(qs: Tensor, qdots: Tensor, mask: Tensor, grid: Grid, tau: float = TAU,
                      distance: str = SEGMENT, band: SurfaceBand | None = None,
                      weighted: bool = True) -> Tensor:
    """Boundary velocity v_d,ij = (sum_l softmin_l(e_ij,l / tau) v^l) b_ij, [B, 2, H, W] m/s.

    weighted=False drops the paper's factor b_ij and returns the solid's velocity field itself
    (the ``Boundary.velocity`` contract: the fluid models weight it by the mask where needed).

    qs, qdots: surface positions (m) and velocities (m/s) [B, S, 2]; mask: b [B, 1, H, W].
    v^l is the velocity of element l (node, or segment interpolated at the closest point).
    A rigid translation U gives v_d = U b exactly; a rigid rotation is exact on the surface
    and off by |omega| * (distance to the nearest surface point) inside.
    band: pass the one used for the mask (it must cover the mask's support); if None it is
    rebuilt with the margin of the default sigma.  Computed and returned in mask.dtype.
    """
    if band is None:
        band = surface_band(qs, grid, band_margin(SIGMA, grid.dx), distance=distance)
    u = _band_velocity(qs, qdots, band, tau, mask.dtype).transpose(1, 2)  # [B, 2, P]
    b = mask.flatten(2).gather(2, band.flat.unsqueeze(1))  # [B, 1, P]
    return scatter_band(u * b if weighted else u, band, grid)


def _band_velocity(qs: Tensor, qdots: Tensor, band: SurfaceBand, tau: float, dtype: torch.dtype) -> Tensor:
    """The softmin-weighted element velocity u [B, P, 2] of the band's cells (``boundary_velocity``
    without the factor b)."""
    e, t = element_distances(qs, band, dtype)
    w = softmin_weights(e, tau, band.truncated)
    return (w.unsqueeze(-1) * element_velocities(qdots.to(dtype), band, t)).sum(2)
