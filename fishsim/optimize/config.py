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
    """The objective (problem.py's docstring): name in OBJECTIVES; cycles: the speed's averaging
    window, the last ``cycles`` tail beats of the fish's frequency."""

    name: str = "distance"
    cycles: float = 2.0

    def check(self, hold_x: bool) -> None:
        if self.name not in OBJECTIVES:
            raise ConfigError(f"unknown objective '{self.name}' (choose from {', '.join(OBJECTIVES)})")
        if hold_x and self.name in FREE_ONLY:
            raise ConfigError(f"objective {self.name} needs a free fish, but hold_x=true holds it in x "
                              "(use objective=thrust, hold_x=false, or the swim tunnel tunnel=true)")
        if not self.cycles > 0:
            raise ConfigError(f"objective.cycles must be > 0 tail beats (got {self.cycles})")

    def check_window(self, lowest_frequency: float, frames: int, h: float) -> None:
        """The speed's window must fit in the episode at the slowest frequency the fish may have."""
        span = self.cycles / lowest_frequency
        if self.name == "speed" and span > frames * h + 1e-12:
            raise ConfigError(f"objective.cycles={self.cycles:g} at {lowest_frequency:g} Hz spans {span:.3g} s, longer "
                              f"than the {frames * h:.3g} s episode: lower objective.cycles, raise frames or the "
                              "lowest frequency")
