"""Training HydroNet on the scene pool: ``run(TrainConfig(...))`` (the CLI's ``train-hydronet``).

One iteration (Wandel et al. 2021): ask the pool for a batch (state at t, boundary at t + h),
step it once with the network, minimise mean_B log(beta L_p + gamma L_b)
(``fluid/hydronet/loss.py``) with Adam, and tell the pool the new (detached) states, so the
network trains on its own rollouts.
With ``teacher > 0`` the numerical solver steps the same batch too and the objective becomes
mean_B log(beta L_p + gamma L_b + teacher L_t) (``loss.teacher_loss``); with ``unroll = k`` an
iteration takes k network steps, back-propagated together, step j against the solver's own
j-step rollout (``train_step``). ``teacher = 0, unroll = 1`` is the paper's physics-only training.

Outputs under ``out_dir``: ``ckpt.pt`` (latest: model, optimiser, pool, RNG, counters; written
atomically, every ``ckpt_every`` iterations or ``ckpt_minutes``, and on Ctrl-C), ``best.pt`` (the
model with the lowest validation loss: a fixed set of scenes rolled out from rest in eval mode),
``log.csv`` and TensorBoard events in ``tb/``, all under ``out_dir`` (default: a new
outputs/train-hydronet/<time>). ``resume=True`` continues exactly where ``ckpt.pt`` stopped:
Ctrl-C or ``kill PID`` (SIGTERM) finishes the current iteration, saves ``ckpt.pt`` and stops
(a second signal stops at once, the last checkpoint kept), so a resumed run equals an
uninterrupted one bit for bit. Command line:
``fishsim train-hydronet key=value ...`` (keys of TrainConfig, dotted for groups: ``net.hidden=16
pool.H=64``). Multi-GPU/CPU: ``torchrun --nproc_per_node N -m fishsim train-hydronet ...``
(DistributedDataParallel; each rank its own pool, ``ckpt_rank{r}.pt``).
"""

from __future__ import annotations

import contextlib
import csv
import math
import os
import signal
import threading
import time
from dataclasses import asdict, dataclass, fields, is_dataclass, replace
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from torch import Tensor, nn

from fishsim.errors import ConfigError, SimulationBlowUp, Terminated
from fishsim.fields import Boundary, FluidParams, FluidState, Grid, rest_state
from fishsim.fluid.hydronet.config import RESUME_NEEDS_OUT_DIR, TrainConfig, resolve_bf16
from fishsim.fluid.hydronet.loss import EPS, LossConfig, LossTerms, energy_loss, hydronet_loss, teacher_loss
from fishsim.fluid.hydronet.model_file import load_file, load_weights
from fishsim.fluid.hydronet.trained_range import stored_range, training_range
from fishsim.fluid.hydronet.unet import HydroNet
from fishsim.io.atomic import atomic_save, atomic_text
from fishsim.learn import swim_check
from fishsim.learn.pool import RUNAWAY, ScenePool, advance, max_speeds, random_scene, scene_boundaries


@dataclass
class Run:
    """The mutable training state (what a checkpoint holds, plus the loss function)."""

    model: nn.Module
    opt: torch.optim.Optimizer
    pool: ScenePool
    loss_fn: object = None
    teacher: object = None          # the numerical solver giving L_t's targets (None: physics only)
    average: nn.Module | None = None  # the weights' moving average (AveragedModel; cfg.ema > 0)
    iteration: int = 0
    best_val: float = math.inf
    best_swim: float = math.inf     # the lowest swimming error of swim_check (swim_every > 0)
    last_val: float = math.nan
    elapsed: float = 0.0

    @property
    def evaluated(self) -> nn.Module:
        """The weights that are validated, swum and saved as model files: the moving average
        when there is one, else the iterate."""
        return self.model if self.average is None else self.average.module


