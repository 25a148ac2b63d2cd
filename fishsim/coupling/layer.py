"""The coupling layer: solid -> fluid (b, v_d) and fluid -> solid (f_ext) (docs/physics.md section 7).

    solid_to_fluid(q, qdot, surface, grid, cfg) -> Boundary(b, v_d)     step 1 of the coupled step
    fish_band(q, qdot, surface, grid, cfg) -> (band, b, v_d on its cells); on_grid(that, grid)
                                                                        the same in two parts
    with_walls(q, qdot, surface, grid, cfg, walls, scale) -> Boundary  step 1 with the tank's walls
    fluid_to_solid(q, p, boundary, surface, grid, cfg, step) -> f_ext   step 3 (sampled pressure)
    exchange_to_solid(q, cell_force, surface, grid, cfg, step) -> f_ext
                                                                        step 3 (momentum exchange)

Only the fish is described here.  The rollout adds the tank walls (mask b_wall, velocity v_wall)
and combines them as a union of soft sets:

    b_total = 1 - (1 - b_fish)(1 - b_wall)    (= max(b_fish, b_wall) where they do not overlap)
    v_total = (b_fish v_fish + b_wall v_wall) / (b_fish + b_wall)     (fishsim.fields.union)

and may pass the combined Boundary to ``fluid_to_solid`` (wall cells are then not sampled by the
default fluid-side IBM weight either).  ``with_walls`` forms the union on the fish's band of cells only.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from fishsim.coupling.band import SurfaceBand, band_margin, nearest_count, scatter_band, surface_band
from fishsim.coupling.config import HARMONIC, SEGMENT, CouplingConfig
from fishsim.coupling.exchange import spread_to_surface
from fishsim.coupling.forces import burn_in_scale, fext_from_surface
from fishsim.coupling.ibm import ibm_force
from fishsim.coupling.mask import band_values
from fishsim.fields import Boundary, Grid, union


def surface_index(surface, device) -> Tensor:
    """The surface polyline's node indices [S] as a long tensor on ``device``."""
    if isinstance(surface, np.ndarray):
        surface = torch.from_numpy(surface)
    return surface.to(device=device, dtype=torch.long)


def solid_to_fluid(q: Tensor, qdot: Tensor, surface, grid: Grid, cfg: CouplingConfig,
                   dtype: torch.dtype = torch.float32) -> Boundary:
    """The fish as a fluid boundary: mask b [B, 1, H, W] and v_d [B, 2, H, W] in ``dtype``.

    v_d is the solid's velocity field on the band of cells around the body (the softmin-weighted
    surface velocity, without the paper's factor b: the fluid models apply the mask themselves,
    e.g. the Brinkman blend (1 - b) v + b v_d).

    q, qdot: world-frame node positions (m) and velocities (m/s) [B, N, 2]; surface: [S] mesh
    indices of the ccw surface polyline (FishMesh.surface).  Differentiable in q and qdot.
    (The rollout unites the fish with the walls: ``with_walls``.)
    """
    return on_grid(fish_band(q, qdot, surface, grid, cfg, dtype), grid)


def fish_band(q: Tensor, qdot: Tensor, surface, grid: Grid, cfg: CouplingConfig,
              dtype: torch.dtype = torch.float32) -> tuple[SurfaceBand, Tensor, Tensor]:
    """``solid_to_fluid`` on the band of cells around the body (fishsim.coupling.band), the only
    cells where b and v_d are not zero: (band, b [B, 1, P], v_d [B, 2, P])."""
    idx = surface_index(surface, q.device)
    qs, qdots = q[:, idx], qdot[:, idx]
    band = surface_band(qs, grid, band_margin(cfg.sigma, grid.dx), cfg.k_nearest, cfg.distance, cfg.sigma)
    return band, *band_values(qs, qdots, band, cfg.xi, cfg.sigma, cfg.tau, cfg.mean, dtype)


def on_grid(fish: tuple[SurfaceBand, Tensor, Tensor], grid: Grid) -> Boundary:
    """``fish_band``'s fish as grid fields [B, ., H, W] (zero off its band's cells)."""
    band, mask, velocity = fish
    return Boundary(mask=scatter_band(mask, band, grid), velocity=scatter_band(velocity, band, grid))


def with_walls(q: Tensor, qdot: Tensor, surface, grid: Grid, cfg: CouplingConfig, walls: Boundary,
               scale: Tensor | None = None, fish: tuple[SurfaceBand, Tensor, Tensor] | None = None) -> Boundary:
    """The fish united with the tank's ``walls`` on ``grid``, a Boundary [B, ., H, W] in the walls' dtype
    whose walls' velocity is multiplied by ``scale`` [B] (a swim tunnel's -U; None: 1):
    ``union(solid_to_fluid(...), walls)`` (module docstring), formed on the fish's band of cells
    only (~1,300 of 30,000 at B = 1). Elsewhere b_fish = 0 and the union is the walls themselves
    as ``united_with_nothing(walls)`` gives them: pass them so, as constants. On the CPU in one
    compiled call from the nodes (kernels.FishOnGrid), elsewhere ``fish_band`` and
    ``torch_band_union``; ``fish``: ``fish_band``'s fish in the walls' dtype if the caller has it
    already (it is then united as it is, not selected again). Differentiable in q, qdot and
    ``scale``."""
    scale = q.new_ones(q.shape[0]) if scale is None else scale
    if fish is not None or q.device.type != "cpu":
        dtype = walls.mask.dtype
        fish = fish_band(q, qdot, surface, grid, cfg, dtype) if fish is None else fish
        return torch_band_union(*fish, grid, walls, scale.to(dtype))
    from fishsim.coupling.kernels import NEGLIGIBLE, BandSettings, FishOnGrid

    index = surface_index(surface, q.device).numpy()
    k, truncated = nearest_count(cfg.k_nearest, len(index))
    settings = BandSettings(grid.dx, grid.H, grid.W, band_margin(cfg.sigma, grid.dx), k, cfg.distance == SEGMENT,
                            NEGLIGIBLE * cfg.sigma, cfg.xi, cfg.sigma, cfg.tau, cfg.mean == HARMONIC, truncated)
    return Boundary(*FishOnGrid.apply(q, qdot, scale, walls.mask, walls.velocity, index, settings))


