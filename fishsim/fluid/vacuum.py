"""The vacuum (``fluid=none``): no fluid, behind the same FluidModel contract as the fluids, so
the rollout, its states and checkpoints never hold a missing fluid."""

from __future__ import annotations

import torch

from fishsim.fields import Boundary, FluidParams, FluidState, Grid


class Vacuum:
    """No fluid: its state holds no field (a and p are [B, 0] tensors, so per-sample selection,
    checkpointing and device moves treat it like any state), its step returns the state
    unchanged, and it exerts no force (``exerts_force`` False: the rollout skips the coupling,
    whose mask would be empty and whose force zero). ``grid``: the tank's grid, kept for callers
    that describe the tank; nothing is computed on it."""

    exerts_force = False
    threads_per_sample = False

    def __init__(self, grid: Grid):
        self.grid = grid

    def initial_state(self, batch: int, device=None, dtype=torch.float32) -> FluidState:
        empty = torch.zeros(batch, 0, device=device, dtype=dtype)
        return FluidState(a=empty, p=empty)

    def step(self, state: FluidState, boundary: Boundary, params: FluidParams,
             start: FluidState | None = None) -> FluidState:
        return state
