"""The ground floor: the grid and the fields the solid's coupling and the fluids exchange (Grid,
Boundary, FluidState, FluidParams), and the one fluid contract (FluidModel) shared by HydroNet
and the numerical solver. It imports nothing from fishsim, so coupling/ and fluid/ both build on it.

Grid and array conventions (docs/physics.md section 4; all lengths in metres, times in seconds):

* The tank is a box of H x W square cells of side ``dx``; ``x`` runs along the columns
  (index j, the long side), ``y`` along the rows (index i).  Cell (i, j) spans
  ``[j dx, (j+1) dx] x [i dx, (i+1) dx]``; its centre is ``x_ij = ((j+1/2) dx, (i+1/2) dx)``.
* MAC staggering (Wandel et al. 2021), every field a tensor ``[B, C, rows, cols]``:

  ======================  ==================  =====================================
  field                   shape               location of entry [i, j]
  ======================  ==================  =====================================
  vector potential ``a``  ``[B, 1, H+1, W+1]``  vertex ``(j dx, i dx)``
  ``v_x = d a / d y``     ``[B, 1, H, W+1]``    vertical face ``(j dx, (i+1/2) dx)``
  ``v_y = -d a / d x``    ``[B, 1, H+1, W]``    horizontal face ``((j+1/2) dx, i dx)``
  pressure ``p``          ``[B, 1, H, W]``      cell centre
  mask ``b``, ``v_d``     ``[B, 1|2, H, W]``    cell centre; ``v_d`` channels are (v_x, v_y)
  ======================  ==================  =====================================

  so ``v = curl a`` is exactly divergence free and the outermost faces are the box walls.
* Vector channels are ordered (x, y) everywhere in fishsim.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from typing import Protocol, Self, runtime_checkable

import torch
from torch import Tensor


@dataclass(frozen=True)
class Grid:
    """A uniform H x W cell grid with spacing ``dx`` [m] (paper: 100 x 300, dx = 2.5 mm)."""

    H: int = 100
    W: int = 300
    dx: float = 2.5e-3

    @property
    def size(self) -> tuple[float, float]:
        """Physical extent (Lx, Ly) in metres."""
        return self.W * self.dx, self.H * self.dx

    def cell_centres(self, device=None, dtype=torch.float32) -> Tensor:
        """Cell-centre coordinates ``x_ij`` as a tensor [H, W, 2] (x, y) in metres."""
        y = (torch.arange(self.H, device=device, dtype=dtype) + 0.5) * self.dx
        x = (torch.arange(self.W, device=device, dtype=dtype) + 0.5) * self.dx
        yy, xx = torch.meshgrid(y, x, indexing="ij")
        return torch.stack([xx, yy], dim=-1)


@dataclass(frozen=True)
class FluidState:
    """Fluid state at one instant; never mutated by a step.

    a: vector potential (2D stream function) on vertices, [B, 1, H+1, W+1], m^2/s.
    p: pressure at cell centres, [B, 1, H, W], Pa (defined up to a constant; kept mean free).
    solves: not state but a record of the step that made it: the solutions of its iterative
        solves (the numerical fluid's joint stages: [B, 2 n, H, W] potentials, m^2/s), None for
        a model without any. A recomputation of the step passes the state back as ``start``
        (``FluidModel.step``), so that those solves start converged. Left out of ``tensors()``
        and dropped by ``map`` and ``with_tensors``.
    """

    a: Tensor
    p: Tensor
    solves: Tensor | None = None

    def _names(self) -> list[str]:
        return [f.name for f in dataclasses.fields(self) if f.name != "solves" and getattr(self, f.name) is not None]

    def map(self, fn: Callable[[str, Tensor], Tensor]) -> Self:
        """The same kind of state with ``fn(name, tensor)`` applied to each of its tensors (a, p
        and a refined state's fine_a): per-sample selection, slicing, device moves."""
        return dataclasses.replace(self, solves=None, **{name: fn(name, getattr(self, name)) for name in self._names()})

    def tensors(self) -> tuple[Tensor, ...]:
        """Its tensors (a, p, a refined state's fine_a; fields that are None left out), the form
        a checkpoint segment passes; ``with_tensors`` rebuilds the state."""
        return tuple(getattr(self, name) for name in self._names())

    def with_tensors(self, tensors) -> Self:
        """The same kind of state with its tensors replaced by ``tensors`` (``tensors()``'s order)."""
        return dataclasses.replace(self, solves=None, **dict(zip(self._names(), tensors, strict=True)))


@dataclass(frozen=True)
class RefinedState(FluidState):
    """A ``FluidState`` on the r = 1 grid that also carries the potential of a refined solver's
    fine grid (``fine_a`` [B, 1, rH+1, rW+1], m^2/s), so successive steps keep the fine-scale
    flow (fishsim.fluid.numerical); the rollout carries it across checkpoint segments."""

    fine_a: Tensor | None = None


@dataclass(frozen=True)
class Boundary:
    """Solid/wall description for one fluid step, given per cell.

    mask: soft boundary mask b in [0, 1], [B, 1, H, W]; 1 = solid or wall, 0 = fluid.
    velocity: boundary velocity v_d, [B, 2, H, W] (v_x, v_y) in m/s: the velocity of the solid
        itself (not multiplied by the mask), meaningful where mask > 0; fluid models weight it
        by the mask (Brinkman blend (1 - b) v + b v_d, HydroNet's b v_d input channel).
    """

    mask: Tensor
    velocity: Tensor


MASK_FLOOR = 1e-12
"""The smallest mask value divided by (union's b1 + b2, a body's share of a mask): below it a mask
is negligible (b v_d < 1e-12 |v|), and dividing by a subnormal soft-mask tail would overflow the
quotient's derivative -num / w^2 to inf (NaN gradients)."""


def union(first: Boundary, second: Boundary) -> Boundary:
    """Two boundaries in one: b = 1 - (1 - b1)(1 - b2); v_d = (b1 v1 + b2 v2) / max(b1 + b2,
    MASK_FLOOR), the mask-weighted mean wherever either mask is not negligible (every consumer
    reads v_d as b v_d)."""
    b1, b2 = first.mask, second.mask
    b = 1 - (1 - b1) * (1 - b2)
    vd = (b1 * first.velocity + b2 * second.velocity) / (b1 + b2).clamp_min(MASK_FLOOR)
    return Boundary(mask=b, velocity=vd)


def all_finite(*tensors: Tensor) -> bool:
    """Whether every entry of the tensors is finite, read from each one's sum (accumulated in at
    least float32; detached, so autograd keeps nothing): a NaN or an infinity makes the sum
    non-finite, and a sum that overflows (entries ~1e34 on the 100 x 300 grid) is a blow-up as
    well. One reduction, 11 us on a 100 x 300 field on one thread, where isfinite's mask and its
    all() take 80 us."""
    return all(bool(torch.isfinite(x.detach().sum(dtype=torch.float32 if x.element_size() < 4 else None)))
               for x in tensors)


@dataclass(frozen=True)
class FluidParams:
    """Physical parameters of one step.

    rho: fluid density [B] (kg/m^3, per unit depth in 2D), paper default 50.
    mu: dynamic viscosity [B] (Pa s), paper default 0.125e-3.
    h: time step (s), paper default 0.01.
    """

    rho: Tensor
    mu: Tensor
    h: float = 0.01


@runtime_checkable
class FluidModel(Protocol):
    """Advances the fluid one time step: ``(a_t, p_t, b_t, v_d,t) -> (a_t+1, p_t+1)``.

    Implemented by ``fishsim.fluid.numerical.NumericalFluid``,
    ``fishsim.fluid.hydronet.HydroNetFluid`` and ``fishsim.fluid.vacuum.Vacuum`` (no fluid);
    callers never branch on which they hold, only on ``exerts_force`` (and, for speed,
    ``threads_per_sample``).
    ``step`` is differentiable with torch autograd and never mutates its inputs.
    """

    grid: Grid
    exerts_force: bool  # False only for the vacuum (fishsim.fluid.vacuum): no coupling needed
    threads_per_sample: bool  # its step spreads one sample over torch's threads (HydroNet's convolutions)

    def initial_state(self, batch: int, device=None, dtype=torch.float32) -> FluidState:
        """Fluid at rest: a = 0, p = 0."""
        ...

    def step(self, state: FluidState, boundary: Boundary, params: FluidParams,
             start: FluidState | None = None) -> FluidState:
        """Return the state one time step ``params.h`` later. ``start``: what this step returned
        before from the same inputs (a checkpoint recomputation passes the forward pass's
        result), the start of the model's iterative solves (HydroNet's pressure recovery from its
        p, the numerical fluid's joint stages from its ``solves``); it changes the result only
        within the solvers' tolerance."""
        ...


GRADIENT_FREE_WORK: ContextVar[int] = ContextVar("gradient_free_work", default=0)
"""The fish-frames (batch x frames) of the gradient-free rollout now running, 0 in any other
context (a differentiable rollout, its checkpointed forward and recomputation included). A fluid
model may use it to run a faster form of its step whose results differ from the differentiable
one's by round-off, when the work repays its set-up (HydroNet's compiled network)."""


@contextmanager
def gradient_free(fish_frames: int) -> Iterator[None]:
    """Mark the block as a rollout of ``fish_frames`` fish-frames that nothing differentiates
    (``GRADIENT_FREE_WORK``)."""
    token = GRADIENT_FREE_WORK.set(fish_frames)
    try:
        yield
    finally:
        GRADIENT_FREE_WORK.reset(token)


def rest_state(grid: Grid, batch: int, device=None, dtype=torch.float32) -> FluidState:
    """Fluid at rest on ``grid``: a = 0 [B, 1, H+1, W+1], p = 0 [B, 1, H, W]."""
    return FluidState(
        a=torch.zeros(batch, 1, grid.H + 1, grid.W + 1, device=device, dtype=dtype),
        p=torch.zeros(batch, 1, grid.H, grid.W, device=device, dtype=dtype),
    )
