"""Fluid -> solid: immersed-boundary pressure forces on the surface nodes (paper Sec. 3.3).

    f_k = -l_k n_k p_k,    p_k = sum_ij p_ij g_ij w_ij / Z_k,    Z_k = sum_ij g_ij w_ij,
    g_ij = exp(-|x_ij - q^k|^2 / (2 sigma'))

f_k [N per unit depth] is the pressure force on the piece of surface of length l_k around node k
with outward normal n_k.  The paper neglects the viscous stress; ``ibm_force(viscous=...)`` adds
the traction mu (grad v + grad v^T) n_k (``coupling.viscous``):

    f_k^visc = mu (G_k + G_k^T) a_k,   G_k = argmin_G sum_ij g_ij w_ij |v_ij - u_k - G (x_ij - q^k)|^2

with u_k the node's velocity (no slip) and the same "outside" samples as the pressure.  The fit
runs from the node, where the fluid moves with the body, out to the cells beyond the mask's band,
so it resolves a boundary layer no thinner than about a cell: on the towed disc of
tests/fluid/test_validation.py (Re = 100) pressure + traction is 0.99-1.14 of the drag the
penalization exchanges with the fluid (the pressure alone 0.67-0.80).

The surface element (``area``):

* ``"chord"`` (default): l_k n_k is replaced by the area vector a_k = J (q^{k+1} - q^{k-1}) / 2
  (half of each adjacent edge times its outward normal; same direction n_k, |a_k| <= l_k).
  sum_k a_k = 0 exactly, so a uniform pressure exerts no net force, and for a linear pressure
  field the forces sum to -grad p * area exactly (divergence theorem on the polygon).
* ``"paper"``: l_k n_k with l_k = (|q^{k-1} - q^k| + |q^k - q^{k+1}|) / 2.  Equal to a_k on
  straight stretches, but at the fish's sharp tail tip (turning angle ~160 deg) l_k n_k
  overshoots a_k by ~l_k: a uniform 100 Pa pressure then pushes a 200-node fish by 0.15 N
  (spurious self-propulsion) and the divergence theorem misses by ~10 %.

Which cells sample the pressure (``weight`` w_ij):

* ``"outside"`` (default), w = S(b) H(n_k . (x_ij - q^k)): the force on the body is the pressure
  the fluid exerts on the outside of its surface, so only cells outside the mask's soft band are
  sampled (S: 1 at b = 0, 0 from b = 0.05 on, ``OUTSIDE_MASK``, C^2), and only on the node's own
  side (H: 0 below the node's tangent line, 1 from one cell above it, C^2, ``side_weight``).
  Inside the band the pressure is the penalisation's, not the fluid's: it balances the forcing
  that drives the band to the body's velocity and grows with that forcing's stiffness (sub-steps
  x passes, or lambda), so sampling it gave a towed disc 12x its drag at the fish's default
  stepping (36x with the rate penalisation); outside it, the disc's pressure drag is 0.67-0.80 of
  the drag the penalisation exchanges with the fluid and its oscillating added-mass force within
  2.4 % of potential flow (tests/fluid/test_validation.py).  Across the thin tail (under a cell)
  the other side's fluid lies one or two cells from a node; the side factor keeps its pressure,
  whose jump drives the fish, from cancelling the node's own (on a 1 mm plate between +P and -P
  the force is 0.02 % off; with w = 1 - b it is 88 % short).
* ``"fluid"``, w = 1 - b: the former default (both failures above).
* ``"body"``, w = b: the paper's formula, which samples the pressure inside the body.
* ``"none"``, w = 1: the plain Gaussian average (inside and outside).

How the samples become p_k (``fit``):

* ``"mean"`` (the paper): the normalised weighted mean.  With one-sided weights its sampling
  point lies ~1 cell off the surface, which biases p_k by ~dx |grad p|.
* ``"linear"`` (default): a weighted least-squares plane p ~ c + g.(x - q^k) over the same
  samples, evaluated at q^k (c).  Exact for linear pressure fields whatever the weights, so the
  one-sided fluid sample is extrapolated to the surface itself.
* ``"wall"``: the same plane with its slope along the node's normal n_k imposed, p ~ c + G_k h +
  g_t s (h, s the offsets along n_k and the tangent), G_k = -rho a_k.n_k the normal momentum
  balance at a no-slip wall of acceleration a_k (viscous term neglected). Around an accelerating
  body the pressure falls off over the body's size (as R / r about a cylinder), and the free
  plane, fitted 0.5-2 cells out, is shallower than the wall's: an oscillating cylinder's force
  15 % short at 8 cells per D, 3 % with the wall's slope (docs/validation.md, "The wall's
  pressure gradient imposed").

sigma' default dx^2 = 6.25e-6 m^2: a kernel of standard deviation one cell, the narrowest whose
discrete moments on the lattice are still those of the continuous Gaussian (the lattice error of
its first moment is ~exp(-2 pi^2 sigma'/dx^2) ~ 3e-9) and that sees ~10 fluid cells on the
outer side of every node; wider kernels smear the pressure along the 2 mm-spaced nodes.
Each node only reads the (2r+1)^2 cells within r = ceil(4 sqrt(sigma') / dx) cells (4 standard
deviations), gathered per node: cost O(B S r^2). Which cells those are jumps when a node crosses
a cell boundary, so the Gaussian is tapered to zero before the window's edge: per axis it is
multiplied by a C^2 smoothstep that is 1 up to (r - 1) dx and 0 from (r + 1/2) dx on (a cell
outside the window is never nearer than that). The taper changes only weights below
exp(-(r - 1)^2 / 2) of the peak (1.1 % at r = 4), and p_k is a smooth function of the node's
position (without it, p_k jumped by ~3e-5 of the pressure scale at every cell crossing).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from fishsim.coupling.config import BODY, CHORD, FLUID, LINEAR, MEAN, NONE, OUTSIDE, PAPER, WALL
from fishsim.coupling.geometry import area_vectors, surface_geometry
from fishsim.fields import Grid

KERNEL_RADIUS = 4.0  # in standard deviations sqrt(sigma')
OUTSIDE_MASK = 0.05  # "outside" samples cells with b below this: the rate penalisation's support (numerical.py)


def kernel_radius(sigma_prime: float, dx: float) -> int:
    """The sampling window's half-width in cells: KERNEL_RADIUS standard deviations, rounded up."""
    return math.ceil(KERNEL_RADIUS * math.sqrt(sigma_prime) / dx)


