"""Memory and time checked before anything is allocated: a run that cannot fit stops with one
line instead of growing into an out-of-memory kill, and a run that cannot finish inside its SLURM
job stops before it starts. ``check_resources=false`` overrides both.

The estimate of an episode (bytes), with B fish, C = (H r) (W r) fluid cells on the internal grid
(r the refinement), N mesh nodes (estimated from the edge length before meshing: the default
0.2 m fish has 1803 nodes at 2 mm (graded), N ~ (L / h_e)^2) and, for gradient runs, T frames:

    base 0.6 GB (Python, torch, compiled kernels)
    + B C 400 B          fluid state and the solver's / U-Net's work arrays per fish
    + B N 16 sqrt(N) B   the solid's banded Newton factors (half-bandwidth ~ sqrt(N) nodes)
    + B T (4 C (1 + 2 n r) + 16 N)   gradient runs: the forward solutions replayed by the checkpointed
                         backward (p; with the numerical fluid's joint stage the 2 n r stage potentials
                         of its n r sub-steps, ``fluid.substeps`` n)
    + G B S C 1 kB       gradient runs: G checkpoint segments' autograd graphs (S frames; G = 2 for one
                         fish in a fluid other than HydroNet, whose backward recomputes the previous
                         segment beside the current one: rollout.Segments; else 1)

Measured for scale: the default HydroNet episode peaks at 0.88 GB (estimate 0.62 GB without
gradients); a 500-frame HydroNet gradient episode at 0.98 GB (estimate 1.5 GB); the numerical
Table 1 episode (300 frames, 10-frame segments, B = 1) at 1.13 GB (estimate 1.55 GB; its replay
record ~1 MB a frame).

The time of an episode (seconds), calibrated on this project's 2-core CPU with nothing else
running (default fish, the defaults of 2026-12-01, freed memory kept in the heap; the hosts of
that week differ by up to 2x): 300 frames at B = 1 take 5.7-6.4 s numerical (fluid 4.4-5.0 s) and
6.0-6.7 s HydroNet (fluid 4.5-5.1 s) forward, 6.7-7.1 / 12.8-14.4 s backward; a fish and frame at
B = 16 10.4-10.7 ms numerical, 15.6-16.7 ms HydroNet (fluid 14.1-15.0 ms):
    per fish and frame  t = 4 ms (N / 1803)^1.5 + c_fluid C r^3    c_numerical = 0.5 us, c_hydronet = 0.55 us
    episode             T frames B fish t, times g for a gradient run (g = 2.5 numerical, 3.2 HydroNet, 1.5 vacuum)
(the B = 1 shares: a batch's solid runs eight fish at once and the numerical fluid two samples
at a time, so a fish and frame at B = 16 is estimated at 19 / 20.5 ms against 10.5 / 16 measured;
r^3: r^2 the cells of the refined grid, r the sub-steps, 79-92 ms against 10.3-10.8 a step at
r = 2.)  The estimate is printed before a run on the CPU;
inside a SLURM job (``SLURM_JOB_END_TIME``) a run estimated to outlast the job is refused.
"""

from __future__ import annotations

import math
import os
import time
from pathlib import Path

from fishsim.errors import ConfigError

NODES_DEFAULT, EDGE_DEFAULT, LENGTH_DEFAULT = 1803, 2.0e-3, 0.2
SOLID_FRAME_S = 4e-3                                    # solid + coupling, default fish, one frame [s]
FLUID_CELL_FRAME_S = {"numerical": 0.5e-6, "hydronet": 0.55e-6, "none": 0.0}
GRADIENT_FACTOR = {"numerical": 2.5, "hydronet": 3.2, "none": 1.5}  # (forward + backward) / forward


def estimated_nodes(length: float, edge_length: float) -> int:
    """Mesh nodes of a fish of ``length`` meshed at ``edge_length`` (scaled from the default)."""
    return int(NODES_DEFAULT * (length / LENGTH_DEFAULT * EDGE_DEFAULT / edge_length) ** 2)


def episode_bytes(cfg, batch: int, gradient_frames: int = 0, segment: int = 25) -> float:
    """The module docstring's estimate for a SimulateConfig-like ``cfg``."""
    cells = 0 if cfg.fluid.model == "none" else cfg.tank.H * cfg.tank.W * refinement(cfg.fluid) ** 2
    nodes = estimated_nodes(cfg.fish.length, cfg.fish.edge_length)
    total = 0.6e9 + batch * cells * 400 + batch * nodes * 16 * math.sqrt(nodes)
    if gradient_frames:
        graphs = 2 if batch == 1 and cfg.fluid.model != "hydronet" else 1
        record = 1 + replayed_solves(cfg.fluid)
        total += batch * gradient_frames * (4 * cells * record + 16 * nodes) + \
            graphs * batch * min(segment, gradient_frames) * cells * 1e3
    return total


