"""Build the fluid model and the tank a config asks for (the only place that branches on it)."""

from __future__ import annotations

from typing import Optional

import torch

from fishsim.fluid.base import Boundary, FluidModel, FluidParams, Grid
from fishsim.fluid.grid import channel, closed_tank


def make_grid(cfg) -> Grid:
    """The tank grid of a ``FluidConfig``."""
    return Grid(H=cfg.H, W=cfg.W, dx=cfg.dx)


def make_fluid(cfg) -> Optional[FluidModel]:
    """The ``FluidModel`` of a ``FluidConfig`` (None for ``model=none``, the vacuum)."""
    if cfg.model == "none":
        return None
    if cfg.model == "numerical":
        from fishsim.fluid.numerical import NumericalFluid

        return NumericalFluid(make_grid(cfg), refinement=cfg.refinement)
    raise ValueError(f"unknown fluid model {cfg.model!r}")


def make_tank(cfg, device=None, dtype=torch.float32) -> Boundary:
    """The tank's walls [1, ., H, W]: closed, or a channel with ``cfg.inflow`` m/s at the ends."""
    grid = make_grid(cfg)
    if cfg.inflow != 0.0:
        return channel(grid, cfg.inflow, cfg.wall_y, cfg.wall_x, 1, device, dtype)
    return closed_tank(grid, cfg.wall_y, cfg.wall_x, 1, device, dtype)


def fluid_params(cfg, batch: int, h: float, device=None, dtype=torch.float32) -> FluidParams:
    """rho, mu as [B] tensors and the time step h."""
    full = lambda v: torch.full((batch,), float(v), device=device, dtype=dtype)
    return FluidParams(rho=full(cfg.rho), mu=full(cfg.mu), h=h)
