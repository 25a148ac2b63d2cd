"""Prototype: the IBM's linear fit in a normal coordinate compressed by the node's convex
curvature, h' = h / (1 + kappa h) (potential flow about a body of radius R = 1 / kappa decays as
R / (R + h), which is linear in h'), the free plane where the surface is flat or concave."""
import torch

from fishsim.coupling import ibm as I

STENCIL = 3


def curvature(qs, j=STENCIL):
    """Menger curvature through q[k-j], q[k], q[k+j] of the closed ccw polyline [B, S, 2]; > 0 convex."""
    a, b = torch.roll(qs, j, 1), torch.roll(qs, -j, 1)
    u, v = qs - a, b - qs
    cross = u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]
    return 2 * cross / ((u.norm(dim=-1) * v.norm(dim=-1) * (b - a).norm(dim=-1)) + 1e-30)


def curved_force(qs, p, mask, grid, sigma_prime, surface=None, cap_cells=1.0, j=STENCIL):
    if surface is not None:
        qs = qs[:, surface]
    elements = I.surface_elements(qs, I.CHORD)
    flat, ox, oy, wn = I.surface_samples(qs, mask, grid, sigma_prime, I.OUTSIDE, p.dtype, elements)
    n = (elements / elements.norm(dim=-1, keepdim=True)).to(p.dtype)
    nx, ny = n[..., 0, None], n[..., 1, None]
    kappa = curvature(qs, j).clamp(0.0, 1.0 / (cap_cells * grid.dx)).to(p.dtype)[..., None]
    h = ox * nx + oy * ny
    s = oy * nx - ox * ny
    h2 = h / (1 + kappa * h.clamp(min=0))
    ox2, oy2 = h2 * nx - s * ny, h2 * ny + s * nx
    p_k = I.fit_at_node(I.gather_cells(p, flat), wn, ox2, oy2, sigma_prime, I.LINEAR)
    return (-p_k.unsqueeze(-1) * elements.to(p.dtype)).to(qs.dtype)
