"""The optimisation problem: which parameters move (bounds, scales), what is maximised (the
objective J), and the evaluation of a batch of candidates as ONE batched rollout.

Parameters live in normalised coordinates z in [0, 1]^P, the optimisers' space:

    x = lo + z (hi - lo)                 (linear scale)
    x = lo (hi / lo)^z                   (log scale, lo > 0)

Objectives J (maximised; every optimiser minimises -J), per fish, over an episode of T frames of
h seconds (t_k = k h), with F_x(t) the total hydrodynamic x force on the fish (N per unit depth),
P(t) = -sum_i f_ext,i(t) . (qdot_i(t) + U_t e_x) the power it gives the fluid (W per unit depth, in
the water's rest frame) and s(t) = x_c(t) + h sum_{k < t} U_k the distance its mass centroid has
swum through the water (x_c alone in free swimming; in a swim tunnel, where the fish is held and
the water passes it at U, the water's travel is added):

    thrust              J = h sum_t F_x(t)                                  N s / m
                        (the forward impulse; the paper's L = -sum_t F_x(t) = -J / h, Fig. 5)
    distance            J = x_head(T) - x_head(0) (+ h sum_t U_t)           m
    speed               J = (s(T) - s(T - W)) / W,  W = N / f               m/s
                        (the mean speed over the last N = ``cycles`` tail beats of the fish's
                        frequency f: over whole beats the surge within a beat cancels; s at the
                        window's start is interpolated linearly between frames, so J is smooth
                        in f, its window never jumps by a frame)
    cost_of_transport   J = (s(T) - s(0)) / (h sum_t P(t))                  m^2 / J
                        (distance per unit of work done on the fluid per unit depth: the
                        transport efficiency; the work the fluid receives stands in for the
                        muscles' work, which the PD solid does not separate from elastic energy.
                        A fish that did no positive work is failed: its J is undefined)

thrust is measured on a fish held in x (``hold_x=true``, the paper's set-up) or a free one;
the others on a free fish or in the swim tunnel (``tunnel=true``).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field

import torch
from torch import Tensor

from fishsim.errors import ConfigError, FishsimError, SimulationBlowUp
from fishsim.optimize.config import ObjectiveConfig, ParamSpec


@dataclass
class Space:
    """The map between normalised z in [0, 1]^P and physical parameters x (module docstring)."""

    names: list[str]
    specs: list[ParamSpec] = field(repr=False)

    def to_x(self, z: Tensor) -> Tensor:
        """x [..., P] from z [..., P] (differentiable)."""
        cols = []
        for i, s in enumerate(self.specs):
            zi = z[..., i]
            cols.append(s.lower * (s.upper / s.lower) ** zi if s.log else s.lower + zi * (s.upper - s.lower))
        return torch.stack(cols, -1)

    def to_z(self, x: Tensor) -> Tensor:
        cols = []
        for i, s in enumerate(self.specs):
            xi = x[..., i]
            cols.append(torch.log(xi / s.lower) / math.log(s.upper / s.lower) if s.log
                        else (xi - s.lower) / (s.upper - s.lower))
        return torch.stack(cols, -1)


def objective(cfg: ObjectiveConfig, metrics: dict[str, Tensor], h: float, start: dict[str, Tensor],
              frequency: Tensor) -> Tensor:
    """J [B] of the module docstring from a rollout's metrics ([T, B] each); ``start``: the
    metrics' values at the initial state ([B]); frequency: each fish's gait frequency [B] (Hz).
    NaN where J is undefined (cost of transport without positive work)."""
    water = h * metrics["tunnel_u"].sum(0)
    if cfg.name == "thrust":
        return h * metrics["thrust_x"].sum(0)
    if cfg.name == "distance":
        return metrics["head_x"][-1] - start["head_x"] + water
    s = travel(metrics, h)
    if cfg.name == "speed":
        return mean_speed(s, start["centroid_x"], h, cfg.cycles / frequency)
    if cfg.name == "cost_of_transport":
        work = h * metrics["power"].sum(0)
        return (s[-1] - start["centroid_x"]) / torch.where(work > 0, work, torch.full_like(work, math.nan))
    raise ConfigError(f"unknown objective '{cfg.name}'")


def travel(metrics: dict[str, Tensor], h: float) -> Tensor:
    """s(t) [T, B] (m): the centroid's x plus the water the swim tunnel has passed it by."""
    return metrics["centroid_x"] + h * torch.cumsum(metrics["tunnel_u"], 0)


