"""What an optimisation varies and maximises: the parameters and objectives with their units,
and their settings (``ParamSpec``, ``ObjectiveConfig``). Plain values, no torch, so the CLI's
config (``fishsim.config``) imports them for ``fishsim optimize --help``; problem.py defines the
objectives and evaluates them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from fishsim.errors import ConfigError

PARAMETERS = {"frequency": "Hz", "amplitude": "1/m", "wave_number": "rad/m", "youngs_modulus": "Pa"}
OBJECTIVES = {"thrust": "N s/m", "distance": "m", "speed": "m/s", "cost_of_transport": "m^2/J"}
FREE_ONLY = ("distance", "speed", "cost_of_transport")


@dataclass
class ParamSpec:
    """One optimised parameter: bounds [lower, upper] in its unit (PARAMETERS), an optional log
    scale, and its start (null: the episode config's value)."""

    lower: float
    upper: float
    log: bool = False
    init: float | None = None

    def check(self, name: str) -> None:
        if name not in PARAMETERS:
            raise ConfigError(f"unknown optimisation parameter '{name}' (choose from {', '.join(PARAMETERS)})")
        lo, hi = self.lower, self.upper
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ConfigError(f"params.{name}: bounds [{lo}, {hi}] are empty or inverted (need lower < upper)")
        if self.log and lo <= 0:
            raise ConfigError(f"params.{name}: a log scale needs lower > 0 (got {lo})")
        if self.init is not None and not lo <= self.init <= hi:
            raise ConfigError(f"params.{name}.init = {self.init} lies outside [{lo}, {hi}]")


@dataclass
class ObjectiveConfig:
    """The objective (problem.py's docstring): name in OBJECTIVES; window: the speed's averaging
    window in s (null: the episode's second half)."""

    name: str = "distance"
    window: float | None = None

    def check(self, hold_x: bool) -> None:
        if self.name not in OBJECTIVES:
            raise ConfigError(f"unknown objective '{self.name}' (choose from {', '.join(OBJECTIVES)})")
        if hold_x and self.name in FREE_ONLY:
            raise ConfigError(f"objective {self.name} needs a free fish, but hold_x=true holds it in x "
                              "(use objective=thrust, or hold_x=false)")
        if self.window is not None and not self.window > 0:
            raise ConfigError(f"objective.window must be > 0 s or null (got {self.window})")