def torch_band_union(band: SurfaceBand, mask: Tensor, velocity: Tensor, grid: Grid, walls: Boundary,
                     scale: Tensor) -> Boundary:
    """``with_walls``'s union in torch operations from ``fish_band``'s fish (CUDA; the reference of
    kernels.FishOnGrid)."""
    B, index = mask.shape[0], band.flat.unsqueeze(1)
    wall_mask = walls.mask.expand(B, -1, -1, -1).flatten(2)                 # [B, 1, H W]
    wall_velocity = (walls.velocity * scale.view(B, 1, 1, 1)).flatten(2)    # [B, 2, H W]
    pair = index.expand(-1, 2, -1)
    joint = union(Boundary(mask, velocity), Boundary(wall_mask.gather(2, index), wall_velocity.gather(2, pair)))
    return Boundary(mask=wall_mask.scatter(2, index, joint.mask).view(B, 1, grid.H, grid.W),
                    velocity=wall_velocity.scatter(2, pair, joint.velocity).view(B, 2, grid.H, grid.W))


def united_with_nothing(walls: Boundary) -> Boundary:
    """``union(nothing, walls)``: the walls as a union leaves them where no body is (b = 1 - (1 -
    b_wall), v_d = 0 where b_wall = 0); ``solid_to_fluid``'s walls."""
    empty = torch.zeros_like(walls.mask)
    return union(Boundary(empty, torch.zeros_like(walls.velocity)), walls)


def fluid_to_solid(q: Tensor, p: Tensor, boundary: Boundary, surface, grid: Grid,
                   cfg: CouplingConfig, step: int | None = None, mass: Tensor | None = None,
                   viscous: tuple[Tensor, Tensor, Tensor] | None = None,
                   wall: tuple[Tensor, Tensor] | None = None) -> Tensor:
    """External hydrodynamic force on every mesh node, f_ext [B, N, 2] N (per unit depth).

    q: node positions [B, N, 2] (m); p: pressure [B, 1, H, W] (Pa); boundary: the mask used to
    weight the IBM samples; step: time-step index t for the burn-in (None: no burn-in);
    mass: lumped node masses [N], how ``force_mode=average`` shares the total (None: equally);
    viscous: (qdot [B, N, 2] m/s, the fluid velocity at the cell centres [B, 2, H, W] m/s,
    mu [B] Pa s) to add the viscous traction (ibm.ibm_force; the caller passes it with
    ``cfg.viscous``), None for the pressure alone; wall: (the nodes' accelerations [B, N, 2]
    m/s^2, rho [B] kg/m^3) for ``cfg.ibm_fit`` "wall" (ibm.ibm_force).
    Result in q.dtype; differentiable in q, p, boundary.mask, the viscous inputs and the wall's
    accelerations.
    """
    idx = surface_index(surface, q.device)
    if viscous is not None:
        qdot, v, mu = viscous
        viscous = (qdot[:, idx], v, mu)
    f = ibm_force(q, p, boundary.mask, grid, cfg.sigma_prime, cfg.ibm_weight, cfg.ibm_fit, cfg.ibm_area, viscous,
                  surface=idx, wall=wall)
    scale = 1.0 if step is None else burn_in_scale(step, cfg.n_burn_in)
    return fext_from_surface(f, idx, q.shape[1], cfg.force_mode, cfg.fix_lateral, scale, mass)


def exchange_to_solid(q: Tensor, cell_force: Tensor, surface, grid: Grid, cfg: CouplingConfig,
                      step: int | None = None, mass: Tensor | None = None) -> Tensor:
    """External hydrodynamic force on every mesh node by momentum exchange, f_ext [B, N, 2] N.

    cell_force: the fluid step's force on the fish per cell [B, 2, H, W] N/m
    (``StepDiagnostics.cell_forces`` with the fish's ``body_share``). Spread onto the surface
    nodes (fishsim.coupling.exchange), then burn-in, force_mode and fix_lateral as
    ``fluid_to_solid``. Result in q.dtype; differentiable.
    """
    idx = surface_index(surface, q.device)
    f, _ = spread_to_surface(q[:, idx], cell_force, grid, cfg.sigma_spread)
    scale = 1.0 if step is None else burn_in_scale(step, cfg.n_burn_in)
    return fext_from_surface(f, idx, q.shape[1], cfg.force_mode, cfg.fix_lateral, scale, mass)