def kernel_cells(qs: Tensor, grid: Grid, radius: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The (2r+1)^2 cells around each node: flat index [B, S, M] (clamped into the grid),
    validity [B, S, M] bool and the offsets x_ij - q^k as two contiguous [B, S, M] tensors
    (x and y components, m, dtype of qs)."""
    centre = torch.floor(qs.detach() / grid.dx).long()  # (j, i) of the cell holding q^k
    step = torch.arange(-radius, radius + 1, device=qs.device)
    di, dj = torch.meshgrid(step, step, indexing="ij")
    j = centre[..., 0, None] + dj.flatten()
    i = centre[..., 1, None] + di.flatten()
    valid = (i >= 0) & (i < grid.H) & (j >= 0) & (j < grid.W)
    flat = i.clamp(0, grid.H - 1) * grid.W + j.clamp(0, grid.W - 1)
    ox = (j.to(qs.dtype) + 0.5) * grid.dx - qs[..., 0, None]      # in qs.dtype (float32 lost 1e-8 m)
    oy = (i.to(qs.dtype) + 0.5) * grid.dx - qs[..., 1, None]
    return flat, valid, ox, oy


def gather_cells(field: Tensor, flat: Tensor) -> Tensor:
    """field [B, 1, H, W] at flat cell indices [B, S, M] -> [B, S, M] (differentiable)."""
    B = field.shape[0]
    return field.reshape(B, -1).gather(1, flat.reshape(B, -1)).view(flat.shape)


def taper(u: Tensor, inner: float, outer: float) -> Tensor:
    """1 for |u| <= inner, 0 for |u| >= outer, the C^2 quintic smoothstep in between."""
    s = ((outer - u.abs()) / (outer - inner)).clamp(0.0, 1.0)
    return s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)


def side_weight(ox: Tensor, oy: Tensor, normal: Tensor, dx: float) -> Tensor:
    """0 -> 1 as a cell's height above the node's tangent line, n_k.(x_ij - q^k), goes 0 -> dx
    (C^2 smoothstep): the cells on the outer side of the node's own surface [B, S, M]."""
    h = ox * normal[..., 0, None] + oy * normal[..., 1, None]
    return taper((h - dx).clamp(max=0.0), 0.0, dx)


def sample_weights(ox: Tensor, oy: Tensor, b: Tensor, valid: Tensor, sigma_prime: float,
                   weight: str, dx: float | None = None, radius: int | None = None,
                   normal: Tensor | None = None) -> Tensor:
    """g_ij w_ij [B, S, M]: Gaussian kernel times the cell weight (module doc; offsets ox, oy
    [B, S, M]; "outside" needs the nodes' unit outward normals [B, S, 2]); with dx and the window
    radius r (cells), the kernel is tapered to 0 at the window's edge."""
    g = torch.exp((ox * ox + oy * oy) * (-0.5 / sigma_prime))
    if radius is not None:
        inner, outer = (radius - 1) * dx, (radius + 0.5) * dx
        g = g * (taper(ox, inner, outer) * taper(oy, inner, outer))
    if weight == FLUID:
        w = 1.0 - b
    elif weight == OUTSIDE:
        w = taper(b, 0.0, OUTSIDE_MASK) * side_weight(ox, oy, normal, dx)
    elif weight == BODY:
        w = b
    elif weight == NONE:
        return g * valid
    else:
        raise ValueError(f"weight must be 'outside', 'fluid', 'body' or 'none', got {weight!r}")
    return g * w * valid


def normalised(w: Tensor) -> Tensor:
    """w_ij / sum_ij w_ij over the last dim (weights summing to 1; 0 where all vanish)."""
    return w / w.sum(-1, keepdim=True).clamp_min(torch.finfo(w.dtype).tiny)


def linear_fit_correction(wn: Tensor, ox: Tensor, oy: Tensor, sigma_prime: float) -> Tensor:
    """d_ij [B, S, M] with p_k = pbar + sum_ij d_ij (p_ij - pbar) the value at the node (offset 0)
    of the weighted least-squares plane p ~ c + g.(x - q^k) (normalised weights wn, pbar the
    weighted mean):

        c = pbar - g.rbar,  g = C^-1 sum wn (r - rbar)(p - pbar)   ->   d_ij = -wn_ij rbar^T C^-1 (r_ij - rbar)

    with the weighted means rbar of the offsets and their covariance C (2 x 2, inverted in closed
    form, regularised by 1e-6 sigma').  Exact for linear p; the samples enter relative to pbar,
    which keeps float32 round-off at the scale of the pressure's variation around the node."""
    rx, ry = (wn * ox).sum(-1, keepdim=True), (wn * oy).sum(-1, keepdim=True)
    dx_, dy_ = ox - rx, oy - ry
    wdx, wdy = wn * dx_, wn * dy_
    c_xx = (wdx * dx_).sum(-1, keepdim=True) + 1e-6 * sigma_prime
    c_yy = (wdy * dy_).sum(-1, keepdim=True) + 1e-6 * sigma_prime
    c_xy = (wdx * dy_).sum(-1, keepdim=True)
    det = c_xx * c_yy - c_xy * c_xy
    ux, uy = (c_yy * rx - c_xy * ry) / det, (c_xx * ry - c_xy * rx) / det   # C^-1 rbar
    return -(ux * wdx + uy * wdy)


def gradient_coefficients(wn: Tensor, ox: Tensor, oy: Tensor, sigma_prime: float) -> tuple[Tensor, Tensor]:
    """(k_x, k_y) [B, S, M] with sum_ij k_b,ij dv_ij = d(dv)/dx_b at the node for the weighted
    least-squares fit dv ~ G (x - q^k) through the node (no intercept):

        G = (sum wn dv r^T) (sum wn r r^T)^-1   ->   k_ij = wn_ij C0^-1 r_ij

    (C0 the offsets' second moments, 2 x 2, inverted in closed form, regularised by 1e-6 sigma').
    Exact for a linear dv that vanishes at the node."""
    wox, woy = wn * ox, wn * oy
    c_xx = (wox * ox).sum(-1, keepdim=True) + 1e-6 * sigma_prime
    c_yy = (woy * oy).sum(-1, keepdim=True) + 1e-6 * sigma_prime
    c_xy = (wox * oy).sum(-1, keepdim=True)
    det = c_xx * c_yy - c_xy * c_xy
    return (c_yy * wox - c_xy * woy) / det, (c_xx * woy - c_xy * wox) / det


def surface_samples(qs: Tensor, mask: Tensor, grid: Grid, sigma_prime: float, weight: str,
                    dtype: torch.dtype, a: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The cells each surface node samples: flat indices [B, S, M], offsets x_ij - q^k (x and y,
    [B, S, M] each, m) and the normalised weights g_ij w_ij / Z_k [B, S, M], in ``dtype`` (the
    offsets are formed in qs.dtype).  a: the nodes' area vectors [B, S, 2] if already computed
    ("outside" needs their normals)."""
    radius = kernel_radius(sigma_prime, grid.dx)
    flat, valid, ox, oy = kernel_cells(qs, grid, radius)
    ox, oy = ox.to(dtype), oy.to(dtype)
    normal = None
    if weight == OUTSIDE:
        a = (area_vectors(qs) if a is None else a).to(dtype)
        normal = a / a.norm(dim=-1, keepdim=True)
    w = sample_weights(ox, oy, gather_cells(mask, flat).to(dtype), valid, sigma_prime, weight, grid.dx, radius,
                       normal)
    return flat, ox, oy, normalised(w)


def fit_at_node(p_cells: Tensor, wn: Tensor, ox: Tensor, oy: Tensor, sigma_prime: float, fit: str,
                normal: Tensor | None = None, dp_dn: Tensor | None = None) -> Tensor:
    """p_k [B, S] from the sampled cells' values [B, S, M] (module docstring, ``fit``; "wall" needs
    the nodes' unit outward normals [B, S, 2] and the imposed slopes dp_dn [B, S], Pa/m)."""
    if fit == WALL:
        h = ox * normal[..., 0, None] + oy * normal[..., 1, None]
        s = oy * normal[..., 0, None] - ox * normal[..., 1, None]
        return _wall_fit(p_cells - dp_dn.unsqueeze(-1) * h, wn, s, sigma_prime)
    p_bar = (wn * p_cells).sum(-1, keepdim=True)
    if fit == MEAN:
        return p_bar.squeeze(-1)
    if fit == LINEAR:
        d = linear_fit_correction(wn, ox, oy, sigma_prime)
        return (p_bar + (d * (p_cells - p_bar)).sum(-1, keepdim=True)).squeeze(-1)
    raise ValueError(f"fit must be 'mean', 'linear' or 'wall', got {fit!r}")


def _wall_fit(y: Tensor, wn: Tensor, s: Tensor, sigma_prime: float) -> Tensor:
    """c [B, S] of the weighted least-squares line y ~ c + g s over the samples (normalised
    weights wn, tangential offsets s [B, S, M]), regularised as ``linear_fit_correction``."""
    y_bar, s_bar = (wn * y).sum(-1, keepdim=True), (wn * s).sum(-1, keepdim=True)
    ds = s - s_bar
    g = (wn * ds * (y - y_bar)).sum(-1, keepdim=True) / ((wn * ds * ds).sum(-1, keepdim=True) + 1e-6 * sigma_prime)
    return (y_bar - g * s_bar).squeeze(-1)


def surface_pressure(qs: Tensor, p: Tensor, mask: Tensor, grid: Grid, sigma_prime: float,
                     weight: str = OUTSIDE, fit: str = LINEAR) -> Tensor:
    """Pressure p_k sampled around every surface node, [B, S] Pa, in p.dtype.

    The offsets x_ij - q^k are formed in qs.dtype, then everything runs in the fluid's dtype."""
    flat, ox, oy, wn = surface_samples(qs, mask, grid, sigma_prime, weight, p.dtype)
    return fit_at_node(gather_cells(p, flat), wn, ox, oy, sigma_prime, fit)


def viscous_traction(flat: Tensor, ox: Tensor, oy: Tensor, wn: Tensor, qdots: Tensor, v: Tensor, mu: Tensor,
                     elements: Tensor, sigma_prime: float) -> Tensor:
    """f_k^visc = mu (G_k + G_k^T) e_k [B, S, 2] (N per unit depth, in v.dtype) on the sampled
    cells (``surface_samples``): G_k (G_ab = dv_a / dx_b) the fit of the fluid velocity v
    [B, 2, H, W] (cell centres, m/s) relative to the node velocities qdots [B, S, 2] through the
    node (``gradient_coefficients``); e_k the surface elements [B, S, 2] (m); mu [B] or scalar
    (Pa s)."""
    kx, ky = gradient_coefficients(wn, ox, oy, sigma_prime)
    u = qdots.to(v.dtype)
    grad = [[None, None], [None, None]]
    for a in range(2):
        dv = gather_cells(v[:, a : a + 1], flat) - u[..., a, None]
        grad[a] = [(kx * dv).sum(-1), (ky * dv).sum(-1)]
    e = elements.to(v.dtype)
    shear = grad[0][1] + grad[1][0]
    f = torch.stack([2 * grad[0][0] * e[..., 0] + shear * e[..., 1],
                     shear * e[..., 0] + 2 * grad[1][1] * e[..., 1]], dim=-1)
    return torch.as_tensor(mu, dtype=v.dtype, device=v.device).reshape(-1, 1, 1) * f


def surface_elements(qs: Tensor, area: str = CHORD) -> Tensor:
    """Outward surface element of each node, [B, S, 2] m: a_k ("chord") or l_k n_k ("paper")."""
    if area == CHORD:
        return area_vectors(qs)
    if area == PAPER:
        l_k, n_k = surface_geometry(qs)
        return l_k.unsqueeze(-1) * n_k
    raise ValueError(f"area must be 'chord' or 'paper', got {area!r}")


def ibm_force(qs: Tensor, p: Tensor, mask: Tensor, grid: Grid, sigma_prime: float = 6.25e-6,
              weight: str = OUTSIDE, fit: str = LINEAR, area: str = CHORD,
              viscous: tuple[Tensor, Tensor, Tensor | float] | None = None, surface: Tensor | None = None,
              wall: tuple[Tensor, Tensor | float] | None = None) -> Tensor:
    """IBM force on every surface node, [B, S, 2] N (per unit depth): the pressure force
    f_k = -e_k p_k and, with ``viscous`` = (qdots [B, S, 2] m/s, fluid velocity at the cell
    centres [B, 2, H, W] m/s, mu [B] or scalar Pa s), the viscous traction mu (G_k + G_k^T) e_k
    (module docstring), both from one sampling of the cells around each node.

    qs: surface polyline [B, S, 2] (ccw, m), or with ``surface`` [S] (long) the mesh nodes [B, N, 2]
    of which those make the polyline; p: pressure [B, 1, H, W] (Pa); mask: b [B, 1, H, W] (of the
    fish, or fish + walls: wall cells are then not sampled either).
    sigma_prime (m^2), weight ("outside" | "fluid" | "body" | "none"), fit ("linear" | "mean"),
    area ("chord" | "paper"): see the module docstring; the traction needs "outside".
    wall: for fit "wall", (the nodes' accelerations [B, S, 2] m/s^2 (of the polyline's nodes, or
    of all mesh nodes with ``surface``), rho [B] or scalar kg/m^3): the imposed slope -rho a.n.
    Differentiable in every tensor input; sampling runs in p.dtype, the result is in qs.dtype.
    On the CPU the defaults (weight "outside", area "chord", no traction; any fit, the wall's with
    a constant rho) run compiled, in float64 (fishsim.coupling.kernels.OutsidePressureForce);
    ``torch_ibm_force`` is the reference.
    """
    constant_rho = wall is None or not (torch.is_tensor(wall[1]) and wall[1].requires_grad)
    if qs.device.type == "cpu" and weight == OUTSIDE and area == CHORD and viscous is None and constant_rho:
        from fishsim.coupling import kernels  # the same formulas, compiled

        fits = {MEAN: kernels.MEAN_FIT, LINEAR: kernels.LINEAR_FIT, WALL: kernels.WALL_FIT}
        if fit not in fits:
            raise ValueError(f"fit must be 'mean', 'linear' or 'wall', got {fit!r}")
        acc, rho = wall if fit == WALL and wall is not None else (None, 0.0)    # the kernel checks the pair
        return kernels.OutsidePressureForce.apply(qs, p, mask, None if surface is None else surface.numpy(),
                                                  OUTSIDE_MASK, grid.dx, sigma_prime,
                                                  kernel_radius(sigma_prime, grid.dx), fits[fit], acc, rho)
    if surface is not None:
        qs = qs[:, surface]
        wall = None if wall is None else (wall[0][:, surface], wall[1])
    return torch_ibm_force(qs, p, mask, grid, sigma_prime, weight, fit, area, viscous, wall)


def torch_ibm_force(qs: Tensor, p: Tensor, mask: Tensor, grid: Grid, sigma_prime: float = 6.25e-6,
                    weight: str = OUTSIDE, fit: str = LINEAR, area: str = CHORD,
                    viscous: tuple[Tensor, Tensor, Tensor | float] | None = None,
                    wall: tuple[Tensor, Tensor | float] | None = None) -> Tensor:
    """``ibm_force`` in torch operations (any device, every option)."""
    if (viscous is not None or fit == WALL) and weight != OUTSIDE:
        raise ValueError(f"the viscous traction and the 'wall' fit sample the cells beyond the band: weight 'outside', "
                         f"got {weight!r}")
    if fit == WALL and wall is None:
        raise ValueError("fit 'wall' needs wall=(the nodes' accelerations, rho)")
    elements = surface_elements(qs, area)
    flat, ox, oy, wn = surface_samples(qs, mask, grid, sigma_prime, weight, p.dtype,
                                       elements if area == CHORD else None)
    normal, dp_dn = None, None
    if fit == WALL:
        normal = (elements / elements.norm(dim=-1, keepdim=True)).to(p.dtype)
        rho = torch.as_tensor(wall[1], dtype=p.dtype, device=p.device).reshape(-1, 1)
        dp_dn = -rho * (wall[0].to(p.dtype) * normal).sum(-1)
    p_k = fit_at_node(gather_cells(p, flat), wn, ox, oy, sigma_prime, fit, normal, dp_dn)
    f = -p_k.unsqueeze(-1) * elements.to(p.dtype)
    if viscous is not None:
        qdots, v, mu = viscous
        f = f + viscous_traction(flat, ox, oy, wn, qdots, v.to(p.dtype), mu, elements, sigma_prime)
    return f.to(qs.dtype)