def make_loss_fn(cfg: TrainConfig):
    """(a_t, p_t, a_t+1, p_t+1, b, v_d, rho, mu, h) -> (L_p [B], L_b [B], L [B], objective), the
    loss of ``fluid/hydronet/loss.py`` on plain tensors, compiled when ``cfg.compile_loss``."""
    grid, loss_cfg = cfg.pool.grid, LossConfig(cfg.beta, cfg.gamma, scheme=cfg.advection)

    def loss_fn(a0, p0, a1, p1, b, vd, rho, mu, h):
        t = hydronet_loss(FluidState(a0, p0), FluidState(a1, p1), Boundary(b, vd), FluidParams(rho, mu, h),
                          grid, loss_cfg)
        return t.momentum, t.boundary, t.total, t.objective

    return torch.compile(loss_fn) if cfg.compile_loss else loss_fn


# ----------------------------------------------------------------------------- one step


def network_forward(net: nn.Module, state: FluidState, boundary: Boundary, params: FluidParams, grid: Grid,
                    bf16: bool) -> FluidState:
    """The network's step from ``state`` to the ``boundary`` at t + h, as training runs it
    (bfloat16 autocast when ``bf16``)."""
    with torch.autocast(state.a.device.type, dtype=torch.bfloat16, enabled=bf16):
        return FluidState(*net(state.a, state.p, boundary.mask, boundary.velocity, params.rho, params.mu, grid.dx,
                               params.h))


TEACHER_RETRIES = 10


def train_step(run: Run, cfg: TrainConfig, net: nn.Module) -> LossTerms:
    """ask -> ``unroll`` steps -> loss -> Adam -> tell; returns the detached loss terms of the
    batch (means over the unrolled steps). With a teacher, step j's target is the solver's own
    j-step rollout from the same start, so the objective also sees the drift of the network's
    rollout; the gradient flows through all ``unroll`` network steps. A batch the teacher cannot
    step (``SimulationBlowUp``: a body grazing a wall can drive the flow in the gap past any
    sub-step count) is dropped, its scenes reset, and another drawn (``TEACHER_RETRIES`` times)."""
    for attempt in range(TEACHER_RETRIES):
        idx, state, boundary, params = run.pool.ask(cfg.batch_size, cfg.unroll)
        try:
            new, steps = unrolled_steps(run, cfg, net, idx, state, boundary, params)
            break
        except SimulationBlowUp:
            if attempt == TEACHER_RETRIES - 1:
                raise
            for i in idx.tolist():
                run.pool.reset(i)
    objective = torch.stack([t.objective for t in steps]).mean()
    run.opt.zero_grad(set_to_none=True)
    objective.backward()
    if cfg.grad_clip > 0:
        nn.utils.clip_grad_norm_(net.parameters(), cfg.grad_clip)
    run.opt.step()
    if run.average is not None:
        run.average.update_parameters(run.model)
    run.pool.tell(idx, new)
    run.iteration += 1
    mean = lambda name: None if getattr(steps[0], name) is None else \
        torch.stack([getattr(t, name).detach() for t in steps]).mean(0)
    return LossTerms(mean("momentum"), mean("boundary"), mean("total"), objective.detach(), mean("teacher"),
                     mean("energy"))


def unrolled_steps(run: Run, cfg: TrainConfig, net: nn.Module, idx: Tensor, state: FluidState,
                   boundary: Boundary, params: FluidParams) -> tuple[FluidState, list[LossTerms]]:
    """The network's ``unroll`` steps from the pool's ``state`` of the scenes ``idx`` (advanced
    between steps), each step's loss terms (with the teacher's j-step rollout as its target)."""
    new, target, steps = state, state, []
    for j in range(cfg.unroll):
        if j:
            boundary = run.pool.advance(idx)
        old = new
        new = network_forward(net, dropped_pressure(old, cfg.pressure_dropout), boundary, params, run.pool.grid,
                              cfg.bf16)
        terms = LossTerms(*run.loss_fn(old.a, old.p, new.a, new.p, boundary.mask, boundary.velocity, params.rho,
                                       params.mu, params.h))
        if run.teacher is not None:
            with torch.no_grad():
                fine = teacher_boundary(run.teacher, cfg, [run.pool.scenes[i] for i in idx.tolist()], boundary)
                target = run.teacher.step(target, fine, params)
                if not max_speeds(target.a, run.pool.grid.dx).max() <= RUNAWAY * cfg.pool.max_speed:
                    raise SimulationBlowUp("the teacher's step ran away (faster than RUNAWAY pool.max_speed)")
            terms = with_teacher(terms, cfg, target, new, boundary, params)
        steps.append(terms)
    return new, steps


