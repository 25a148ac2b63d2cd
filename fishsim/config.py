"""Structured configs: every command's config is a tree of dataclasses, composed by Hydra from
the YAML files in ``fishsim/conf`` and validated here, so an unknown key or an impossible value
fails before any work starts, with one line saying what is wrong.

Each dataclass mirrors the constructor or function it configures; ``validate`` methods check
values that types alone cannot (positivity, ranges) and raise ``ConfigError``.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from importlib import resources
from typing import Any, Optional

from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from fishsim.errors import ConfigError


def _require(cond: bool, msg: str) -> None:
    if not cond:
        raise ConfigError(msg)


def _positive(**values: float) -> None:
    for name, v in values.items():
        _require(v is not None and math.isfinite(v) and v > 0, f"{name} must be > 0 (got {v})")


@dataclass
class FishConfig:
    """The fish body and its mesh (PHYSICS.md section 2); see ``fishsim.mesh.make_fish_mesh``."""

    length: float = 0.2
    profile: str = "kern"
    poly_coeffs: list[float] = field(default_factory=list)
    edge_length: float = 2.0e-3
    min_angle: float = 30.0
    actuator_spacing: float = 4.0e-3
    actuator_x_range: list[float] = field(default_factory=lambda: [0.05, 0.95])
    tail_tip_width: Optional[float] = None
    mesh_file: Optional[str] = None

    def validate(self) -> None:
        _positive(**{"fish.length": self.length, "fish.edge_length": self.edge_length,
                     "fish.actuator_spacing": self.actuator_spacing})
        _require(self.profile in ("kern", "polynomial"),
                 f"fish.profile must be 'kern' or 'polynomial' (got '{self.profile}')")
        _require(0 < self.min_angle <= 33.8,
                 f"fish.min_angle must be in (0, 33.8] degrees, Triangle's limit (got {self.min_angle})")
        _require(self.edge_length < self.length / 10,
                 f"fish.edge_length={self.edge_length} m is too coarse for a {self.length} m fish")
        lo, hi = self.actuator_x_range
        _require(0 <= lo < hi <= 1, f"fish.actuator_x_range must satisfy 0 <= lo < hi <= 1 (got {lo}, {hi})")


@dataclass
class MeshCommandConfig:
    """``fishsim mesh``: mesh the fish, write it and a preview picture."""

    fish: FishConfig = field(default_factory=FishConfig)
    output: str = "fish.vtu"
    preview: bool = True
    out_dir: Optional[str] = None

    def validate(self) -> None:
        self.fish.validate()


ROOTS: dict[str, type] = {"mesh": MeshCommandConfig}


def config_dir() -> str:
    """The shipped config folder (inside the package, so installed wheels find it)."""
    return str(resources.files("fishsim") / "conf")


def load_config(command: str, overrides: list[str] | None = None) -> Any:
    """Compose ``conf/<command>.yaml`` with command-line ``key=value`` overrides, check it
    against the command's structured config and return the validated dataclass instance.

    Raises ConfigError (one line) for an unknown key, a wrong type or an impossible value.
    """
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.errors import HydraException

    overrides = list(overrides or [])
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=config_dir(), version_base="1.3"):
            raw = compose(config_name=command, overrides=overrides)
    except (HydraException, OmegaConfBaseException) as err:
        raise ConfigError(_one_line(err)) from None
    return to_dataclass(command, raw)


def to_dataclass(command: str, raw: Any) -> Any:
    """Merge a composed config into the command's schema, build the dataclasses, validate."""
    schema = OmegaConf.structured(ROOTS[command])
    try:
        merged = OmegaConf.merge(schema, raw)
        cfg = OmegaConf.to_object(merged)
    except OmegaConfBaseException as err:
        raise ConfigError(_one_line(err)) from None
    cfg.validate()
    return cfg


def to_yaml(cfg: Any) -> str:
    """The resolved config as YAML (stored with every output)."""
    return OmegaConf.to_yaml(OmegaConf.structured(cfg))


def _one_line(err: Exception) -> str:
    """Condense an OmegaConf/Hydra error into one line with a hint on how to fix it."""
    text = " ".join(str(err).split()) or type(err).__name__
    unknown = re.search(r"Could not override '([^']+)'", text) or re.search(r"Key '([^']+)' not in", text)
    if unknown and ("not in struct" in text or "Could not override" in text):
        return (f"config error: unknown config key '{unknown.group(1)}' (check the spelling; "
                "`fishsim <command> --help` lists the config groups and keys)")
    for tail in (" full_key:", " Config search path:", " See https:"):
        text = text.split(tail)[0]
    return f"config error: {text.strip()}"
