"""The paper's frequency study (Fig. 4): the head's x displacement after an episode against the
controller frequency, for several fluids, each batched (B = number of frequencies) in one rollout,
compared with a reference fluid (the numerical solver on the refined grid by default).

Per fluid: displacement [mm] per frequency, wall time, and against the reference the Spearman rank
correlation rho_s (Pearson correlation of the ranks), the argmax frequency, and the mean absolute
mismatch in mm and in grid cells (dx). A fish that blows up is marked (NaN, its frame and reason)
and the rest of its batch carries on.
"""

from __future__ import annotations

import itertools
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


def spearman(a, b) -> float:
    """Spearman rank correlation of two sequences (NaN if either is constant or has NaN)."""
    from scipy.stats import spearmanr

    a, b = np.asarray(a, float), np.asarray(b, float)
    if not (np.isfinite(a).all() and np.isfinite(b).all()) or a.std() == 0 or b.std() == 0:
        return math.nan
    return float(spearmanr(a, b).statistic)


def run_fluid(name: str, cfg: SwimStudyConfig, device: str = "cpu") -> dict:
    """One batched episode of every frequency in fluid ``name`` (``episode``)."""
    return episode([*FLUIDS[name], *cfg.overrides], cfg.frequencies, cfg.frames, device)


def episode(overrides: list[str], frequencies, frames: int, device: str = "cpu") -> dict:
    """One batched `fishsim simulate` episode (B = one fish per frequency, in memory, no files)
    with ``overrides``: the head's x displacement [mm] and the mean thrust F_x [mN/m] per fish,
    the wall time and any fish that blew up (NaN, with its frame and reason)."""
    from fishsim.commands.simulate import build_episode
    from fishsim.config import load_config
    from fishsim.rollout import head_node, rollout

    freqs = ",".join(str(f) for f in frequencies)
    sim = load_config("simulate", [*overrides, f"frames={frames}", f"batch.frequency=[{freqs}]", f"device={device}"])
    ep = build_episode(sim)
    state = ep.swimmer.initial_state(ep.params, ep.origin)
    head0 = state.q[:, head_node(ep.swimmer.solid.mesh), 0].clone()
    failures: dict = {}
    t0 = time.perf_counter()
    with torch.no_grad():
        _, m = rollout(ep.swimmer, state, ep.params, sim.frames, failures=failures)
    wall = time.perf_counter() - t0
    dx_mm = (1e3 * (m["head_x"][-1] - head0)).cpu().numpy()
    thrust = (1e3 * m["thrust_x"].mean(0)).cpu().numpy()
    for b in failures:
        dx_mm[b] = thrust[b] = math.nan
    return {"displacement_mm": dx_mm.tolist(), "mean_thrust_mN": thrust.tolist(), "wall_s": wall,
            "dx_mm": 1e3 * sim.fluid.dx, "s_per_fish_frame": wall / (len(frequencies) * sim.frames),
            "failures": {str(frequencies[b]): {"frame": f, "reason": why} for b, (f, why) in failures.items()}}


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


# ------------------------------------------------------------------------------------------------
# Convergence of the study in the numerical knobs (suite=convergence)
# ------------------------------------------------------------------------------------------------


@dataclass
class Knob:
    """One numerical setting of the study: the `fishsim simulate` key, its values from coarse to
    fine (``finer``: "up" when a larger value is finer, "down" when smaller is, e.g. a kernel
    width), the shipped default (its error is reported), and an optional episode length of its own
    (a shorter episode for an expensive refinement)."""

    key: str
    values: list[float]
    default: float
    finer: str = "up"
    frames: int | None = None

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
    return {"substeps": Knob("fluid.substeps", [4, 8, 16], 8),
            "penalization": Knob("fluid.penalization_iterations", [1, 2, 4], 2),
            "kernel": Knob("coupling.sigma_prime", [2.5e-5, 1.25e-5, 6.25e-6], 6.25e-6, finer="down"),
            "grid": Knob("fluid.refinement", [1, 2], 1),
            "grid_short": Knob("fluid.refinement", [1, 2, 4], 1, frames=30)}


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


def observed_order(values, d) -> dict:
    """From results d at settings ``values`` (coarse to fine, constant ratio r), the observed
    order p = ln(e1 / e2) / ln r of the last three (e1 = d2 - d1, e2 = d3 - d2; NaN unless they
    converge monotonically) and the Richardson estimate d_inf = d3 + e2 / (r^p - 1); with two
    settings only the last change. All per column of d [n_values, n]."""
    d = np.asarray(d, float)
    v = np.asarray(values, float)
    last_change = d[-1] - d[-2]
    out = {"last_change": last_change.tolist(), "order": [math.nan] * d.shape[1], "richardson": [math.nan] * d.shape[1]}
    if len(v) < 3:
        return out
    r = max(v[-1] / v[-2], v[-2] / v[-1])
    e1, e2 = d[-2] - d[-3], d[-1] - d[-2]
    for j in range(d.shape[1]):
        if e1[j] * e2[j] > 0 and abs(e2[j]) < abs(e1[j]):
            p = math.log(abs(e1[j] / e2[j])) / math.log(r)
            out["order"][j] = p
            out["richardson"][j] = float(d[-1, j] + e2[j] / (r ** p - 1))
    return out


def convergence_study(cfg: ConvergenceStudyConfig, device: str = "cpu",
                      progress: Callable[[str], None] | None = None) -> dict:
    """Each knob's settings run as one batched episode (identical runs shared); per knob the
    displacement and thrust per setting, their observed orders, Richardson estimates and the
    default's error against the finest setting and against the Richardson estimate."""
    cache: dict[tuple, dict] = {}
    results = {}
    for name, knob in cfg.knobs.items():
        frames = knob.frames or cfg.frames
        runs = []
        for v in knob.values:
            key = (knob.key, float(v), frames)
            if key not in cache:
                if progress:
                    progress(f"{name} {knob.key}={v:g}")
                overrides = [*cfg.overrides, f"{knob.key}={v:g}" if knob.key != "fluid.refinement" else f"{knob.key}={int(v)}"]
                cache[key] = episode(overrides, cfg.frequencies, frames, device)
            runs.append(cache[key])
        d = np.array([r["displacement_mm"] for r in runs])
        f = np.array([r["mean_thrust_mN"] for r in runs])
        entry = {"key": knob.key, "values": list(knob.values), "default": knob.default, "frames": frames,
                 "displacement_mm": d.tolist(), "mean_thrust_mN": f.tolist(),
                 "wall_s": [r["wall_s"] for r in runs], "failures": [r["failures"] for r in runs],
                 "displacement": observed_order(knob.values, d), "thrust": observed_order(knob.values, f)}
        if knob.default in knob.values:
            i = list(knob.values).index(knob.default)
            rich = np.asarray(entry["displacement"]["richardson"])
            entry["default_error_vs_finest"] = ((d[i] - d[-1]) / np.abs(d[-1])).tolist()
            entry["default_error_vs_richardson"] = ((d[i] - rich) / np.abs(rich)).tolist()
        results[name] = entry
    return results
