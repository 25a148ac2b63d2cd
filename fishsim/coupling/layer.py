"""The coupling layer: solid -> fluid (b, v_d) and fluid -> solid (f_ext) (docs/physics.md section 7).

    solid_to_fluid(q, qdot, surface, grid, cfg) -> Boundary(b, v_d)     step 1 of the coupled step
    fluid_to_solid(q, p, boundary, surface, grid, cfg, step) -> f_ext   step 3 (sampled pressure)
    exchange_to_solid(q, cell_force, surface, grid, cfg, step) -> f_ext
                                                                        step 3 (momentum exchange)

Only the fish is described here.  The rollout adds the tank walls (mask b_wall, velocity v_wall)
and combines them as a union of soft sets:

    b_total = 1 - (1 - b_fish)(1 - b_wall)    (= max(b_fish, b_wall) where they do not overlap)
    v_total = (b_fish v_fish + b_wall v_wall) / (b_fish + b_wall)     (fishsim.fluid.grid.union)

and may pass the combined Boundary to ``fluid_to_solid`` (wall cells are then not sampled by the
default fluid-side IBM weight either).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from fishsim.coupling.band import NODE, SEGMENT, band_margin, surface_band
from fishsim.coupling.exchange import spread_to_surface
from fishsim.coupling.forces import AVERAGE, PER_NODE, burn_in_scale, fext_from_surface
from fishsim.coupling.ibm import BODY, CHORD, FLUID, LINEAR, MEAN, NONE, PAPER, ibm_force
from fishsim.coupling.mask import ARITHMETIC, HARMONIC, boundary_velocity, soft_mask
from fishsim.errors import ConfigError
from fishsim.fluid.base import Boundary, Grid

_CHOICES = {
    "distance": (SEGMENT, NODE),
    "mean": (HARMONIC, ARITHMETIC),
    "ibm_weight": (FLUID, BODY, NONE),
    "ibm_fit": (LINEAR, MEAN),
    "ibm_area": (CHORD, PAPER),
    "force_mode": (PER_NODE, AVERAGE),
    "force": ("pressure", "exchange"),
}


@dataclass(frozen=True)
class CouplingConfig:
    """Coupling parameters (SI units; the reasons for each default are in mask.py / ibm.py).

    xi: soft-min temperature of the mask distance, m^2 (paper 5e-7).
    sigma: mask softness, m^2 (paper values 5e-9, 5e-7, 5e-5): b goes 0.05 -> 0.95 over one
        2.5 mm cell at 5e-7.
    tau: soft-min temperature of the boundary velocity, m^2 (= xi: nearest surface point).
    sigma_prime: IBM Gaussian variance, m^2 (dx^2 = 6.25e-6: one-cell standard deviation).
    distance: "segment" (exact distance to the polyline, no scallops) | "node" (paper).
    mean: soft-min of the squared distances, "harmonic" (0 on the surface) | "arithmetic" (paper).
    ibm_weight: cells sampled for the pressure, "fluid" (1 - b) | "body" (b, paper) | "none".
    ibm_fit: "linear" (plane fit evaluated at the node) | "mean" (paper's weighted mean).
    ibm_area: "chord" (area vectors summing to 0) | "paper" (l_k n_k).
    force: "pressure" (the IBM-sampled pressure, the paper's; any fluid) | "exchange" (the
        momentum the numerical fluid's penalization exchanges with the body, viscous stress
        included; fishsim.coupling.exchange).
    sigma_spread: variance of the kernel spreading the exchanged force onto the surface nodes,
        m^2 (default (1.5 dx)^2 = 1.40625e-5; exchange.py).
    force_mode: "per_node" (free swimming) | "average" (paper's optimisation mode).
    fix_lateral: drop the y force ("x-axis fixed", paper Sec. 4.4).
    n_burn_in: forces are scaled by min(1, t / n_burn_in) (paper Sec. 3.4); our default 20
        steps = 0.2 s, the controller's activation ramp t_a.
    added_mass_ratio: the added-mass stabilisation's M^ / M (fishsim.coupling.added_mass);
        0 switches it off (plain explicit coupling, unstable for this light fish at the
        calibrated stroke).  Stable for (M_a - M) / 2 <= M^ <= M + M_a in every mode.
    k_nearest: surface elements kept per cell; on a bent 250-node fish K = 12 reproduces the
        all-segment mask and v_d to 1e-15 (K = 8: 5e-10, K = 4: 0.1 m/s in v_d).
    """

    xi: float = 5e-7
    sigma: float = 5e-7
    tau: float = 5e-7
    sigma_prime: float = 6.25e-6
    distance: str = SEGMENT
    mean: str = HARMONIC
    ibm_weight: str = FLUID
    ibm_fit: str = LINEAR
    ibm_area: str = CHORD
    force: str = "pressure"
    sigma_spread: float = 1.40625e-5
    force_mode: str = PER_NODE
    fix_lateral: bool = False
    n_burn_in: int = 20
    added_mass_ratio: float = 5.0
    k_nearest: int = 12

    def __post_init__(self):
        for name in ("xi", "sigma", "tau", "sigma_prime", "sigma_spread"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"coupling.{name} must be > 0 (m^2), got {getattr(self, name)}")
        for name, allowed in _CHOICES.items():
            if getattr(self, name) not in allowed:
                raise ConfigError(f"coupling.{name} must be one of {allowed}, got {getattr(self, name)!r}")
        if not self.added_mass_ratio >= 0:
            raise ConfigError(f"coupling.added_mass_ratio must be >= 0, got {self.added_mass_ratio}")
        if self.n_burn_in < 0 or self.k_nearest < 1:
            raise ConfigError("coupling.n_burn_in must be >= 0 and coupling.k_nearest >= 1")


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
    """
    idx = surface_index(surface, q.device)
    qs, qdots = q[:, idx], qdot[:, idx]
    band = surface_band(qs, grid, band_margin(cfg.sigma, grid.dx), cfg.k_nearest, cfg.distance)
    mask = soft_mask(qs, grid, cfg.xi, cfg.sigma, cfg.distance, cfg.mean, band, dtype)
    velocity = boundary_velocity(qs, qdots, mask, grid, cfg.tau, cfg.distance, band, weighted=False)
    return Boundary(mask=mask, velocity=velocity)


def fluid_to_solid(q: Tensor, p: Tensor, boundary: Boundary, surface, grid: Grid,
                   cfg: CouplingConfig, step: int | None = None) -> Tensor:
    """External hydrodynamic force on every mesh node, f_ext [B, N, 2] N (per unit depth).

    q: node positions [B, N, 2] (m); p: pressure [B, 1, H, W] (Pa); boundary: the mask used to
    weight the IBM samples; step: time-step index t for the burn-in (None: no burn-in).
    Result in q.dtype; differentiable in q, p and boundary.mask.
    """
    idx = surface_index(surface, q.device)
    f = ibm_force(q[:, idx], p, boundary.mask, grid, cfg.sigma_prime, cfg.ibm_weight,
                  cfg.ibm_fit, cfg.ibm_area)
    scale = 1.0 if step is None else burn_in_scale(step, cfg.n_burn_in)
    return fext_from_surface(f, idx, q.shape[1], cfg.force_mode, cfg.fix_lateral, scale)


def exchange_to_solid(q: Tensor, cell_force: Tensor, surface, grid: Grid, cfg: CouplingConfig,
                      step: int | None = None) -> Tensor:
    """External hydrodynamic force on every mesh node by momentum exchange, f_ext [B, N, 2] N.

    cell_force: the fluid step's force on the fish per cell [B, 2, H, W] N/m
    (``StepDiagnostics.cell_forces`` with the fish's ``body_share``). Spread onto the surface
    nodes (fishsim.coupling.exchange), then burn-in, force_mode and fix_lateral as
    ``fluid_to_solid``. Result in q.dtype; differentiable.
    """
    idx = surface_index(surface, q.device)
    f, _ = spread_to_surface(q[:, idx], cell_force, grid, cfg.sigma_spread)
    scale = 1.0 if step is None else burn_in_scale(step, cfg.n_burn_in)
    return fext_from_surface(f, idx, q.shape[1], cfg.force_mode, cfg.fix_lateral, scale)
