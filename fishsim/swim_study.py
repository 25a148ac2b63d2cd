"""The paper's frequency study (Fig. 4): the head's x displacement after an episode against the
controller frequency, for several fluids, each batched (B = number of frequencies) in one rollout,
compared with a reference fluid (the numerical solver on the refined grid by default).

Per fluid: displacement [mm] per frequency, wall time, and against the reference the Spearman rank
correlation rho_s (Pearson correlation of the ranks), the argmax frequency, and the mean absolute
mismatch in mm and in grid cells (dx). A fish that blows up is marked (NaN, its frame and reason)
and the rest of its batch carries on.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from fishsim.errors import ConfigError

# The fluids the study knows, as `fishsim simulate` overrides.
FLUIDS = {
    "numerical_r2": ["fluid=numerical", "fluid.refinement=2"],
    "numerical": ["fluid=numerical"],
    "hydronet": ["fluid=hydronet"],
    "hydronet_network": ["fluid=hydronet", "fluid.pressure=network"],
}
# The paper's Table 1 (300 frames, their hardware) and Fig. 4 (mean mismatch, argmax).
PAPER = {"hydronet_forward_s_per_frame": 213.0 / 300, "comsol_s_per_frame": (5 * 3600 + 16 * 60 + 39) / 300,
         "mean_mismatch_mm": 15.0, "mean_mismatch_cells": 6.0, "argmax_hz": 5.0}


@dataclass
class SwimStudyConfig:
    """suite=swim. frequencies (Hz); frames per episode; fluids: names of FLUIDS; reference: the
    one the others are compared with; overrides: more `fishsim simulate` overrides for every run
    (e.g. a smaller tank)."""

    frequencies: list[float] = field(default_factory=lambda: [3.0, 4.0, 5.0, 6.0, 7.0])
    frames: int = 120
    fluids: list[str] = field(default_factory=lambda: ["numerical_r2", "numerical", "hydronet", "hydronet_network"])
    reference: str = "numerical_r2"
    overrides: list[str] = field(default_factory=list)

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


def ranks(x: np.ndarray) -> np.ndarray:
    """Ranks 0..n-1 (ties get their mean rank)."""
    order = np.argsort(x, kind="stable")
    r = np.empty(len(x))
    r[order] = np.arange(len(x), dtype=float)
    for v in np.unique(x):
        r[x == v] = r[x == v].mean()
    return r


def spearman(a, b) -> float:
    """Spearman rank correlation of two sequences (NaN if either is constant or has NaN)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        return math.nan
    ra, rb = ranks(a), ranks(b)
    if ra.std() == 0 or rb.std() == 0:
        return math.nan
    return float(np.corrcoef(ra, rb)[0, 1])


def run_fluid(name: str, cfg: SwimStudyConfig, device: str = "cpu") -> dict:
    """One batched episode of every frequency in fluid ``name``; head x displacement in mm."""
    from fishsim.commands.simulate import build_episode
    from fishsim.config import load_config
    from fishsim.rollout import rollout

    freqs = ",".join(str(f) for f in cfg.frequencies)
    sim = load_config("simulate", [*FLUIDS[name], f"frames={cfg.frames}", f"batch.frequency=[{freqs}]",
                                   f"device={device}", *cfg.overrides])
    ep = build_episode(sim)
    state = ep.swimmer.initial_state(ep.params, ep.origin)
    head0 = state.q[:, int(np.argmax(ep.swimmer.solid.mesh.points[:, 0])), 0].clone()
    failures: dict = {}
    t0 = time.perf_counter()
    with torch.no_grad():
        _, m = rollout(ep.swimmer, state, ep.params, sim.frames, failures=failures)
    wall = time.perf_counter() - t0
    dx_mm = (1e3 * (m["head_x"][-1] - head0)).cpu().numpy()
    for b in failures:
        dx_mm[b] = math.nan
    return {"displacement_mm": dx_mm.tolist(), "wall_s": wall, "dx_mm": 1e3 * sim.fluid.dx,
            "s_per_fish_frame": wall / (len(cfg.frequencies) * sim.frames),
            "failures": {str(cfg.frequencies[b]): {"frame": f, "reason": why} for b, (f, why) in failures.items()}}


def compare(result: dict, reference: dict, frequencies) -> dict:
    """rho_s, argmax and the mean absolute mismatch of ``result`` against ``reference``."""
    a, r = np.asarray(result["displacement_mm"]), np.asarray(reference["displacement_mm"])
    ok = np.isfinite(a) & np.isfinite(r)
    mismatch = float(np.mean(np.abs(a[ok] - r[ok]))) if ok.any() else math.nan
    f = np.asarray(frequencies, float)
    return {"spearman": spearman(a, r),
            "argmax_hz": float(f[np.nanargmax(a)]) if np.isfinite(a).any() else math.nan,
            "mean_mismatch_mm": mismatch, "mean_mismatch_cells": mismatch / result["dx_mm"]}


def frequency_study(cfg: SwimStudyConfig, device: str = "cpu",
                    progress: Callable[[str], None] | None = None) -> dict:
    """Every fluid of ``cfg`` (reference first), compared with the reference."""
    order = [cfg.reference] + [f for f in cfg.fluids if f != cfg.reference]
    results = {}
    for name in order:
        if progress:
            progress(name)
        results[name] = run_fluid(name, cfg, device)
    for name, res in results.items():
        res.update(compare(res, results[cfg.reference], cfg.frequencies))
    return results
