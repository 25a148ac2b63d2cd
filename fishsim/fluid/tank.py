"""The tank the fluid fills (docs/physics.md section 4): its grid, its walls and the inflow at its
ends, as one config (``TankConfig``, the ``tank`` config group) that simulate, optimize and
validate share. Torch-free, so the CLI's help can import it; ``fishsim.fluid.factory`` builds
the walls from it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

from fishsim.errors import ConfigError

if TYPE_CHECKING:
    from fishsim.fields import Grid


@dataclass
class TankConfig:
    """A box of H x W square cells of side dx with solid wall bands and an optional inflow.

    H, W: cells along y (rows) and x (columns); the paper's 100 x 300.  dx: cell size, m (2.5 mm).
    wall_y, wall_x: thickness of the wall bands in cells (bottom/top, left/right).
    inflow: x-velocity (m/s) imposed in the left and right bands (0: a closed tank; a channel
        otherwise, inflow equal to outflow; ``fishsim.fluid.grid.channel``).
    """

    H: int = 100
    W: int = 300
    dx: float = 2.5e-3
    wall_y: int = 3
    wall_x: int = 5
    inflow: float = 0.0

    @property
    def size(self) -> tuple[float, float]:
        """(length along x, height along y) in m."""
        return self.W * self.dx, self.H * self.dx

    @property
    def centre(self) -> tuple[float, float]:
        """The box's centre (x, y) in m."""
        length, height = self.size
        return length / 2, height / 2

    @property
    def grid(self) -> Grid:
        """The tank's ``Grid`` (imported on use: this module stays torch-free)."""
        from fishsim.fields import Grid

        return Grid(self.H, self.W, self.dx)

    def validate(self) -> None:
        if not (self.dx is not None and math.isfinite(self.dx) and self.dx > 0):
            raise ConfigError(f"tank.dx must be > 0 (got {self.dx})")
        if not (self.H >= 16 and self.W >= 16):
            raise ConfigError(f"the tank must be at least 16 x 16 cells (got tank.H={self.H}, tank.W={self.W})")
        if not (0 <= self.wall_y < self.H // 4 and 0 <= self.wall_x < self.W // 4):
            raise ConfigError(f"tank.wall_y / tank.wall_x must be >= 0 and under a quarter of the tank "
                              f"(got {self.wall_y}, {self.wall_x} on {self.H} x {self.W})")
        if not math.isfinite(self.inflow):
            raise ConfigError(f"tank.inflow must be finite (got {self.inflow})")
