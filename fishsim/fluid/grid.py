"""MAC-grid stencils in physical units, shared by HydroNet's loss and the numerical solver.

Layout (``fishsim.fields``; docs/physics.md section 4): H x W cells of side ``dx`` [m], row index i
along y, column index j along x, every field ``[B, C, rows, cols]``:

* ``a``  [B, 1, H+1, W+1]  vector potential at vertices ``(j dx, i dx)``                    [m^2/s]
* ``vx`` [B, 1, H, W+1]    x-velocity on vertical faces ``(j dx, (i+1/2) dx)``              [m/s]
* ``vy`` [B, 1, H+1, W]    y-velocity on horizontal faces ``((j+1/2) dx, i dx)``            [m/s]
* ``p``  [B, 1, H, W]      pressure (or any scalar: mask b, divergence) at cell centres

A face velocity is passed around as the pair ``(vx, vy)`` (type ``Faces``).  The outermost faces
(``vx[..., 0]``, ``vx[..., W]``, ``vy[..., 0, :]``, ``vy[..., H, :]``) lie on the box walls and
carry the normal velocity through them.

Each stencil is written once below as a formula on arrays extended by ghost values
(``pad_faces``); the ghost values encode the wall condition (``WallBC``): the normal velocity is
continued by odd reflection about the wall face, the tangential velocity by reflection about the
wall half a cell away (no-slip: ``2 u_wall - u``, slip: ``u``).  Everything is batched, pure torch,
differentiable, and works on any device and dtype.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from fishsim.fields import MASK_FLOOR, Boundary, Grid, union  # noqa: F401  (MASK_FLOOR, union: re-exported)

Faces = tuple[Tensor, Tensor]
"""A MAC face field ``(vx [B, C, H, W+1], vy [B, C, H+1, W])``."""

X, Y = -1, -2  # tensor dims of the x (columns) and y (rows) directions


# --------------------------------------------------------------------------------------------
# Wall conditions and ghost values
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class WallBC:
    """Condition on the tangential velocity at the four box walls (the normal one is the value
    stored on the outer faces).

    slip: False = no-slip (u = u_wall at the wall), True = free slip (du/dn = 0).
    u_bottom, u_top: x-velocity of the walls y = 0 and y = Ly (a moving lid) [m/s].
    v_left, v_right: y-velocity of the walls x = 0 and x = Lx [m/s].
    """

    slip: bool = False
    u_bottom: float = 0.0
    u_top: float = 0.0
    v_left: float = 0.0
    v_right: float = 0.0


NO_SLIP = WallBC()
FREE_SLIP = WallBC(slip=True)


def _ghost_normal(v: Tensor, dim: int, n: int) -> Tensor:
    """Extend ``v`` by ``n`` values beyond its wall faces (first and last entries along ``dim``)
    by odd reflection about them: ``v[-k] = 2 v[0] - v[k]`` (linear continuation)."""
    L = v.shape[dim]
    lo0, hi0 = v.narrow(dim, 0, 1), v.narrow(dim, L - 1, 1)
    lo = [2 * lo0 - v.narrow(dim, k, 1) for k in range(n, 0, -1)]
    hi = [2 * hi0 - v.narrow(dim, L - 1 - k, 1) for k in range(1, n + 1)]
    return torch.cat(lo + [v] + hi, dim)


def _ghost_tangential(v: Tensor, dim: int, n: int, lo_wall: float, hi_wall: float, slip: bool) -> Tensor:
    """Extend ``v`` by ``n`` values beyond walls lying half a cell before its first and after its
    last entry along ``dim``: ``v[-k] = v[k-1]`` (slip) or ``2 u_wall - v[k-1]`` (no-slip)."""
    L = v.shape[dim]

    def mirror(k: int, wall: float) -> Tensor:
        inner = v.narrow(dim, k, 1)
        return inner if slip else 2 * wall - inner

    lo = [mirror(k - 1, lo_wall) for k in range(n, 0, -1)]
    hi = [mirror(L - k, hi_wall) for k in range(1, n + 1)]
    return torch.cat(lo + [v] + hi, dim)


def pad_faces(v: Faces, walls: WallBC = NO_SLIP, n: int = 1) -> Faces:
    """Face velocities extended by ``n`` ghost layers on every side, [B, C, H+2n, W+1+2n] and
    [B, C, H+1+2n, W+2n]; the ghosts encode ``walls`` (module docstring)."""
    vx, vy = v
    vx = _ghost_normal(vx, X, n)
    vx = _ghost_tangential(vx, Y, n, walls.u_bottom, walls.u_top, walls.slip)
    vy = _ghost_normal(vy, Y, n)
    vy = _ghost_tangential(vy, X, n, walls.v_left, walls.v_right, walls.slip)
    return vx, vy


def _core(q: Tensor, n: int, dim: int) -> Tensor:
    """Strip ``n`` ghost layers along ``dim``."""
    return q.narrow(dim, n, q.shape[dim] - 2 * n)


def zero_walls(v: Faces) -> Faces:
    """Set the normal velocity on the four box walls (outer faces) to zero."""
    vx, vy = v
    vx = F.pad(vx[..., 1:-1], (1, 1))
    vy = F.pad(vy[..., 1:-1, :], (0, 0, 1, 1))
    return vx, vy


# --------------------------------------------------------------------------------------------
# First-order operators: curl, divergence, gradient
# --------------------------------------------------------------------------------------------


def curl(a: Tensor, dx: float) -> Faces:
    """v = curl a:  vx = da/dy,  vy = -da/dx  (vertices -> faces), exactly divergence free.

    a: [B, 1, H+1, W+1] m^2/s -> vx [B, 1, H, W+1], vy [B, 1, H+1, W] in m/s.
    """
    vx = (a[..., 1:, :] - a[..., :-1, :]) / dx
    vy = -(a[..., :, 1:] - a[..., :, :-1]) / dx
    return vx, vy


def divergence(v: Faces, dx: float) -> Tensor:
    """div v = dvx/dx + dvy/dy at cell centres (faces -> centres), [B, C, H, W] in 1/s.
    Includes the wall faces, so sum(div v) dx^2 is the net outflow through the box."""
    vx, vy = v
    return (vx[..., 1:] - vx[..., :-1]) / dx + (vy[..., 1:, :] - vy[..., :-1, :]) / dx


def gradient(p: Tensor, dx: float) -> Faces:
    """grad p on the faces (centres -> faces), zero on the wall faces (homogeneous Neumann).

    p: [B, C, H, W] -> ([B, C, H, W+1], [B, C, H+1, W]).  With it,
    <grad p, v> = -<p, div v> for every v with zero normal wall velocity (``divergence`` is minus
    its adjoint).
    """
    gx = F.pad((p[..., 1:] - p[..., :-1]) / dx, (1, 1))
    gy = F.pad((p[..., 1:, :] - p[..., :-1, :]) / dx, (0, 0, 1, 1))
    return gx, gy


def vorticity(v: Faces, dx: float, walls: WallBC = NO_SLIP) -> Tensor:
    """omega = dvy/dx - dvx/dy at the vertices, [B, C, H+1, W+1] in 1/s (wall values from the
    ghosts of ``walls``).  For v = curl a, omega = -lap a."""
    vx, vy = pad_faces(v, walls, 1)
    vx, vy = _core(vx, 1, X), _core(vy, 1, Y)
    return (vy[..., 1:] - vy[..., :-1]) / dx - (vx[..., 1:, :] - vx[..., :-1, :]) / dx


# --------------------------------------------------------------------------------------------
# Laplacians
# --------------------------------------------------------------------------------------------


def _laplacian5(q: Tensor, dx: float) -> Tensor:
    """5-point Laplacian of an array with one ghost layer on every side (returns the core)."""
    c = q[..., 1:-1, 1:-1]
    return (q[..., 1:-1, 2:] + q[..., 1:-1, :-2] + q[..., 2:, 1:-1] + q[..., :-2, 1:-1] - 4 * c) / dx**2


def laplacian_faces(v: Faces, dx: float, walls: WallBC = NO_SLIP) -> Faces:
    """Component-wise 5-point Laplacian lap v on the faces, 1/(m s); wall ghosts from ``walls``.
    The discrete mode sin(k x) cos(k y) has eigenvalue -(8/dx^2) sin^2(k dx/2) (docs/validation.md)."""
    vx, vy = pad_faces(v, walls, 1)
    return _laplacian5(vx, dx), _laplacian5(vy, dx)


def laplacian_centres(p: Tensor, dx: float) -> Tensor:
    """lap p = div grad p at the centres with homogeneous Neumann walls, [B, C, H, W].
    This is the operator of the pressure projection, diagonalised by the DCT-II."""
    return divergence(gradient(p, dx), dx)


# --------------------------------------------------------------------------------------------
# Advection (v . grad) v = div(v v) in flux form
# --------------------------------------------------------------------------------------------


ALBADA_U = 1e-3     # m/s: width of the smooth upwind switch
ALBADA_EPS = 1e-8   # (m/s)^2: smoothing of the van Albada limiter


def _median(a: Tensor, b: Tensor, c: Tensor) -> Tensor:
    return torch.maximum(torch.minimum(a, b), torch.minimum(torch.maximum(a, b), c))


def koren(u: Tensor, c: Tensor, d: Tensor) -> Tensor:
    """Face value between the upwind cell c and the downwind cell d (u: the one upwind of c).

    Third-order upwind-biased interpolation phi = (5c + 2d - u)/6 (kappa = 1/3), limited to the
    TVD range between c and median(c, d, c + 2 (c - u)) (Koren 1993).
    """
    return _median(c, (5 * c + 2 * d - u) / 6, _median(c, d, 3 * c - 2 * u))


def albada(u: Tensor, c: Tensor, d: Tensor, eps: float) -> Tensor:
    """Face value between the upwind cell c and the downwind cell d with the van Albada limiter:
    c + (1/2) ((a^2 + eps) b + (b^2 + eps) a) / (a^2 + b^2 + 2 eps), a = c - u, b = d - c.
    Second order, TVD, and a smooth function of u, c, d (no min/max): gradients through it have
    no kinks. eps [same units^2] keeps it smooth where a = b = 0."""
    a, b = c - u, d - c
    return c + 0.5 * ((a * a + eps) * b + (b * b + eps) * a) / (a * a + b * b + 2 * eps)


def _midpoint_values(q: Tensor, velocity: Tensor, dim: int, scheme: str) -> Tensor:
    """Values of ``q`` (two ghost layers along ``dim``) between consecutive entries m, m+1 for
    m = 1 .. len-3 (padded indices), upwinded by the sign of ``velocity`` there."""
    L = q.shape[dim] - 3
    qm, q0, q1, q2 = (q.narrow(dim, s, L) for s in range(4))
    if scheme == "central":
        return 0.5 * (q0 + q1)
    if scheme == "koren":
        return torch.where(velocity >= 0, koren(qm, q0, q1), koren(q2, q1, q0))
    if scheme == "albada":                  # smooth limiter, smooth upwinding (width ALBADA_U m/s)
        w = 0.5 * (1 + torch.tanh(velocity / ALBADA_U))
        return w * albada(qm, q0, q1, ALBADA_EPS) + (1 - w) * albada(q2, q1, q0, ALBADA_EPS)
    raise ValueError(f"unknown advection scheme {scheme!r}; use 'koren', 'albada' or 'central'")


def advection(v: Faces, dx: float, walls: WallBC = NO_SLIP, scheme: str = "koren") -> Faces:
    """Convective acceleration (v . grad) v = div(v v) on the faces, m/s^2.

    Flux form on the MAC control volumes: for vx,
    (v.grad vx)_ij = [U q]_(centre i, j) - [U q]_(centre i, j-1)) / dx
                   + ([V q]_(vertex i+1, j) - [V q]_(vertex i, j)) / dx,
    with the transporting velocities U, V averaged onto the control-volume faces and the
    transported value q interpolated by ``scheme``: "central" (second order, energy conserving,
    the HydroNet residual) or "koren" (third-order upwind, TVD-limited; the solver).  vy likewise.
    Values on the wall faces are set to zero (the normal wall velocity is prescribed).
    """
    n = 2
    vxp, vyp = pad_faces(v, walls, n)
    # x-momentum: transport of vx
    vx_rows = _core(vxp, n, Y)  # [H, W+5], ghost columns only
    U = 0.5 * (vx_rows[..., 1:-2] + vx_rows[..., 2:-1])  # cell centres c = -1 .. W
    Fx = U * _midpoint_values(vx_rows, U, X, scheme)
    vx_cols = _core(vxp, n, X)  # [H+4, W+1], ghost rows only
    V = 0.5 * (vyp[..., n:-n, n - 1 : -n] + vyp[..., n:-n, n : -n + 1 or None])  # vertices [H+1, W+1]
    Gx = V * _midpoint_values(vx_cols, V, Y, scheme)
    ax = (Fx[..., 1:] - Fx[..., :-1]) / dx + (Gx[..., 1:, :] - Gx[..., :-1, :]) / dx
    # y-momentum: transport of vy
    vy_cols = _core(vyp, n, X)  # [H+5, W]
    V = 0.5 * (vy_cols[..., 1:-2, :] + vy_cols[..., 2:-1, :])  # cell centres r = -1 .. H
    Fy = V * _midpoint_values(vy_cols, V, Y, scheme)
    vy_rows = _core(vyp, n, Y)  # [H+1, W+4]
    U = 0.5 * (vxp[..., n - 1 : -n, n:-n] + vxp[..., n : -n + 1 or None, n:-n])  # vertices [H+1, W+1]
    Gy = U * _midpoint_values(vy_rows, U, X, scheme)
    ay = (Fy[..., 1:, :] - Fy[..., :-1, :]) / dx + (Gy[..., 1:] - Gy[..., :-1]) / dx
    return zero_walls((ax, ay))


# --------------------------------------------------------------------------------------------
# Interpolation between centres, faces and vertices
# --------------------------------------------------------------------------------------------


def faces_to_centres(v: Faces) -> Tensor:
    """Average each face component onto the cell centres: [B, 2C, H, W], channels (x, y)."""
    vx, vy = v
    return torch.cat([0.5 * (vx[..., 1:] + vx[..., :-1]), 0.5 * (vy[..., 1:, :] + vy[..., :-1, :])], 1)


def centres_to_faces(q: Tensor) -> Faces:
    """Average a centre field onto the faces, each face the mean of its two cells; a wall face
    takes its one cell's value.  q: [B, C, H, W] -> ([B, C, H, W+1], [B, C, H+1, W])."""
    return _to_x_faces(q), _to_y_faces(q)


