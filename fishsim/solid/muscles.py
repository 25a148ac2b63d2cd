"""Which elements are muscles, how strong, and on which side: the muscle layout of a fish.

Two models (docs/physics.md section 2):

- `station_muscles` (the paper's, ``fish.muscles=paper``): the elements the mesher marked in
  `FishMesh.actuator`, one surface element per station, whole (weight fraction 1), top or bottom.
  Its muscle cross-section is one element, so the stroke shrinks with the element size.
- `layer_muscles` (the default, ``fish.muscles=layer``): a muscle layer along each side of the
  body between X = x_range[0] L and x_range[1] L, of thickness `thickness` times the local
  half-width b(X), measured inwards from the surface:

      top layer     Y >= w_top(X) - thickness b(X)
      bottom layer  Y <= w_bot(X) + thickness b(X),      b(X) = (w_top(X) - w_bot(X)) / 2

  with w_top(X) > 0 > w_bot(X) the body's surface (the mesh's boundary polyline). Every element
  that overlaps a layer is a muscle; its PD weight is k_m times the area it has inside the
  layers, A_e (f_top + f_bot), so the muscle's cross-section is the layer's whatever the mesh.

The area fractions are exact for the layer boundary interpolated linearly between the vertices
of each element (the surface is the mesh's own polyline, the inner edge is second-order close
to the curve): each element is first cut by the planes X = x0, X = x1 into at most three
triangles (numpy; the cut does not depend on the thickness), then the part of each triangle
where the linear function d = Y - y_inner(X) is >= 0 (top) has the closed form below, so the
fractions are piecewise smooth in the thickness and differentiable by torch autograd.

An element overlapping both layers (the thin tail, where one element spans the width) carries
both muscles in one: w_top/2 |F m - a_top n|^2 + w_bot/2 |F m - a_bot n|^2 equals, up to a
constant independent of the positions, (w_top + w_bot)/2 |F m - a n|^2 with a the weighted mean
target stretch, so the element's contraction is top_share u_top + (1 - top_share) u_bot,
top_share = f_top / (f_top + f_bot).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from fishsim.errors import ConfigError
from fishsim.mesh.fish_mesh import ACTUATOR_TOP, FishMesh

MUSCLE_MODELS = ("layer", "paper")

# Fractions below this are not muscles (an element touching the layer's edge at a point).
_MIN_FRACTION = 1e-9


@dataclass(frozen=True)
class MuscleLayout:
    """The muscles of a mesh.

    elements: [n_act] int64 element indices of the muscles.
    fraction: [n_act] area fraction of each element inside the muscle layers (weight k_m A_e
        fraction; 1 for the paper's stations; 0 allowed: a muscle of no strength).
    top_share: [n_act] share of the element's muscle on the top side (Y > 0): its contraction is
        top_share max(0, h) + (1 - top_share) max(0, -h) (1 or 0 for pure top / bottom muscles).
    """

    elements: np.ndarray
    fraction: np.ndarray
    top_share: np.ndarray

    def __post_init__(self):
        n = len(self.elements)
        if self.fraction.shape != (n,) or self.top_share.shape != (n,):
            raise ValueError("MuscleLayout arrays must all have shape [n_act]")
        if n and not (np.all(self.fraction >= 0) and np.all(self.fraction <= 1 + 1e-12)):
            raise ValueError("muscle area fractions must lie in [0, 1]")


def station_muscles(mesh: FishMesh) -> MuscleLayout:
    """The paper's muscles: the elements marked in mesh.actuator, whole, top (1) or bottom (2)."""
    elements = np.asarray(mesh.actuated, np.int64)
    top = (np.asarray(mesh.actuator)[elements] == ACTUATOR_TOP).astype(np.float64)
    return MuscleLayout(elements, np.ones(len(elements)), top)


def check_layer(thickness: float, x_range) -> None:
    """ConfigError (one line) unless 0 < thickness <= 1 and 0 <= x0 < x1 <= 1."""
    if not (np.isfinite(thickness) and 0.0 < thickness <= 1.0):
        raise ConfigError(f"muscle layer thickness must be a fraction of the local half-width in (0, 1], "
                          f"got {thickness} (try 0.3)")
    if not (len(x_range) == 2 and 0.0 <= x_range[0] < x_range[1] <= 1.0):
        raise ConfigError(f"muscle x_range must be (start, end) fractions of L with 0 <= start < end <= 1, "
                          f"got {list(x_range)}")


def layer_muscles(mesh: FishMesh, thickness: float, x_range=(0.05, 0.95),
                  elements: np.ndarray | None = None) -> MuscleLayout:
    """The muscle layers of `mesh` (module docstring): every element with a share of its area in
    the top or bottom layer of `thickness` (fraction of the local half-width, in (0, 1]) between
    X = x_range[0] L and x_range[1] L; or, if `elements` is given, exactly those elements (some
    perhaps with fraction 0: e.g. the layer's elements at a larger thickness, so that models at
    nearby thicknesses share one muscle list)."""
    check_layer(thickness, x_range)
    t = torch.tensor(float(thickness), dtype=torch.float64)
    f_top, f_bot = (f.numpy() for f in layer_fractions(mesh, t, x_range))
    total = f_top + f_bot
    if elements is None:
        elements = np.flatnonzero(total > _MIN_FRACTION)
    elements = np.asarray(elements, np.int64)
    f_top, total = f_top[elements], total[elements]
    share = np.where(total > 0, f_top / np.where(total > 0, total, 1.0), 0.5)
    return MuscleLayout(elements, np.minimum(total, 1.0), share)


def layer_weights(model, thickness: torch.Tensor, x_range=(0.05, 0.95)) -> tuple[torch.Tensor, torch.Tensor]:
    """(muscle_weight [n_act] in Pa m^2, top_share [n_act]) of `model`'s muscles (a SolidModel
    built with layer_muscles at this thickness and x_range) as torch functions of `thickness`
    (a scalar tensor): k_m A_e (f_top + f_bot) and f_top / (f_top + f_bot). Pass them to
    pd_step(muscle_weight=...) and WaveController.contraction(top_share=...) to differentiate a
    loss with respect to the layer's thickness (a co-design parameter)."""
    f_top, f_bot = layer_fractions(model.mesh, thickness, x_range, model.muscles)
    total = f_top + f_bot
    area = torch.as_tensor(model.fem.area[model.muscles])
    share = torch.where(total > 0, f_top / torch.where(total > 0, total, torch.ones_like(total)),
                        torch.full_like(total, 0.5))
    return model.material.muscle_stiffness * area * total, share


def layer_fractions(mesh: FishMesh, thickness: torch.Tensor, x_range=(0.05, 0.95),
                    elements: np.ndarray | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Area fractions (f_top, f_bot), each [T] (or [len(elements)]), of the elements inside the top
    and bottom muscle layers of `thickness` (a scalar tensor, fraction of the local half-width;
    differentiable). Element geometry: the mesh's rest positions."""
    pieces, owner, areas = _slab_pieces(mesh, x_range)
    X, Y = pieces[..., 0], pieces[..., 1]
    w_top, w_bot = surface_half_widths(mesh, X.ravel())
    w_top, w_bot = w_top.reshape(X.shape), w_bot.reshape(X.shape)
    half = torch.as_tensor(0.5 * (w_top - w_bot))
    t = torch.as_tensor(thickness, dtype=torch.float64)
    d_top = torch.as_tensor(Y - w_top) + t * half               # >= 0 inside the top layer
    d_bot = torch.as_tensor(w_bot - Y) + t * half               # >= 0 inside the bottom layer
    piece_area = torch.as_tensor(_triangle_areas(pieces))
    T = mesh.n_elements
    index = torch.as_tensor(owner)
    A = torch.as_tensor(areas)
    f_top = torch.zeros(T, dtype=torch.float64).index_add(0, index, positive_part_area(d_top, piece_area)) / A
    f_bot = torch.zeros(T, dtype=torch.float64).index_add(0, index, positive_part_area(d_bot, piece_area)) / A
    if elements is not None:
        f_top, f_bot = f_top[elements], f_bot[elements]
    return f_top, f_bot


def positive_part_area(d: torch.Tensor, area: torch.Tensor) -> torch.Tensor:
    """Area [P] of the part of each triangle where a linear function is >= 0, given its values
    d [P, 3] at the vertices and the triangle areas [P]. With k the vertex whose sign differs
    from the other two and t_k = d_k^2 / ((d_k - d_i)(d_k - d_j)) (the similar sub-triangle at
    k, as a fraction of the area): area t_k if d_k is the only positive value, area (1 - t_k) if
    it is the only non-positive one, the whole or nothing if all signs agree."""
    pos = d > 0
    n_pos = pos.sum(-1)
    d_i, d_j = d.roll(-1, -1), d.roll(-2, -1)
    den = (d - d_i) * (d - d_j)
    tip = d * d / torch.where(den == 0, torch.ones_like(den), den)
    one_up = (tip * pos).sum(-1)                 # n_pos == 1: the positive vertex's corner
    one_down = 1 - (tip * ~pos).sum(-1)          # n_pos == 2: all but the negative vertex's corner
    share = torch.where(n_pos == 3, torch.ones_like(one_up),
                        torch.where(n_pos == 2, one_down, torch.where(n_pos == 1, one_up, torch.zeros_like(one_up))))
    return area * share


def surface_half_widths(mesh: FishMesh, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(w_top, w_bot) [K]: the largest and smallest Y of the mesh's surface polyline at each X [K]
    (m); the body occupies w_bot(X) <= Y <= w_top(X) wherever its outline is a graph over X."""
    p = mesh.points[mesh.surface]
    a, b = p, np.roll(p, -1, axis=0)
    lo, hi = np.minimum(a[:, 0], b[:, 0]), np.maximum(a[:, 0], b[:, 0])
    dx = b[:, 0] - a[:, 0]
    ok = np.abs(dx) > 1e-12 * mesh.length                      # vertical segments (blunt ends) are skipped
    X = np.asarray(X, np.float64)
    w_top, w_bot = np.full(X.shape, -np.inf), np.full(X.shape, np.inf)
    for start in range(0, len(X), 4096):                       # [chunk, edges] at a time
        x = X[start:start + 4096, None]
        inside = ok[None, :] & (x >= lo[None, :]) & (x <= hi[None, :])
        s = (x - a[None, :, 0]) / np.where(ok, dx, 1.0)[None, :]
        y = a[None, :, 1] + s * (b[None, :, 1] - a[None, :, 1])
        w_top[start:start + 4096] = np.where(inside, y, -np.inf).max(1)
        w_bot[start:start + 4096] = np.where(inside, y, np.inf).min(1)
    if not (np.all(np.isfinite(w_top)) and np.all(np.isfinite(w_bot))):
        raise ConfigError("the muscle layer lies outside the fish's outline (x_range must stay within [0, 1])")
    return w_top, w_bot


def _triangle_areas(tri: np.ndarray) -> np.ndarray:
    """Signed areas [P] of triangles [P, 3, 2] (> 0 when ccw)."""
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    return 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])


def _slab_pieces(mesh: FishMesh, x_range) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The elements cut to x0 <= X <= x1 (x0, x1 = x_range L): (pieces [P, 3, 2] ccw triangles,
    owner [P] element index, element areas [T]). Elements inside are one piece, elements cut by
    a plane (clipped polygons of up to 5 vertices) are fanned into triangles, those outside
    are dropped."""
    x0, x1 = x_range[0] * mesh.length, x_range[1] * mesh.length
    tri = mesh.points[mesh.triangles]                                  # [T, 3, 2]
    areas = _triangle_areas(tri)
    xmin, xmax = tri[:, :, 0].min(1), tri[:, :, 0].max(1)
    inside = (xmin >= x0) & (xmax <= x1)
    pieces, owner = [tri[inside]], [np.flatnonzero(inside)]
    for e in np.flatnonzero(~inside & (xmax > x0) & (xmin < x1)):
        poly = _clip(_clip(list(tri[e]), x0, +1.0), x1, -1.0)
        for k in range(1, len(poly) - 1):
            pieces.append(np.array([[poly[0], poly[k], poly[k + 1]]]))
            owner.append(np.array([e]))
    pieces, owner = np.concatenate(pieces), np.concatenate(owner)
    keep = _triangle_areas(pieces) > 0.0
    return pieces[keep], owner[keep], areas


def _clip(poly: list, x_cut: float, sign: float) -> list:
    """The convex polygon (list of [2] vertices) cut to sign (X - x_cut) >= 0 (Sutherland-Hodgman)."""
    out = []
    for k in range(len(poly)):
        p, q = poly[k], poly[(k + 1) % len(poly)]
        dp, dq = sign * (p[0] - x_cut), sign * (q[0] - x_cut)
        if dp >= 0:
            out.append(p)
        if (dp >= 0) != (dq >= 0):
            out.append(p + (q - p) * (dp / (dp - dq)))
    return out
