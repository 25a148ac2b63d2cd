"""Small grids and nets so the HydroNet tests run in seconds on 2 cores."""

import pytest
import torch

from fishsim.fields import FluidParams, Grid
from fishsim.fluid.hydronet.config import NetConfig, PoolConfig


@pytest.fixture
def grid() -> Grid:
    return Grid(16, 32, 2.5e-3)


@pytest.fixture
def tiny_net() -> NetConfig:
    return NetConfig(hidden=4, depth=2)


@pytest.fixture
def tiny_pool() -> PoolConfig:
    return PoolConfig(size=6, H=24, W=48, fish_length=(0.06, 0.08), obstacle_cells=(2.0, 4.0), episode_steps=8)


def paper_params(batch: int, rho: float = 50.0, mu: float = 1.25e-4) -> FluidParams:
    return FluidParams(torch.full((batch,), rho), torch.full((batch,), mu), 0.01)
