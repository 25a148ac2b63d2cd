"""HydroNet settings that the CLI's config (``fishsim.config``) needs without torch, for the
commands' help: the pressures a ``HydroNetFluid`` can give (unet.py; "recovered" is computed by
fishsim/fluid/pressure.py), ``EvalConfig``, the held-out evaluation's
(fishsim/learn/evaluate.py), and ``TrainConfig``, train-hydronet's (fishsim/learn/train.py),
with its network's ``NetConfig`` (unet.py) and its scene pool's ``PoolConfig``
(fishsim/learn/pool.py).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from fishsim.errors import ConfigError
from fishsim.fluid.tank import TankConfig
from fishsim.resources import cpu_flags

if TYPE_CHECKING:
    from fishsim.fields import Grid

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
    tank: TankConfig = field(default_factory=TankConfig)
    still_steps: int = 300
    energy_steps: int = 150
    energy_frequency: float = 5.0


@dataclass(frozen=True)
class NetConfig:
    """U-Net hyper-parameters. hidden: channels of the first level (Wandel: 20); depth: number of
    down/up levels (Wandel: 4); bound_a, bound_p: A, P in grid units; condition: (rho, nu*) inputs;
    pressure_input: p_t is an input and p_t+1 = p_t + the net's update (Wandel); false: p_t+1 is
    the net's output from (a_t, b, v_d) alone, as the solver's pressure is (the Lagrange multiplier
    of v_t+1's divergence: no p_t in it), so it cannot carry p_t forward."""

    hidden: int = 20
    depth: int = 4
    bound_a: float = 400.0
    bound_p: float = 64.0
    condition: bool = False
    pressure_input: bool = True

    @property
    def in_channels(self) -> int:
        return 15 if self.condition else 13


@dataclass(frozen=True)
class PoolConfig:
    """Scene distribution and pool mechanics (SI units; ranges are (low, high)).

    size: scenes in the pool; H, W, dx, h: training grid (a crop: the net is fully convolutional).
    episode_steps: average steps a scene lives before its round-robin reset.
    rho (uniform), mu (log-uniform): fluid ranges; equal ends = one fluid.
    max_speed: bound on body, surface and inflow speeds (m/s).
    wall: range of wall thickness in cells; p_inflow: probability of an inflow/outflow channel.
    p_fish: probability of a swimming fish; max_obstacles: rigid obstacles per scene.
    sigma: log-uniform range of the mask softness (m^2); p_sigma_coupling: probability of the
        coupling's default 5e-7 instead.
    fish_length, fish_freq (Hz), fish_amp (tail amplitude / L), fish_wavelength (/ L): fish ranges;
        fish_speed (m/s): range of the translation speed of the half of the fish that translates.
    obstacle_cells: range of obstacle half-sizes in cells; tau_motion: OU correlation time (s) of
        the target velocities.
    replay: ``fishsim simulate`` trajectory files (on this grid, h, a fixed tank) whose fish are
        replayed (``fishsim.learn.pool.Replay``); p_replay: probability of a replayed fish
        instead of a random scene.
    """

    size: int = 256
    H: int = 64
    W: int = 128
    dx: float = 2.5e-3
    h: float = 0.01
    episode_steps: int = 500
    rho: tuple[float, float] = (50.0, 50.0)
    mu: tuple[float, float] = (1.25e-4, 1.25e-4)
    max_speed: float = 0.5
    wall: tuple[int, int] = (2, 5)
    p_inflow: float = 0.3
    p_fish: float = 0.4
    max_obstacles: int = 2
    sigma: tuple[float, float] = (5e-9, 5e-5)
    p_sigma_coupling: float = 0.5
    fish_length: tuple[float, float] = (0.1, 0.2)
    fish_freq: tuple[float, float] = (1.0, 8.0)
    fish_amp: tuple[float, float] = (0.03, 0.1)
    fish_wavelength: tuple[float, float] = (0.7, 1.5)
    fish_speed: tuple[float, float] = (0.0, 0.15)
    obstacle_cells: tuple[float, float] = (3.0, 14.0)
    tau_motion: float = 1.0
    replay: tuple[str, ...] = ()
    p_replay: float = 0.0

    @property
    def grid(self) -> Grid:
        from fishsim.fields import Grid

        return Grid(self.H, self.W, self.dx)


@dataclass(frozen=True)
class TrainConfig:
    """Everything a training run needs (plain values; mirrors the Hydra config).

    net, pool: network and scene-pool settings (``pool.rho``/``pool.mu`` are the fluid ranges).
    iterations: total optimiser steps; batch_size: scenes per step (per rank); lr: Adam step size.
    beta, gamma: loss weights; advection: "koren" | "central" scheme of the loss's residual.
    teacher: weight of L_t, the numerical solver's one-step target (0: physics only, the paper).
    teacher_refinement: r of that solver: it steps on the r times finer grid (the scenes' bodies
        sampled on its cells, the pool's state prolonged, its own rollout kept fine) and its step
        is restricted to the training grid (1: the training grid itself).
    teacher_pressure: weight kappa of L_P, the mean-free pressure's squared relative error on the fluid cells,
        added to L_t (the gradient term hardly sees a large-scale error; needs a teacher; 0: off).
    energy: weight of L_E, the step's relative kinetic-energy error against the solver's (needs a
        teacher; 0: off).
    unroll: network steps per iteration, back-propagated through together (1: Wandel's one step);
        with a teacher, step j is compared with the solver's own j-step rollout.
    pressure_dropout: probability that a training step's sample gets p_t = 0 as its input (the
        loss still sees the true p_t): the network must then make p_t+1 from the flow and the
        bodies, not carry p_t forward (0: off).
    device: "cpu" | "cuda"; threads: torch CPU threads (0: default).
    bf16: bfloat16 autocast for the U-Net trunk: true | false | "auto" (``resolve_bf16``: on where
    it is fast, a GPU with bf16 or a CPU with AMX; elsewhere float32, since without AMX bf16 runs
    ~10x slower than float32 on the CPU); channels_last: NHWC memory layout;
    compile: torch.compile the trunk (measured slower on CPU); compile_loss: torch.compile the
    loss (~80 s once; then the Koren residual's forward + backward runs 10x faster). log_every, ckpt_every (iterations), ckpt_minutes,
    val_every, val_scenes, val_steps: bookkeeping. grad_clip: max gradient norm (0: off).
    ema: decay d of an exponential moving average of the weights, theta_avg <- d theta_avg + (1 - d)
    theta after every step (Polyak averaging; 0: off): the validation, the swim checks and the
    model files (best.pt, best_swim.pt) then hold the average, which follows the run over ~1 / (1 -
    d) iterations without the iterate's step-to-step scatter; ckpt.pt keeps both.
    swim_every: every this many iterations the network swims the frequency study (swim_frequencies
    [Hz], swim_frames) against the numerical fluid (refined ``swim_refinement`` times: 2 is the
    reference of ``fishsim validate suite=swim``, ~10 min once per folder on one thread), logged
    to swim.csv; best_swim.pt keeps the closest (``swim_check``; 0: off).
    out_dir: the run's folder; null: a new outputs/train-hydronet/<time> (``fishsim.io.outdir``).
    resume: continue from ``out_dir/ckpt.pt`` exactly (its lr replaced by ``lr``); needs out_dir.
    overwrite: start a new run in an out_dir that holds one (else refused: a run is never lost).
    init_from: start a new run from the weights of this best.pt / ckpt.pt (fresh optimiser and
    pool: fine-tuning on another crop size or fluid range); ignored when resuming.
    warm_pool: when trained weights meet a freshly drawn pool (init_from, or resuming a compact
    checkpoint), first step each scene by the network a random 0..warm_pool times, so training
    does not start on the pool's start-ups alone (``ScenePool.warm``; 0: off).
    freeze_norm: train with every BatchNorm in eval mode (``HydroNet.freeze_norm``): normalised by
    its running statistics, which stay as loaded, its scale and shift still trained, so the map
    trained is the map used in inference (fine-tuning a trained model; a new model needs the
    batch statistics: leave it false). Without it the running statistics follow the pool's
    states, and they alone moved the frequency study by up to 5 % in 100 iterations.
    """

    out_dir: str | None = None
    iterations: int = 200_000
    batch_size: int = 16
    lr: float = 1e-3
    beta: float = 1.0
    gamma: float = 20.0
    teacher: float = 0.0
    teacher_refinement: int = 1
    teacher_pressure: float = 0.0
    energy: float = 0.0
    unroll: int = 1
    pressure_dropout: float = 0.0
    advection: str = "koren"
    net: NetConfig = field(default_factory=lambda: NetConfig(hidden=16))
    pool: PoolConfig = field(default_factory=PoolConfig)
    device: str = "cpu"
    threads: int = 0
    bf16: bool | str = "auto"
    channels_last: bool = True
    compile: bool = False
    compile_loss: bool = True
    seed: int = 0
    log_every: int = 10
    ckpt_every: int = 2000
    ckpt_minutes: float = 5.0
    val_every: int = 500
    val_scenes: int = 8
    val_steps: int = 40
    grad_clip: float = 0.0
    ema: float = 0.0
    swim_every: int = 0
    swim_frames: int = 120
    swim_refinement: int = 1
    swim_frequencies: tuple[float, ...] = (3.0, 4.0, 5.0, 6.0, 7.0)
    resume: bool = False
    overwrite: bool = False
    init_from: str = ""
    warm_pool: int = 200
    freeze_norm: bool = False
    progress: bool = True

    def validate(self) -> None:
        """Reject impossible values with one line (ConfigError) before any work starts."""
        _check(self.iterations >= 1 and self.batch_size >= 1, "iterations and batch_size must be >= 1")
        _check(self.lr > 0 and self.beta > 0 and self.gamma >= 0 and self.teacher >= 0,
               "lr and beta must be > 0, gamma and teacher >= 0")
        _check(self.teacher_refinement >= 1,
               f"teacher_refinement must be a positive integer (1: the training grid), got {self.teacher_refinement}")
        _check(self.teacher_pressure >= 0 and (self.teacher_pressure == 0 or self.teacher > 0),
               f"teacher_pressure must be >= 0 and needs the solver's step (teacher > 0), got {self.teacher_pressure}")
        _check(self.energy >= 0 and (self.energy == 0 or self.teacher > 0),
               f"energy must be >= 0 and needs the solver's step (teacher > 0), got energy={self.energy}")
        _check(self.warm_pool >= 0, f"warm_pool must be >= 0 steps (0: off), got {self.warm_pool}")
        _check(0 <= self.ema < 1, f"ema must be a decay in [0, 1) (0: off), got {self.ema}")
        _check(self.unroll >= 1, f"unroll must be >= 1 network steps per iteration, got {self.unroll}")
        _check(0 <= self.pressure_dropout < 1, f"pressure_dropout must be a probability in [0, 1), got {self.pressure_dropout}")
        _check(self.swim_refinement >= 1, f"swim_refinement must be a positive integer, got {self.swim_refinement}")
        _check(self.swim_every >= 0 and self.swim_frames >= 1 and len(self.swim_frequencies) >= 1
               and all(f > 0 for f in self.swim_frequencies),
               "swim_every must be >= 0 (0: off), swim_frames >= 1 and swim_frequencies positive values [Hz]")
        _check(self.advection in ("koren", "central"), f"advection must be koren or central, got {self.advection!r}")
        _check(self.bf16 in (True, False, "auto"), f"bf16 must be true, false or auto, got {self.bf16!r}")
        _check(self.device in ("cpu", "cuda") or self.device.startswith("cuda:"),
               f"device must be cpu or cuda, got {self.device!r}")
        _check(self.net.hidden >= 1 and self.net.depth >= 1, "net.hidden and net.depth must be >= 1")
        p = self.pool
        _check(p.size >= self.batch_size, f"pool.size ({p.size}) must be >= batch_size ({self.batch_size})")
        _check(p.H >= 16 and p.W >= 16, f"pool.H x pool.W must be at least 16 x 16 (got {p.H} x {p.W})")
        _check(p.dx > 0 and p.h > 0 and p.max_speed > 0, "pool.dx, pool.h and pool.max_speed must be > 0")
        for name in ("rho", "mu", "sigma", "fish_length", "fish_freq", "fish_wavelength",
                     "obstacle_cells", "wall"):
            lo, hi = getattr(p, name)
            _check(0 < lo <= hi, f"pool.{name} must be a range 0 < low <= high, got [{lo}, {hi}]")
        for name in ("fish_amp", "fish_speed"):  # fish_amp 0: a fish that holds still (still a boundary to learn)
            lo, hi = getattr(p, name)
            _check(0 <= lo <= hi, f"pool.{name} must be a range 0 <= low <= high, got [{lo}, {hi}]")
        _check(0 <= p.p_replay <= 1 and (p.p_replay == 0 or len(p.replay) > 0),
               f"pool.p_replay must be a probability in [0, 1] and > 0 needs pool.replay files (got {p.p_replay}, "
               f"{len(p.replay)} files)")
        for path in p.replay:
            _check(Path(path).is_file(), f"pool.replay: no such trajectory file {path} (make one with fishsim simulate)")
        _check(self.net.condition or (p.rho[0] == p.rho[1] and p.mu[0] == p.mu[1]),
               "a fluid range (pool.rho / pool.mu low < high) needs net.condition=true")
        _check(not self.resume or bool(self.out_dir), RESUME_NEEDS_OUT_DIR)


def cpu_has_amx_bf16(cpuinfo: str = "/proc/cpuinfo") -> bool:
    """Whether this CPU multiplies bfloat16 matrices in hardware (Intel AMX: the ``amx_bf16``
    flag of /proc/cpuinfo; False where the file cannot be read)."""
    return "amx_bf16" in cpu_flags(cpuinfo)


def cpu_has_bf16(cpuinfo: str = "/proc/cpuinfo") -> bool:
    """Whether this CPU has bfloat16 instructions at all (AMX or AVX512-BF16: the ``amx_bf16`` or
    ``avx512_bf16`` flag; False where the file cannot be read). The shipped U-Net's step at 100 x
    300, B = 2, took 8.8 ms in bf16 against 19.2 ms float32 with AVX512-BF16 (2026-12-01), 248 ms
    against 24-32 ms with neither."""
    return bool({"amx_bf16", "avx512_bf16"} & cpu_flags(cpuinfo))


def resolve_bf16(bf16: bool | str, device_type: str) -> bool:
    """``TrainConfig.bf16`` as a bool: "auto" is True on a GPU that supports bfloat16 and on a CPU
    with AMX (measured on this project's CPUs: the U-Net's step at 100 x 300, B = 1, 17 ms in bf16
    against 24-32 ms float32 with AMX, 248 ms against 24-32 ms with no bf16 instructions), else
    False. AVX512-BF16 alone is left out: there a training batch's forward + backward (16 x 64 x
    128) took 77 ms in bf16 against 124 ms float32 (2026-12-01), a small share of an iteration
    whose teacher solves dominate; ``bf16=true`` takes it."""
    if bf16 != "auto":
        return bool(bf16)
    if device_type == "cuda":
        import torch

        return torch.cuda.is_bf16_supported()
    return cpu_has_amx_bf16()


RESUME_NEEDS_OUT_DIR = ("resume=true needs out_dir=<the folder of the run to continue> (without it every run "
                        "starts in a new outputs/train-hydronet/<time> folder)")


def _check(ok: bool, message: str) -> None:
    if not ok:
        raise ConfigError(message)
