"""HydroNet settings that the CLI's config (``fishsim.config``) needs without torch, for the
commands' help: the pressures a ``HydroNetFluid`` can give (unet.py; "recovered" is computed by
fishsim/fluid/pressure.py) and ``EvalConfig``, the held-out evaluation's (evaluate.py).
"""

from __future__ import annotations

from dataclasses import dataclass, field

RECOVERED, NETWORK = "recovered", "network"
PRESSURES = (RECOVERED, NETWORK)


@dataclass(frozen=True)
class EvalConfig:
    """Held-out scenes and protocol (SI units; see evaluate.py's docstring)."""

    speeds: list[float] = field(default_factory=lambda: [0.1, 0.2, 0.3])
    frequencies: list[float] = field(default_factory=lambda: [3.0, 5.0, 7.0])
    radius: float = 0.01
    fish_amp: float = 0.06
    warmup: int = 50
    steps: int = 100
    rho: float = 50.0
    mu: float = 1.25e-4
    h: float = 0.01
    H: int = 100
    W: int = 300
    dx: float = 2.5e-3
    wall_y: int = 3
    wall_x: int = 5
    still_steps: int = 300
    energy_steps: int = 150
    energy_frequency: float = 5.0
