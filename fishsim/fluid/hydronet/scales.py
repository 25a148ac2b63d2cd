"""Reference scales that make HydroNet work in O(1), grid-sized numbers.

The natural units of a MAC grid with spacing ``dx`` [m] stepped with ``h`` [s] are one cell and one
step (Wandel et al. 2021 train directly in these "grid units"):

    U* = dx / h                  [m/s]     velocity: 1 cell per step (0.25 m/s at 2.5 mm / 0.01 s)
    A* = U* dx = dx^2 / h        [m^2/s]   vector potential: a jump of A* between two vertices is U*
    P* = rho U*^2                [Pa]      pressure, per sample (3.125 Pa at rho = 50)
    R* = rho U* / h = P* / dx    [Pa/m]    momentum residual (1250 Pa/m at rho = 50)
    nu* = mu h / (rho dx^2)      [-]       grid viscosity, the only fluid parameter left once p is
                                          divided by P* (0.004 ... 0.16 for the paper's fluids)

In these units the IMEX Navier-Stokes residual reads dv/dt + (vbar.grad) vbar + grad p - nu* lap vbar,
independent of rho: the network and the loss see the same problem for every fluid except for nu*.
"""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

from fishsim.fields import FluidParams, Grid


@dataclass(frozen=True)
class Scales:
    """Per-sample reference scales; tensors are [B, 1, 1, 1] so they broadcast over fields.

    velocity: U* = dx / h [m/s]; potential: A* = dx^2 / h [m^2/s]; pressure: P* = rho U*^2 [Pa];
    residual: R* = rho U* / h [Pa/m]; nu: nu* = mu h / (rho dx^2) [-].
    """

    velocity: float
    potential: float
    pressure: Tensor
    residual: Tensor
    nu: Tensor


def scales_of(grid: Grid, params: FluidParams) -> Scales:
    """Grid units of ``grid`` and ``params`` (see module docstring); rho, mu are [B]."""
    u = grid.dx / params.h
    rho = params.rho.reshape(-1, 1, 1, 1)
    mu = params.mu.reshape(-1, 1, 1, 1)
    return Scales(
        velocity=u,
        potential=u * grid.dx,
        pressure=rho * u**2,
        residual=rho * u / params.h,
        nu=mu * params.h / (rho * grid.dx**2),
    )
