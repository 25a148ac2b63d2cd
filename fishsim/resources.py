"""Memory checked before anything is allocated: a run that cannot fit stops with one line
instead of growing into an out-of-memory kill.

The estimate of an episode (bytes), with B fish, C = (H r) (W r) fluid cells on the internal grid
(r the refinement), N mesh nodes (estimated from the edge length before meshing: the default
0.2 m fish has 1775 nodes at 2 mm (graded), N ~ (L / h_e)^2) and, for gradient runs, T frames:

    base 0.6 GB (Python, torch, compiled kernels)
    + B C 400 B          fluid state and the solver's / U-Net's work arrays per fish
    + B N 16 sqrt(N) B   the solid's banded Newton factors (half-bandwidth ~ sqrt(N) nodes)
    + B T (4 C + 16 N)   gradient runs: the forward solutions replayed by the checkpointed backward
    + B S C 1 kB         gradient runs: one checkpoint segment's autograd graph (S frames)

Measured for scale: the default HydroNet episode peaks at 0.88 GB (estimate 0.62 GB without
gradients); a 500-frame HydroNet gradient episode at 0.98 GB (estimate 1.5 GB).
"""

from __future__ import annotations

import math
from pathlib import Path

from fishsim.errors import ConfigError

NODES_DEFAULT, EDGE_DEFAULT, LENGTH_DEFAULT = 1775, 2.0e-3, 0.2


def estimated_nodes(length: float, edge_length: float) -> int:
    """Mesh nodes of a fish of ``length`` meshed at ``edge_length`` (scaled from the default)."""
    return int(NODES_DEFAULT * (length / LENGTH_DEFAULT * EDGE_DEFAULT / edge_length) ** 2)


def episode_bytes(cfg, batch: int, gradient_frames: int = 0, segment: int = 25) -> float:
    """The module docstring's estimate for a SimulateConfig-like ``cfg``."""
    f = cfg.fluid
    cells = 0 if f.model == "none" else f.H * f.W * (f.refinement if f.model == "numerical" else 1) ** 2
    nodes = estimated_nodes(cfg.fish.length, cfg.fish.edge_length)
    total = 0.6e9 + batch * cells * 400 + batch * nodes * 16 * math.sqrt(nodes)
    if gradient_frames:
        total += batch * gradient_frames * (4 * cells + 16 * nodes) + batch * min(segment, gradient_frames) * cells * 1e3
    return total


def available_bytes() -> float | None:
    """MemAvailable of /proc/meminfo (None where it cannot be read)."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return float(line.split()[1]) * 1024
    except OSError:
        return None
    return None


def check_memory(cfg, batch: int, gradient_frames: int = 0, segment: int = 25) -> None:
    """ConfigError (one line) when the estimate exceeds 90 % of the available memory, unless
    ``cfg.check_memory`` is false."""
    if not getattr(cfg, "check_memory", True):
        return
    need, have = episode_bytes(cfg, batch, gradient_frames, segment), available_bytes()
    if have is not None and need > 0.9 * have:
        raise ConfigError(f"this run needs about {need / 1e9:.3g} GB of memory and {have / 1e9:.3g} GB are available "
                          f"(grid {cfg.fluid.H} x {cfg.fluid.W}, refinement {cfg.fluid.refinement}, "
                          f"~{estimated_nodes(cfg.fish.length, cfg.fish.edge_length)} mesh nodes, {batch} fish); "
                          "use a smaller grid, a coarser fish.edge_length or fewer fish, or check_memory=false")