def dropped_pressure(state: FluidState, probability: float) -> FluidState:
    """``state`` as the network's input with p_t zeroed in each sample with ``probability``
    (``TrainConfig.pressure_dropout``; the network carried p_t forward: its step's p changed by
    0.2-0.5 of the solver's on the held-out fish)."""
    if probability == 0:
        return state
    keep = (torch.rand(state.p.shape[0], 1, 1, 1, device=state.p.device) >= probability).to(state.p.dtype)
    return FluidState(state.a, state.p * keep)


def teacher_boundary(teacher, cfg: TrainConfig, scenes: list, boundary: Boundary) -> Boundary:
    """The ``scenes``' bodies as the teacher reads them: ``boundary`` itself at r = 1, else sampled
    on its ``boundary_grid`` (the walls r times as many cells thick)."""
    r = cfg.teacher_refinement
    return boundary if r == 1 else scene_boundaries(scenes, teacher.boundary_grid, boundary.mask.device, r)


def with_teacher(terms: LossTerms, cfg: TrainConfig, target: FluidState, new: FluidState, boundary: Boundary,
                 params: FluidParams) -> LossTerms:
    """``terms`` with L_t (and, with ``cfg.energy``, L_E) of ``new`` against the solver's
    ``target`` added to L and the objective."""
    new = FluidState(new.a.float(), new.p.float())
    lt = teacher_loss(new, target, params, cfg.pool.grid, boundary, cfg.teacher_pressure)
    le = energy_loss(new, target, boundary, params, cfg.pool.grid) if cfg.energy else None
    total = terms.total + cfg.teacher * lt + (0 if le is None else cfg.energy * le)
    return LossTerms(terms.momentum, terms.boundary, total, torch.log(total + EPS).mean(), lt, le)


def make_teacher(cfg: TrainConfig):
    """The numerical solver at `fishsim simulate`'s defaults (``NumericalConfig``: the joint stage
    the references are measured with) on the training grid, refined ``teacher_refinement`` times;
    None when ``teacher == 0``. (Until 2026-11-30 it took ``NumericalFluid``'s own keyword
    defaults, the split passes at 8 x 3: on the frequency study 45.2 / 79.2 / 127.1 / 181.5 /
    246.9 mm at 3-7 Hz against the joint stage's 45.4 / 80.2 / 128.3 / 184.0 / 249.2.)"""
    if cfg.teacher == 0:
        return None
    from fishsim.learn.evaluate import reference_fluid

    return reference_fluid(cfg.pool.grid, cfg.teacher_refinement)


@torch.no_grad()
def validate(model: HydroNet, cfg: TrainConfig, seed: int = 12345) -> float:
    """Mean log L (with L_t when training against the solver) over the second half of
    ``val_steps`` eval-mode steps of ``val_scenes`` fixed scenes started from rest (same scenes
    and motions every call)."""
    rng = np.random.default_rng(seed)
    scenes = [random_scene(rng, cfg.pool) for _ in range(cfg.val_scenes)]
    grid, dev = cfg.pool.grid, next(model.parameters()).device
    params = FluidParams(torch.tensor([s.rho for s in scenes], device=dev, dtype=torch.float32),
                         torch.tensor([s.mu for s in scenes], device=dev, dtype=torch.float32), cfg.pool.h)
    state = rest_state(grid, len(scenes), dev)
    was_training, losses, teacher = model.training, [], make_teacher(cfg)
    model.eval()
    for k in range(cfg.val_steps):
        scenes = [advance(s, cfg.pool, rng) for s in scenes]
        boundary = scene_boundaries(scenes, grid, dev)
        new = network_forward(model, state, boundary, params, grid, cfg.bf16)
        if k >= cfg.val_steps // 2:
            loss_cfg = LossConfig(cfg.beta, cfg.gamma, scheme=cfg.advection)
            terms = hydronet_loss(state, new, boundary, params, grid, loss_cfg)
            if teacher is not None:
                fine = teacher_boundary(teacher, cfg, scenes, boundary)
                target = teacher.step(FluidState(state.a.float(), state.p.float()), fine, params)
                terms = with_teacher(terms, cfg, target, new, boundary, params)
            losses.append(terms.objective.item())
        state = new
    model.train(was_training)
    return float(np.mean(losses))