def _to_x_faces(q: Tensor) -> Tensor:
    qx = torch.cat([q[..., :1], q, q[..., -1:]], X)
    return 0.5 * (qx[..., 1:] + qx[..., :-1])


def _to_y_faces(q: Tensor) -> Tensor:
    qy = torch.cat([q[..., :1, :], q, q[..., -1:, :]], Y)
    return 0.5 * (qy[..., 1:, :] + qy[..., :-1, :])


def vector_to_faces(v: Tensor) -> Faces:
    """A centre vector field [B, 2, H, W] (x, y) -> its normal components on the faces:
    vx from channel 0 onto the vertical faces, vy from channel 1 onto the horizontal faces."""
    return _to_x_faces(v[:, 0:1]), _to_y_faces(v[:, 1:2])


def face_masks(b: Tensor) -> Faces:
    """Face masks (b_x, b_y) of a centre mask b [B, 1, H, W]: the average of the two cells
    sharing a face (the one cell on the walls).  Same as ``centres_to_faces``."""
    return centres_to_faces(b)


def centres_to_vertices(q: Tensor) -> Tensor:
    """Average of the (up to) four cells around each vertex: [B, C, H, W] -> [B, C, H+1, W+1]."""
    q = F.pad(q, (1, 1, 1, 1), mode="replicate")
    return 0.25 * (q[..., 1:, 1:] + q[..., 1:, :-1] + q[..., :-1, 1:] + q[..., :-1, :-1])