def mean_speed(s: Tensor, s0: Tensor, h: float, window: Tensor) -> Tensor:
    """(s(T) - s(T - W)) / W [B] (m/s) from positions s [T, B] at t = h, 2h, ..., T h and s0 [B]
    at t = 0, over the last ``window`` W [B] seconds, s(T - W) interpolated linearly between
    frames (smooth in W). A window longer than the episode is cut to it (W = T h)."""
    full = torch.cat([s0[None].to(s), s])                          # [T + 1, B] at t = 0, h, ..., T h
    T = s.shape[0]
    window = window.to(s).clamp(max=T * h)
    u = ((T * h - window) / h).to(s)                               # the window's start in frames
    k = u.detach().floor().clamp(0, T - 1).long()
    w = u - k
    at = lambda i: full.gather(0, i[None])[0]
    start = at(k) * (1 - w) + at(k + 1) * w
    return (full[-1] - start) / window


@dataclass
class Evaluation:
    """The result of evaluating B candidates: J [B] (NaN where failed), dJ/dz [B, P] (gradient
    runs), failures {b: (frame, reason)}, fish-frames simulated, wall time (s)."""

    J: Tensor
    grad_z: Tensor | None
    failures: dict
    frames: int
    seconds: float


class Problem:
    """Candidates z [B, P] -> objective J [B], by one batched, checkpointed rollout of the episode
    built from the config (fishsim.episode.build_episode with B = 1, then each
    optimised parameter set per candidate). segment: gradient-checkpoint segment (frames);
    truncate: truncated backpropagation window (frames, 0: full; fishsim.rollout.rollout)."""

    def __init__(self, cfg, space: Space, objective_cfg: ObjectiveConfig, segment: int = 25, truncate: int = 0):
        from fishsim.episode import build_episode
        from fishsim.resources import check_memory

        check_memory(cfg, 1, gradient_frames=cfg.frames, segment=segment)      # a gradient iteration
        o = getattr(cfg, "optimizer", None)
        popsize = getattr(o, "popsize", None) or 8
        check_memory(cfg, min(popsize, getattr(o, "max_batch", None) or popsize))   # a CMA-ES batch
        self.cfg, self.space, self.objective_cfg, self.segment = cfg, space, objective_cfg, segment
        self.truncate = truncate
        self.episode = build_episode(cfg)
        self.base = self.episode.params
        self._check_amplitude()

    def _check_amplitude(self) -> None:
        """The largest amplitude the bounds allow must keep every muscle's contraction below 1."""
        if "amplitude" not in self.space.names:
            return
        hi = self.space.specs[self.space.names.index("amplitude")].upper
        c = self.base.controller
        peak = float(dataclasses.replace(c, C=torch.full_like(c.C, hi)).peak_contraction(self.episode.swimmer.solid)[0])
        if peak >= 1:
            raise ConfigError(f"params.amplitude.upper = {hi:g} 1/m contracts a muscle by {peak:.2f} >= 1; "
                              f"use upper < {hi / peak:.4g}")

    def initial_x(self) -> list[float]:
        """Each parameter's start: its ``init`` or the episode config's value, clipped to bounds."""
        values = self.current(self.base)
        return [float(min(max(s.init if s.init is not None else v, s.lower), s.upper))
                for s, v in zip(self.space.specs, values)]

    def current(self, params) -> list[float]:
        c = params.controller
        now = {"frequency": float(c.omega[0]) / (2 * math.pi), "amplitude": float(c.C[0]),
               "wave_number": float(c.gamma[0]), "youngs_modulus": float(params.E[0])}
        return [now[n] for n in self.space.names]

    def params_for(self, x: Tensor):
        """SwimParams of B candidates x [B, P] (physical units), differentiable w.r.t. x."""
        from fishsim.fluid.factory import fluid_params

        B, base = x.shape[0], self.base
        col = {n: x[:, i] for i, n in enumerate(self.space.names)}
        c = base.controller
        pick = lambda name, value: col[name] if name in col else value.expand(B)
        omega = 2 * math.pi * col["frequency"] if "frequency" in col else c.omega.expand(B)
        controller = dataclasses.replace(c, C=pick("amplitude", c.C), omega=omega, gamma=pick("wave_number", c.gamma))
        fluid = fluid_params(self.cfg.fluid, B, self.cfg.h, x.device)
        return dataclasses.replace(base, controller=controller, E=pick("youngs_modulus", base.E), fluid=fluid)

    def evaluate(self, z: Tensor, gradient: bool = False, isolate: bool = True) -> Evaluation:
        """J [B] of candidates z [B, P] (normalised, on the CPU); with ``gradient`` also dJ/dz by
        autograd through the checkpointed rollout, run on the episode's device (both returned on
        the CPU). ``isolate``: a failing candidate is marked (J = NaN,
        its reason in ``failures``) and the others carry on; else a blow-up raises."""
        from fishsim.rollout import rollout

        t0 = time.perf_counter()
        sw, cfg = self.episode.swimmer, self.cfg
        z = z.detach().to(self.episode.device, torch.float64).clone().requires_grad_(gradient)
        failures: dict = {} if isolate else None
        with torch.set_grad_enabled(gradient):
            x = self.space.to_x(z)
            params = self.params_for(x)
            state = sw.initial_state(params, self.episode.origin)
            start = _start_metrics(sw, state)
            try:
                _, metrics = rollout(sw, state, params, cfg.frames, segment=self.segment if gradient else 0,
                                     failures=failures, truncate=self.truncate)
                J = objective(self.objective_cfg, metrics, cfg.h, start, params.controller.omega / (2 * math.pi))
                mark_undefined(J, failures, cfg.frames, self.objective_cfg.name)
            except SimulationBlowUp:
                if failures is None or len(failures) < z.shape[0]:
                    raise
                J = torch.full((z.shape[0],), math.nan, dtype=torch.float64)  # all failed: each is recorded
            grad = None
            if gradient:
                if not bool(torch.isfinite(J).all()):
                    raise SimulationBlowUp(f"the objective is {J.tolist()} (not finite"
                                           f"{': ' + UNDEFINED[self.objective_cfg.name] if self.objective_cfg.name in UNDEFINED else ''})")
                (grad,) = torch.autograd.grad(J.sum(), z)
                if not bool(torch.isfinite(grad).all()):
                    raise SimulationBlowUp(f"the gradient dJ/dz is {grad.tolist()} (not finite) at J = {J.tolist()}")
        J = J.detach().cpu().clone()
        for b in (failures or {}):
            J[b] = float("nan")
        frames = z.shape[0] * cfg.frames * (2 if gradient and self.segment < cfg.frames else 1)
        return Evaluation(J, None if grad is None else grad.cpu(), failures or {}, frames, time.perf_counter() - t0)

    def evaluate_population(self, z: Tensor, max_batch: int | None = None, executor=None) -> Evaluation:
        """J [B] of a gradient-free population z [B, P] in chunks of at most ``max_batch`` fish
        (None: one batch), each ONE batched rollout with failing members isolated: run here one
        after another, or with ``executor`` (a submitit executor) as one job each, in parallel.
        The chunks' results are joined in order; ``seconds`` is the wall time of the whole."""
        t0 = time.perf_counter()
        chunks = list(z.split(max_batch or z.shape[0]))
        if executor is None:
            parts = [self.evaluate(c) for c in chunks]
        else:
            jobs = [executor.submit(evaluate_chunk, self.cfg, c, self.segment, self.truncate) for c in chunks]
            parts = [_result(job) for job in jobs]
        failures, offset = {}, 0
        for c, part in zip(chunks, parts):
            failures.update({b + offset: why for b, why in part.failures.items()})
            offset += c.shape[0]
        return Evaluation(torch.cat([part.J for part in parts]), None, failures, sum(part.frames for part in parts),
                          time.perf_counter() - t0)