# ------------------------------------------------------------------------ checkpoints


def save_checkpoint(run: Run, cfg: TrainConfig, out: Path, rank: int) -> None:
    """Rank 0: model, optimiser, counters, pool, RNG in ckpt.pt; other ranks: their pool, RNG and
    model copy (identical parameters under DDP) in ckpt_rank{r}.pt."""
    model = run.model.module if hasattr(run.model, "module") else run.model
    common = {"pool": run.pool.state_dict(), "torch_rng": torch.get_rng_state(), "iteration": run.iteration,
              "model": model.state_dict()}
    if rank > 0:
        atomic_save(common, out / f"ckpt_rank{rank}.pt")
        return
    if run.average is not None:
        common["average"] = run.average.state_dict()
    atomic_save({**common, "optimizer": run.opt.state_dict(),
                 "net": asdict(model.cfg), "config": asdict(cfg), "best_val": run.best_val, "best_swim": run.best_swim,
                 "last_val": run.last_val, "elapsed": run.elapsed}, out / "ckpt.pt")


def load_checkpoint(run: Run, out: Path, rank: int, lr: float | None = None) -> bool:
    """Restore ``run`` from ckpt.pt (and ckpt_rank{r}.pt for rank r > 0); ``lr`` replaces the
    saved learning rate. A compact checkpoint (``compact_checkpoint``: no pool) keeps the freshly
    drawn pool: everything else continues exactly. Returns whether the pool was restored."""
    main = load_file(out / "ckpt.pt", "checkpoint")
    own = main if rank == 0 else load_file(out / f"ckpt_rank{rank}.pt", "checkpoint")
    model = run.model.module if hasattr(run.model, "module") else run.model
    load_weights(model, main, out / "ckpt.pt")
    run.opt.load_state_dict(main["optimizer"])
    for group in run.opt.param_groups:  # the configured lr wins: resume with a smaller one to anneal
        group["lr"] = main["config"]["lr"] if lr is None else lr
    restored = "pool" in own
    if restored:
        run.pool.load_state_dict(own["pool"])
    if run.average is not None and "average" in main:   # else it starts from the next step's weights
        run.average.load_state_dict(main["average"])
    torch.set_rng_state(own["torch_rng"])
    run.iteration, run.best_val = main["iteration"], main["best_val"]
    run.best_swim = main.get("best_swim", math.inf)
    run.last_val, run.elapsed = main["last_val"], main["elapsed"]
    return restored


def compact_checkpoint(src: str | Path, dest: str | Path) -> Path:
    """ckpt.pt without its scene pool (model, optimiser, counters, RNG: ~3x smaller), small
    enough to commit so that training continues in a later sitting: copy it to
    ``<out_dir>/ckpt.pt`` and run with ``resume=true`` (the pool is redrawn)."""
    sd = torch.load(src, map_location="cpu", weights_only=False)
    sd.pop("pool", None)
    dest = Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    atomic_save(sd, dest)
    return dest


def save_weights(model: HydroNet, run: Run, path: Path, cfg: TrainConfig, score: float) -> None:
    """A model file (best.pt, best_swim.pt): the weights, the net config, the iteration, the score
    they were kept for and the fluid range they were trained for."""
    atomic_save({"model": model.state_dict(), "net": asdict(model.cfg), "iteration": run.iteration,
                 "val": score, "training_range": training_range(cfg.pool)}, path)


def checkpoint_weights(sd: dict) -> dict:
    """The weights a checkpoint or model file stands for: the moving average where a ckpt.pt
    keeps one (an ``ema`` run validates, swims and saves the average, so its model is that), else
    its model's."""
    if "average" not in sd:
        return sd["model"]
    return {k.removeprefix("module."): v for k, v in sd["average"].items() if k.startswith("module.")}