def vertices_to_centres(a: Tensor) -> Tensor:
    """Average of the four vertices of each cell: [B, C, H+1, W+1] -> [B, C, H, W]."""
    return 0.25 * (a[..., 1:, 1:] + a[..., 1:, :-1] + a[..., :-1, 1:] + a[..., :-1, :-1])


# --------------------------------------------------------------------------------------------
# Stream function <-> velocity
# --------------------------------------------------------------------------------------------


def stream_function(v: Faces, dx: float) -> Tensor:
    """The vector potential a with curl a = v, for a divergence-free v, mean removed.

    Path integral from the vertex (0, 0): up the left wall a(i+1, 0) = a(i, 0) + dx vx(i, 0), then
    along each row a(i, j+1) = a(i, j) - dx vy(i, j).  For div v = 0 (to round-off) this is
    path independent and curl(stream_function(v)) reproduces v to round-off (a cumsum, O(N)).
    A general v must first be made divergence free: ``fishsim.fluid.numerical.project``.
    v: ([B,1,H,W+1], [B,1,H+1,W]) m/s -> a [B, 1, H+1, W+1] m^2/s.
    """
    vx, vy = v
    left = F.pad(torch.cumsum(vx[..., 0:1] * dx, Y), (0, 0, 1, 0))  # [B, 1, H+1, 1]
    a = torch.cat([left, left - torch.cumsum(vy * dx, X)], X)
    return a - a.mean(dim=(-2, -1), keepdim=True)