def refinement(fluid) -> int:
    """The internal grid's refinement r of a fluid config (1 but for the numerical fluid's)."""
    return getattr(fluid, "refinement", 1)


def replayed_solves(fluid) -> int:
    """The fields of iterative solves a fluid config's step records for a recomputation to replay
    (``FluidState.solves``): the numerical fluid's joint stage, two a sub-step at its floor of n r
    sub-steps; 0 for any other."""
    joint = fluid.model == "numerical" and (getattr(fluid, "implicit", False) or getattr(fluid, "brinkman", None))
    return 2 * fluid.substeps * refinement(fluid) if joint else 0


def available_bytes() -> float | None:
    """MemAvailable of /proc/meminfo (None where it cannot be read)."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return float(line.split()[1]) * 1024
    except OSError:
        return None
    return None


def cpu_fields(cpuinfo: str = "/proc/cpuinfo") -> dict[str, str]:
    """The first core's fields of /proc/cpuinfo ("model name", "flags", ...; empty where the file
    cannot be read)."""
    fields: dict[str, str] = {}
    try:
        for line in Path(cpuinfo).read_text().splitlines():
            if not line.strip():
                break
            key, _, value = line.partition(":")
            fields.setdefault(key.strip(), value.strip())
    except OSError:
        pass
    return fields


def cpu_flags(cpuinfo: str = "/proc/cpuinfo") -> set[str]:
    """The CPU's feature flags (``cpu_fields``' "flags": avx2, avx512_bf16, amx_bf16, ...)."""
    return set(cpu_fields(cpuinfo).get("flags", "").split())


def episode_seconds(cfg, batch: int, frames: int, gradient: bool = False) -> float:
    """The module docstring's time estimate [s] of ``frames`` frames of ``batch`` fish."""
    f, r = cfg.fluid, refinement(cfg.fluid)
    nodes = estimated_nodes(cfg.fish.length, cfg.fish.edge_length)
    per_frame = SOLID_FRAME_S * (nodes / NODES_DEFAULT) ** 1.5
    if f.model != "none":
        per_frame += FLUID_CELL_FRAME_S[f.model] * cfg.tank.H * cfg.tank.W * r**3
    return frames * batch * per_frame * (GRADIENT_FACTOR[f.model] if gradient else 1.0)


def job_seconds_left() -> float | None:
    """Seconds until the SLURM job this runs in ends (``SLURM_JOB_END_TIME``), None outside one."""
    end = os.environ.get("SLURM_JOB_END_TIME", "")
    return float(end) - time.time() if end.strip().isdigit() else None


def describe_seconds(seconds: float) -> str:
    """A duration for people: '40 s', '12 min', '3.5 h', '2.1 days'."""
    for unit, size in (("days", 86400.0), ("h", 3600.0), ("min", 60.0)):
        if seconds >= 2 * size:
            return f"{seconds / size:.2g} {unit}"
    return f"{seconds:.0f} s"


def check_time(cfg, batch: int, frames: int, gradient: bool = False) -> float:
    """The estimated run time [s]; ConfigError (one line) when it exceeds what is left of the
    SLURM job this runs in, unless ``cfg.check_resources`` is false."""
    need, left = episode_seconds(cfg, batch, frames, gradient), job_seconds_left()
    if getattr(cfg, "check_resources", True) and left is not None and need > left:
        raise ConfigError(f"this run needs about {describe_seconds(need)} (estimate) and its SLURM job ends in "
                          f"{describe_seconds(max(left, 0.0))}; ask for a longer job (hydra.launcher.timeout_min), "
                          "run fewer frames or fish, or pass check_resources=false")
    return need


def check_memory(cfg, batch: int, gradient_frames: int = 0, segment: int = 25) -> None:
    """ConfigError (one line) when the estimate exceeds 90 % of the available memory, unless
    ``cfg.check_resources`` is false."""
    if not getattr(cfg, "check_resources", True):
        return
    need, have = episode_bytes(cfg, batch, gradient_frames, segment), available_bytes()
    if have is not None and need > 0.9 * have:
        raise ConfigError(f"this run needs about {need / 1e9:.3g} GB of memory and {have / 1e9:.3g} GB are available "
                          f"(grid {cfg.tank.H} x {cfg.tank.W}, refinement {refinement(cfg.fluid)}, "
                          f"~{estimated_nodes(cfg.fish.length, cfg.fish.edge_length)} mesh nodes, {batch} fish); "
                          "use a smaller grid, a coarser fish.edge_length or fewer fish, or check_resources=false")


def announce_time(seconds: float, what: str, device: str = "cpu") -> None:
    """One line on stderr with a CPU run's estimated time, for runs long enough to wonder (>= 30 s)."""
    if device == "cpu" and seconds >= 30:
        from rich.console import Console

        Console(stderr=True).print(f"[dim]{what}: about {describe_seconds(seconds)} on a 2-core CPU (estimate)[/]")