def export_model(checkpoint: str | Path, dest: str | Path, metadata: dict) -> Path:
    """Ship a trained model: the weights (``checkpoint_weights``) and net config of ``checkpoint`` (best.pt or ckpt.pt,
    no optimiser or pool) and the fluid range it was trained for to ``dest``, and ``metadata``
    (config, command, losses, evaluation) with that range to ``dest`` with suffix .json. Returns ``dest``; ``load_hydronet(dest)`` reads it back."""
    import json

    sd = torch.load(checkpoint, map_location="cpu", weights_only=False)
    dest = Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    trained = stored_range(sd, Path(checkpoint))
    if trained is None and "train_config" in metadata:
        trained = training_range(metadata["train_config"]["pool"])
    atomic_save({"model": checkpoint_weights(sd), "net": sd["net"], "iteration": sd["iteration"],
                 "val": sd.get("val", sd.get("best_val")), "training_range": trained}, dest)
    meta = {**metadata, "training_range": trained}
    dest.with_suffix(".json").write_text(json.dumps(meta, indent=2, default=str) + "\n")
    return dest


# ------------------------------------------------------------------------------ logging


class Logger:
    """CSV + TensorBoard (rank 0 only) and a rich progress bar (plain lines when not a terminal)."""

    COLUMNS = ("iteration", "seconds", "loss", "L_p", "L_b", "val", "it_per_s", "samples_per_s", "L_t", "L_E")

    def __init__(self, out: Path, cfg: TrainConfig, start: int):
        from rich.console import Console

        self.cfg, self.t0, self.i0 = cfg, time.perf_counter(), start
        trim_log(out / "log.csv", start, self.COLUMNS)
        new = not (out / "log.csv").exists()
        self.csv_file = open(out / "log.csv", "a", newline="")  # noqa: SIM115 (closed in close())
        self.csv = csv.writer(self.csv_file)
        if new:
            self.csv.writerow(self.COLUMNS)
        self.console = Console()
        try:
            from torch.utils.tensorboard import SummaryWriter

            self.tb = SummaryWriter(str(out / "tb"), purge_step=start + 1 if start else None)
        except ImportError:                       # tensorboard is the optional `train` extra
            self.tb = None
            self.console.print("[yellow]TensorBoard logging off (pip install 'fishsim[train]' for it); "
                               "log.csv has the same numbers[/]")
        self.bar = self._progress(start) if cfg.progress and self.console.is_terminal else None

    def _progress(self, start: int):
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

        bar = Progress(TextColumn("hydronet"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                       TextColumn("{task.fields[status]}"), console=self.console)
        bar.start()
        self.task = bar.add_task("train", total=self.cfg.iterations, completed=start, status="")
        return bar

    def log(self, run: Run, terms: LossTerms) -> None:
        dt = time.perf_counter() - self.t0
        rate = (run.iteration - self.i0) / max(dt, 1e-9)
        row = [run.iteration, round(run.elapsed, 1), terms.objective.item(), terms.momentum.mean().item(),
               terms.boundary.mean().item(), run.last_val, rate, rate * self.cfg.batch_size,
               *(math.nan if t is None else t.mean().item() for t in (terms.teacher, terms.energy))]
        self.csv.writerow(row)
        self.csv_file.flush()
        for name, value in zip(self.COLUMNS[2:], row[2:]):
            if math.isfinite(value) and self.tb is not None:
                self.tb.add_scalar(f"train/{name}", value, run.iteration)
        teach = ("" if terms.teacher is None else f"  L_t {row[8]:.2e}") + \
            ("" if terms.energy is None else f"  L_E {row[9]:.2e}")
        status = f"loss {row[2]:.3f}  L_p {row[3]:.2e}  L_b {row[4]:.2e}{teach}  val {row[5]:.3f}  {rate:.2f} it/s"
        if self.bar is not None:
            self.bar.update(self.task, completed=run.iteration, status=status)
        elif run.iteration % (10 * self.cfg.log_every) == 0:
            print(f"[{time.strftime('%H:%M:%S')}] it {run.iteration}: {status}", flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()
        self.csv_file.close()
        if self.tb is not None:
            self.tb.close()


def trim_log(path: Path, start: int, columns: tuple[str, ...]) -> None:
    """Drop the rows of log.csv after iteration ``start``, the checkpoint this run starts from
    (rows a run wrote after its last checkpoint before a SIGKILL, or of a replaced run), and a
    row cut short, so that a resumed log holds each iteration once; a log of a version with fewer
    ``columns`` gets the new ones (nan in its rows)."""
    if not path.exists():
        return
    lines = path.read_text().splitlines(keepends=True)
    keep = lines[:1] + [line for line in lines[1:] if _row_iteration(line) is not None
                        and _row_iteration(line) <= start]
    old = lines[0].rstrip("\n").split(",") if lines else list(columns)
    if old != list(columns[:len(old)]):
        raise ConfigError(f"{path} holds another run's log (columns {old}); give another out_dir")
    pad = ",nan" * (len(columns) - len(old))
    if len(keep) < len(lines) or pad:
        atomic_text(path, "".join([",".join(columns) + "\n"] + [line.rstrip("\n") + pad + "\n" for line in keep[1:]]))


def _row_iteration(line: str) -> int | None:
    """The iteration of a whole log.csv row (None for a row cut short)."""
    try:
        return int(line.split(",", 1)[0]) if line.endswith("\n") else None
    except ValueError:
        return None


# ---------------------------------------------------------------------------------- run


def _setup_distributed(cfg: TrainConfig) -> tuple[int, int, torch.device]:
    """(rank, world size, device); initialises torch.distributed under torchrun (WORLD_SIZE > 1):
    gloo on CPU, nccl on CUDA (one GPU per local rank)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    device = torch.device(cfg.device)
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
    rank = dist.get_rank() if world > 1 else 0
    if device.type == "cuda":
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        torch.cuda.set_device(device)
    return rank, world, device


def build(cfg: TrainConfig, rank: int, world: int, device: torch.device) -> tuple[Run, nn.Module]:
    """Model (seeded), optimiser and pool (seeded per rank); the second value is what the training
    step calls (DDP wrapper and/or compiled module)."""
    torch.manual_seed(cfg.seed)
    model = HydroNet(cfg.net).to(device)
    model.freeze_norm = cfg.freeze_norm
    model.train()
    if cfg.channels_last:
        model = model.to(memory_format=torch.channels_last)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    pool = ScenePool(cfg.pool, cfg.batch_size, seed=cfg.seed * 1000 + rank, device=device)
    net: nn.Module = model
    if world > 1:
        net = nn.parallel.DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None)
    if cfg.compile:
        net = torch.compile(net)
    average = None
    if cfg.ema > 0:
        from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

        average = AveragedModel(model, multi_avg_fn=get_ema_multi_avg_fn(cfg.ema), use_buffers=True)
    return Run(model, opt, pool, make_loss_fn(cfg), make_teacher(cfg), average), net


def _due(run: Run, cfg: TrainConfig, last_save: float, world: int) -> bool:
    """Checkpoint now? Every ``ckpt_every`` iterations, or ``ckpt_minutes`` after the last save
    (rank 0's clock decides, broadcast so that all ranks save at the same iteration)."""
    due = run.iteration % cfg.ckpt_every == 0
    if run.iteration % cfg.log_every == 0:
        timed = torch.tensor([float(time.perf_counter() - last_save > 60 * cfg.ckpt_minutes)],
                             device=run.pool.device)  # NCCL broadcasts CUDA tensors only
        if world > 1:
            dist.broadcast(timed, 0)
        due = due or bool(timed.item())
    return due


def _after_step(run: Run, cfg: TrainConfig, out: Path, rank: int, world: int, log: Logger | None,
                terms: LossTerms, last_save: float) -> float:
    """Validation (+ best.pt), logging and checkpointing after one iteration; returns the time of
    the last checkpoint."""
    if rank == 0 and run.iteration % cfg.val_every == 0:
        run.last_val = validate(run.evaluated, cfg)
        if run.last_val < run.best_val:
            run.best_val = run.last_val
            save_weights(run.evaluated, run, out / "best.pt", cfg, run.best_val)
    if rank == 0 and cfg.swim_every and run.iteration % cfg.swim_every == 0:
        save_weights(run.evaluated, run, out / "swim_model.pt", cfg, math.nan)
        error = swim_check.check(out / "swim_model.pt", out, cfg, run.iteration)
        if error < run.best_swim:
            run.best_swim = error
            save_weights(run.evaluated, run, out / "best_swim.pt", cfg, error)
    if log is not None and run.iteration % cfg.log_every == 0:
        log.log(run, terms)
    if _due(run, cfg, last_save, world):
        save_checkpoint(run, cfg, out, rank)
        return time.perf_counter()
    return last_save


def _restore(run: Run, cfg: TrainConfig, out: Path, rank: int, device: torch.device) -> None:
    """resume: everything from out/ckpt.pt; else init_from: the weights only; trained weights on
    a freshly drawn pool then age it first (``cfg.warm_pool``). A run already in ``out`` is
    continued (resume) or replaced (overwrite), never silently restarted."""
    if cfg.resume and not (out / "ckpt.pt").exists():
        raise ConfigError(f"resume=true but {out} holds no ckpt.pt to continue; drop resume=true to start "
                          "training, or give the out_dir of the run to continue")
    if not (cfg.resume or cfg.overwrite) and (out / "ckpt.pt").exists():
        raise ConfigError(f"{out} already holds a training run (ckpt.pt); pass resume=true to continue it, "
                          "overwrite=true to start again, or another out_dir")
    trained_on_fresh_pool = False
    if cfg.resume:
        trained_on_fresh_pool = not load_checkpoint(run, out, rank, cfg.lr)
    elif cfg.init_from:
        load_weights(run.model, load_file(Path(cfg.init_from), "model (init_from)"), Path(cfg.init_from))
        trained_on_fresh_pool = True
    if trained_on_fresh_pool and cfg.warm_pool:
        t0 = time.perf_counter()
        run.pool.warm(network_step(run, cfg), cfg.warm_pool, cfg.batch_size)
        if rank == 0:
            print(f"warmed the freshly drawn scene pool: each scene stepped 0..{cfg.warm_pool} times by the "
                  f"network ({time.perf_counter() - t0:.0f} s; warm_pool=0: off)", flush=True)


def network_step(run: Run, cfg: TrainConfig):
    """(state, boundary, params) -> the network's next FluidState (``network_forward``), without
    gradient and in eval mode (BatchNorm's running statistics, left unchanged)."""

    @torch.no_grad()
    def step(state: FluidState, boundary: Boundary, params: FluidParams) -> FluidState:
        was_training = run.model.training
        run.model.eval()
        try:
            return network_forward(run.model, state, boundary, params, run.pool.grid, cfg.bf16)
        finally:
            run.model.train(was_training)

    return step


class StopRequest:
    """What SIGINT / SIGTERM ask of a training run. The first sets ``signal`` and the loop stops
    at the next iteration boundary, so the checkpoint it saves (model, Adam, pool and its RNG,
    torch's RNG) continues bit for bit; a second one stops at once (KeyboardInterrupt, or
    Terminated for SIGTERM) without saving, the last checkpoint kept."""

    def __init__(self) -> None:
        self.signal: str | None = None

    def handle(self, signum, frame) -> None:
        name = "SIGTERM" if signum == signal.SIGTERM else "SIGINT"
        if self.signal is not None:
            raise (Terminated if name == "SIGTERM" else KeyboardInterrupt)(f"a second {name}")
        self.signal = name


@contextlib.contextmanager
def stop_requests():
    """Within: SIGINT and SIGTERM set the yielded StopRequest (also for a background job whose
    shell ignores SIGINT, and ``kill PID``); the previous handlers are restored on exit."""
    stop = StopRequest()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return
    old = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    for s in old:
        signal.signal(s, stop.handle)
    try:
        yield stop
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def _stop_now(stop: StopRequest, world: int, device: torch.device) -> bool:
    """Has any rank been asked to stop? (all ranks agree, so they stop at the same iteration)"""
    if world == 1:
        return stop.signal is not None
    code = torch.tensor([{None: 0, "SIGINT": 1, "SIGTERM": 2}[stop.signal]], device=device)
    dist.all_reduce(code, op=dist.ReduceOp.MAX)
    stop.signal = {0: None, 1: "SIGINT", 2: "SIGTERM"}[int(code.item())]
    return stop.signal is not None


def _loop(run_: Run, cfg: TrainConfig, net: nn.Module, out: Path, rank: int, world: int,
          log: Logger | None) -> tuple[str | bool, LossTerms | None, bool]:
    """Iterate until ``cfg.iterations`` or a stop request; returns (the stopping signal's name or
    False, the last loss terms, whether the state is whole: False after a forced stop)."""
    terms, last_save = None, time.perf_counter()
    t_last = last_save
    with stop_requests() as stop:
        try:
            while run_.iteration < cfg.iterations and not _stop_now(stop, world, run_.pool.device):
                terms = train_step(run_, cfg, net)
                now = time.perf_counter()
                run_.elapsed, t_last = run_.elapsed + now - t_last, now
                last_save = _after_step(run_, cfg, out, rank, world, log, terms, last_save)
        except KeyboardInterrupt as err:            # a second signal (Terminated is one too)
            return ("SIGTERM" if isinstance(err, Terminated) else "SIGINT"), terms, False
    return (stop.signal or False) if run_.iteration < cfg.iterations else False, terms, True


def _run_folder(cfg: TrainConfig, rank: int, world: int) -> Path:
    """The run's folder, made and locked by rank 0 (``make_out_dir``: out_dir, or a new unique
    outputs/train-hydronet/<time>); under torchrun the other ranks are told which."""
    from fishsim.io.outdir import make_out_dir

    if cfg.resume and not cfg.out_dir:
        raise ConfigError(RESUME_NEEDS_OUT_DIR)
    if world == 1:
        return make_out_dir("train-hydronet", cfg.out_dir)
    box: list = [None]
    if rank == 0:
        try:
            box = [str(make_out_dir("train-hydronet", cfg.out_dir))]
        except ConfigError as err:
            box = [err]
    dist.broadcast_object_list(box, 0)
    if isinstance(box[0], Exception):
        raise ConfigError(str(box[0]))
    return Path(box[0])


def run(cfg: TrainConfig | dict) -> dict:
    """Train HydroNet as configured (a TrainConfig or the same as a nested dict); returns a
    summary (iterations, losses, this session's iterations/s and samples/s, paths; interrupted:
    the stopping signal's name or False; saved: whether the checkpoint is of the last iteration)."""
    cfg = train_config(cfg)
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    rank, world, device = _setup_distributed(cfg)
    cfg = replace(cfg, bf16=resolve_bf16(cfg.bf16, device.type))
    out = _run_folder(cfg, rank, world)
    run_, net = build(cfg, rank, world, device)
    _restore(run_, cfg, out, rank, device)
    log = Logger(out, cfg, run_.iteration) if rank == 0 else None
    start, t0 = run_.iteration, time.perf_counter()
    interrupted, terms, whole = _loop(run_, cfg, net, out, rank, world, log)
    if whole:
        save_checkpoint(run_, cfg, out, rank)
    if log is not None:
        log.close()
    if world > 1:
        dist.destroy_process_group()
    rate = (run_.iteration - start) / max(time.perf_counter() - t0, 1e-9)
    return {"iteration": run_.iteration, "interrupted": interrupted, "saved": whole, "best_val": run_.best_val,
            "last_val": run_.last_val, "loss": terms.objective.item() if terms is not None else math.nan,
            "it_per_s": rate, "samples_per_s": rate * cfg.batch_size * world, "out_dir": str(out), "rank": rank}


# ------------------------------------------------------------------------ command line


def _from_dict(cls, d: dict):
    """Dataclass ``cls`` from a plain (nested) dict; lists become tuples; unknown keys fail."""
    names = {f.name: f for f in fields(cls)}
    unknown = set(d) - set(names)
    if unknown:
        raise ValueError(f"unknown {cls.__name__} keys {sorted(unknown)}; known: {sorted(names)}")
    defaults = cls()
    kw = {}
    for k, v in d.items():
        cur = getattr(defaults, k)
        kw[k] = _from_dict(type(cur), v) if is_dataclass(cur) else tuple(v) if isinstance(v, list) else v
    return cls(**kw)


def train_config(d: dict | TrainConfig) -> TrainConfig:
    """A TrainConfig from a plain dict (e.g. ``OmegaConf.to_container`` of the Hydra config) or
    from a TrainConfig whose ranges came back from OmegaConf as lists (made tuples again)."""
    return _from_dict(TrainConfig, asdict(d) if isinstance(d, TrainConfig) else d)
