"""The settings of the studies in swim_study.py (``fishsim validate suite=swim / convergence``):
plain values, no numpy or torch, so the CLI's config (``fishsim.config``) imports them for
``fishsim validate --help``.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

from fishsim.errors import ConfigError

# The fluids the study knows, as `fishsim simulate` overrides.
FLUIDS = {
    "numerical_r2": ["fluid=numerical", "fluid.refinement=2"],
    "numerical": ["fluid=numerical"],
    "hydronet": ["fluid=hydronet"],
    "hydronet_recovered": ["fluid=hydronet", "fluid.pressure=recovered"],
}


@dataclass
class SwimStudyConfig:
    """suite=swim. frequencies (Hz); frames per episode; fluids: names of FLUIDS; reference: the
    one the others are compared with; overrides: more `fishsim simulate` overrides for every run
    (e.g. a smaller tank); hydronet_overrides: more for the HydroNet runs only (``fishsim
    validate`` puts its hydronet node's model_file, bf16, pressure_tol and strict_range before
    them; the fluid's own pressure stays); reuse: the metrics.json of an earlier study with the
    same frequencies, frames and overrides, whose fluids are read from it instead of re-run
    (HydroNet fluids only if their hydronet_overrides match too: another model_file is re-run),
    e.g. to judge a new model against a stored r = 2 reference (10-15 min on a 2-core CPU)."""

    frequencies: list[float] = field(default_factory=lambda: [3.0, 4.0, 5.0, 6.0, 7.0])
    frames: int = 120
    fluids: list[str] = field(default_factory=lambda: ["numerical_r2", "numerical", "hydronet", "hydronet_recovered"])
    reference: str = "numerical_r2"
    overrides: list[str] = field(default_factory=list)
    hydronet_overrides: list[str] = field(default_factory=list)
    reuse: str | None = None

    def validate(self) -> None:
        if len(self.frequencies) < 2 or not all(f > 0 for f in self.frequencies):
            raise ConfigError(f"swim.frequencies needs at least 2 positive values (got {list(self.frequencies)})")
        unknown = [f for f in self.fluids if f not in FLUIDS]
        if unknown or not self.fluids:
            raise ConfigError(f"swim.fluids: unknown {unknown} (choose from {', '.join(FLUIDS)})")
        if self.reference not in self.fluids:
            raise ConfigError(f"swim.reference '{self.reference}' must be one of swim.fluids {list(self.fluids)}")
        if self.frames < 1:
            raise ConfigError(f"swim.frames must be >= 1 (got {self.frames})")


@dataclass
class Knob:
    """One numerical setting of the study: the `fishsim simulate` key, its values from coarse to
    fine (``finer``: "up" when a larger value is finer, "down" when smaller is, e.g. a kernel
    width), the shipped default (its error is reported; None: a setting of another scheme than
    the default's, run with ``base``), an optional episode length of its own (a shorter episode
    for an expensive refinement), the overrides every setting and the limit run with (``base``:
    e.g. the split passes, ``fluid.implicit=false``), and optionally the overrides that run the
    knob's limit directly (``limit``: e.g. infinitely many passes, ``fluid.implicit=true``), the
    default's error against which is reported too."""

    key: str
    values: list[float]
    default: float | None
    finer: str = "up"
    frames: int | None = None
    base: list[str] = field(default_factory=list)
    limit: list[str] = field(default_factory=list)

    def override(self, value: float) -> str:
        """The `fishsim simulate` override of one setting (an integer for the grid's refinement)."""
        return f"{self.key}={int(value)}" if self.key == "fluid.refinement" else f"{self.key}={value:g}"

    def episode_frames(self, value: float, frames: int) -> int:
        """The episode length of one setting: ``frames`` at the default's frame step; the frame
        step's own knob (key ``h``) keeps the episode's duration, frames x default / h."""
        return round(frames * self.default / value) if self.key == "h" else frames

    def check(self, name: str) -> None:
        v = self.values
        if len(v) < 2 or self.finer not in ("up", "down"):
            raise ConfigError(f"convergence.knobs.{name}: give >= 2 values and finer: up | down")
        sign = 1 if self.finer == "up" else -1
        ordered = all(sign * (b - a) > 0 for a, b in itertools.pairwise(v))
        if not ordered:
            raise ConfigError(f"convergence.knobs.{name}.values must go from coarse to fine "
                              f"({'increasing' if self.finer == 'up' else 'decreasing'}; got {list(v)})")


def _knobs() -> dict[str, Knob]:
    split = ["fluid.implicit=false", "fluid.substeps=8"]
    return {"substeps": Knob("fluid.substeps", [2, 4, 8], 4),
            "penalization": Knob("fluid.penalization_iterations", [1, 3, 9], None, base=split,
                                 limit=["fluid.implicit=true"]),
            "kernel": Knob("coupling.sigma_prime", [2.5e-5, 1.25e-5, 6.25e-6], 6.25e-6, finer="down"),
            "grid": Knob("fluid.refinement", [1, 2], 1),
            "grid_short": Knob("fluid.refinement", [1, 2, 4], 1, frames=30),
            "frame_step": Knob("h", [0.01, 0.005, 0.0025], 0.01, finer="down"),
            "coupling_passes": Knob("coupling.subiterations", [1, 8], 1)}


@dataclass
class ConvergenceStudyConfig:
    """suite=convergence: the frequency study (head displacement, mean thrust) against each knob,
    the others at their defaults. overrides: for every run (the fluid: numerical by default)."""

    frequencies: list[float] = field(default_factory=lambda: [3.0, 5.0, 7.0])
    frames: int = 120
    knobs: dict[str, Knob] = field(default_factory=_knobs)
    overrides: list[str] = field(default_factory=lambda: ["fluid=numerical"])

    def validate(self) -> None:
        if not self.frequencies or not all(f > 0 for f in self.frequencies) or self.frames < 1:
            raise ConfigError("convergence.frequencies must be positive and convergence.frames >= 1")
        for name, knob in self.knobs.items():
            knob.check(name)