def potential_pressure(v: Faces, p: Tensor, dx: float) -> tuple[Tensor, Tensor]:
    """(v, p) -> (a, p) with ``stream_function`` (v divergence free) and p mean free."""
    return stream_function(v, dx), p - p.mean(dim=(-2, -1), keepdim=True)


# --------------------------------------------------------------------------------------------
# Domain boundaries: wall bands and inflow / outflow bands (Boundary on the cell centres)
# --------------------------------------------------------------------------------------------


def wall_mask(
    grid: Grid, thickness_y: int = 3, thickness_x: int = 5, batch: int = 1, device=None, dtype=torch.float32
) -> Tensor:
    """Mask [B, 1, H, W] of solid wall bands: ``thickness_y`` rows at the bottom and top,
    ``thickness_x`` columns at the left and right (Wandel et al.: 3 and 5).  Zero gives no band."""
    m = torch.zeros(batch, 1, grid.H, grid.W, device=device, dtype=dtype)
    if thickness_y > 0:
        m[..., :thickness_y, :] = 1.0
        m[..., -thickness_y:, :] = 1.0
    if thickness_x > 0:
        m[..., :thickness_x] = 1.0
        m[..., -thickness_x:] = 1.0
    return m


def closed_tank(
    grid: Grid, thickness_y: int = 3, thickness_x: int = 5, batch: int = 1, device=None, dtype=torch.float32
) -> Boundary:
    """A closed tank at rest: ``wall_mask`` with zero boundary velocity."""
    b = wall_mask(grid, thickness_y, thickness_x, batch, device, dtype)
    return Boundary(mask=b, velocity=torch.zeros(batch, 2, grid.H, grid.W, device=device, dtype=dtype))


def channel(
    grid: Grid,
    speed: float | Tensor,
    thickness_y: int = 3,
    thickness_x: int = 5,
    batch: int = 1,
    device=None,
    dtype=torch.float32,
) -> Boundary:
    """Inflow/outflow on the short sides: wall bands of ``thickness_y`` rows at the bottom and top
    (at rest) and bands of ``thickness_x`` columns at the left and right that impose v_x = speed
    (scalar or [B], m/s) over the open rows.  Inflow equals outflow, as the projection needs."""
    b = wall_mask(grid, thickness_y, thickness_x, batch, device, dtype)
    speed = torch.as_tensor(speed, device=device, dtype=dtype).reshape(-1, 1, 1)
    vd = torch.zeros(batch, 2, grid.H, grid.W, device=device, dtype=dtype)
    open_rows = slice(thickness_y, grid.H - thickness_y)
    ends = torch.zeros(grid.H, grid.W, device=device, dtype=dtype)
    ends[open_rows, :thickness_x] = 1.0
    ends[open_rows, grid.W - thickness_x :] = 1.0
    vd[:, 0] = speed * ends
    return Boundary(mask=b, velocity=vd)


