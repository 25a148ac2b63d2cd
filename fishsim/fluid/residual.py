"""The incompressible Navier-Stokes momentum residual (docs/physics.md section 5), written once.

    R = rho [ (v_new - v_old) / h + (vbar . grad) vbar ] + grad p_new - mu lap vbar,
    vbar = (v_old + v_new) / 2                                  (IMEX, Wandel et al. 2021)

on the MAC faces, in Pa/m (N/m^3 per unit depth).  HydroNet's unsupervised loss weights R with
``fluid_face_masks`` and (v_new - v_d) with ``boundary_face_masks``; the numerical solver's tests
use the same function as an oracle.  Stencils come from ``fishsim.fluid.grid``: central flux-form
advection, 5-point Laplacian with wall ghosts, pressure gradient zero on the wall faces.
"""

from __future__ import annotations

import torch
from torch import Tensor

from fishsim.fields import Grid
from fishsim.fluid.grid import NO_SLIP, Faces, WallBC, advection, face_masks, gradient, laplacian_faces


def per_sample(x: Tensor | float, like: Tensor) -> Tensor:
    """A scalar or [B] parameter as a [B, 1, 1, 1] (or scalar) tensor on ``like``'s device/dtype."""
    x = torch.as_tensor(x, device=like.device, dtype=like.dtype)
    return x.reshape(-1, 1, 1, 1) if x.ndim else x


def momentum_residual(
    v_old: Faces,
    v_new: Faces,
    p_new: Tensor,
    rho: Tensor | float,
    mu: Tensor | float,
    h: float,
    grid: Grid,
    walls: WallBC = NO_SLIP,
    scheme: str = "central",
) -> Faces:
    """IMEX momentum residual (R_x, R_y) on the faces, [B, 1, H, W+1] and [B, 1, H+1, W], Pa/m.

    v_old, v_new: face velocities (vx, vy) in m/s (e.g. ``grid.curl(a)``); p_new [B, 1, H, W] Pa;
    rho [B] kg/m^3 (2D: per unit depth), mu [B] Pa s, h s.  The wall-face entries are not
    momentum equations (their normal velocity is prescribed): mask them with
    ``fluid_face_masks``, which is zero there.  ``scheme`` selects the advective interpolation
    (``grid.advection``); ``walls`` the ghost values of the Laplacian and advection at the box.
    """
    dx = grid.dx
    vbar = tuple(0.5 * (o + n) for o, n in zip(v_old, v_new))
    adv = advection(vbar, dx, walls, scheme)
    lap = laplacian_faces(vbar, dx, walls)
    grad_p = gradient(p_new, dx)
    rho_, mu_ = per_sample(rho, p_new), per_sample(mu, p_new)
    return tuple(
        rho_ * ((n - o) / h + a) + g - mu_ * l
        for o, n, a, g, l in zip(v_old, v_new, adv, grad_p, lap)
    )


def boundary_face_masks(b: Tensor) -> Faces:
    """Boundary weight of each face, the mean of its two cells' soft mask b [B, 1, H, W]
    (``grid.face_masks``); in [0, 1], 1 = solid.  Used for the boundary term
    || b_f (v_new - v_d) ||^2 with v_d on faces from ``grid.vector_to_faces``."""
    return face_masks(b)


def fluid_face_masks(b: Tensor) -> Faces:
    """Fluid weight of each face, 1 - b_f, and zero on the four box-wall faces (where the
    normal velocity is prescribed, not solved for).  Weights the momentum residual."""
    bx, by = face_masks(b)
    fx, fy = 1 - bx, 1 - by
    fx = torch.cat([torch.zeros_like(fx[..., :1]), fx[..., 1:-1], torch.zeros_like(fx[..., :1])], -1)
    fy = torch.cat([torch.zeros_like(fy[..., :1, :]), fy[..., 1:-1, :], torch.zeros_like(fy[..., :1, :])], -2)
    return fx, fy