UNDEFINED = {"cost_of_transport": "the fish did no positive work on the fluid, so its cost of transport is undefined"}


def mark_undefined(J: Tensor, failures: dict | None, frames: int, name: str) -> None:
    """Record each member whose objective is not finite (and that did not fail before) as failed
    at the episode's end, with the reason (UNDEFINED)."""
    for b in torch.nonzero(~torch.isfinite(J.detach())).flatten().tolist() if failures is not None else []:
        failures.setdefault(b, (frames, f"objective {name} is not finite: {UNDEFINED.get(name, 'check the episode')}"))


def _result(job) -> Evaluation:
    """A submitted chunk's evaluation; a job that died (killed, out of time or memory) is one line."""
    from submitit.core.utils import FailedJobError, UncompletedJobError

    try:
        return job.result()
    except (FailedJobError, UncompletedJobError) as err:
        first = (str(err).strip().splitlines() or [type(err).__name__])[0]
        raise FishsimError(f"population job {job.job_id} failed: {first} (its log: {job.paths.stderr})") from None


def evaluate_chunk(cfg, z: Tensor, segment: int, truncate: int) -> Evaluation:
    """One chunk of a population evaluated in a process of its own (a submitit job): the
    problem rebuilt from the config, then Problem.evaluate(z)."""
    space = Space(list(cfg.params), list(cfg.params.values()))
    return Problem(cfg, space, cfg.objective, segment=segment, truncate=truncate).evaluate(z)


def _start_metrics(swimmer, state) -> dict[str, Tensor]:
    """The metrics' positions at the initial state (forces zero)."""
    from fishsim.rollout import FrameOutput, frame_metrics

    zero = torch.zeros_like(state.q)
    out = FrameOutput(f_ext=zero, contraction=torch.zeros(1))
    return {k: v.detach() for k, v in frame_metrics(swimmer, state, out).items()}
