"""HydroNet against the numerical solver on held-out scenes (issue: "evaluation").

Scenes on the paper's tank (100 x 300 cells, dx = 2.5 mm, h = 0.01 s, closed, walls 3/5 cells),
none of them drawn by the training pool:

* ``cylinder_U``: a disc of radius ``radius`` (default 1 cm = 8 cells across) towed along x at
  U m/s from x = 0.1 m, started impulsively;
* ``fish_f``: a 0.2 m fish at the tank centre beating at f Hz with the pool's prescribed
  kinematics (carangiform envelope, one wavelength per body, tail amplitude ``fish_amp`` L).

Protocol, per scene (all batched): the numerical solver runs ``warmup`` steps from rest; from that
common state S_0

* one step of each model -> relative errors of v and of the mean-free p on fluid cells;
* ``steps`` steps of each model (each on its own rollout) -> the same errors at the end, the mean
  IMEX residual L_p of each model's own steps (grid units, ``loss.momentum_loss``), max |div v|,
  and the IBM pressure force on the body (coupling defaults) every step: mean drag/thrust.

Two checks of the network's own dynamics over longer rollouts from rest (``energy_checks``):

* still fish: a fish of zero amplitude at the tank centre in still water for ``still_steps``
  steps of the network: max |v| at the end (m/s; the exact answer is 0);
* kinetic energy: the prescribed fish at ``energy_frequency`` Hz, ``energy_steps`` steps from rest
  with each model: E = rho / 2 sum_f (1 - b_f) v_f^2 dx^2 (J/m) and the ratio E_net / E_ref.

Relative errors: e_v = |v_net - v_num| / |v_num| over faces weighted by the fluid face mask
(1 - b); e_p likewise over cells weighted by 1 - b, both pressures made mean free over the fluid.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from fishsim.coupling.ibm import ibm_force
from fishsim.coupling.mask import SIGMA
from fishsim.fields import Boundary, FluidModel, FluidParams, FluidState
from fishsim.fluid.factory import make_walls
from fishsim.fluid.grid import curl, divergence, union, vorticity
from fishsim.fluid.hydronet.config import EvalConfig
from fishsim.fluid.hydronet.loss import mean_free, momentum_loss
from fishsim.fluid.residual import fluid_face_masks
from fishsim.learn.pool import Fish, Motion, fish_boundaries, fish_surface, mask_from_distance


class Scenes:
    """The held-out scenes' boundaries and body surfaces at step k (time k h)."""

    def __init__(self, cfg: EvalConfig, device=None):
        self.cfg, self.grid, self.device = cfg, cfg.tank.grid, device
        self.names = [f"cylinder_{u:g}" for u in cfg.speeds] + [f"fish_{f:g}Hz" for f in cfg.frequencies]
        self.still = Motion(cfg.tank.centre, (0.0, 0.0), (0.0, 0.0), (0.0, 0.0), (0.0, 0.0),   # at the centre
                            0.0, 0.0, 0.0, 0.0, 0.0, 0.0, (0.1, 0.03))
        self.fish = [self.swimmer(f) for f in cfg.frequencies]
        self.tank = make_walls(cfg.tank, torch.float32, device)
        n = 64
        th = torch.arange(n, dtype=torch.float32, device=device) * (2 * math.pi / n)
        self.circle = cfg.radius * torch.stack([torch.cos(th), torch.sin(th)], -1)  # ccw [n, 2]

    def centre(self, u: float, k: int) -> tuple[float, float]:
        return 0.1 + u * k * self.cfg.h, self.cfg.tank.centre[1]

    def swimmer(self, frequency: float, amplitude: float | None = None) -> Fish:
        """The 0.2 m fish held at the tank's centre, beating at ``frequency`` Hz with tail amplitude
        ``amplitude`` L (default fish_amp)."""
        amp = self.cfg.fish_amp if amplitude is None else amplitude
        return Fish(0.2, amp * 0.2, frequency, 2 * math.pi / 0.2, 0.0, 0.2, self.still)

    def boundary(self, k: int) -> Boundary:
        """b, v_d [B, ., H, W] of every scene at step k (walls included)."""
        x = self.grid.cell_centres(device=self.device)
        parts = []
        for u in self.cfg.speeds:
            cx, cy = self.centre(u, k)
            s = self.cfg.radius - torch.sqrt((x[..., 0] - cx) ** 2 + (x[..., 1] - cy) ** 2)
            b = mask_from_distance(s, SIGMA)[None, None]
            v = torch.zeros(1, 2, self.grid.H, self.grid.W, device=self.device)
            v[:, 0] = u
            parts.append(Boundary(b, v))
        t = k * self.cfg.h
        parts += fish_boundaries(self.fish, [t] * len(self.fish), [SIGMA] * len(self.fish), self.grid, self.device)
        parts = [union(self.tank, p) for p in parts]
        return Boundary(torch.cat([p.mask for p in parts]), torch.cat([p.velocity for p in parts]))

    def surfaces(self, k: int) -> list[Tensor]:
        """Each body's ccw surface polyline [1, S, 2] at step k."""
        out = [(self.circle + torch.tensor(self.centre(u, k), device=self.device))[None] for u in self.cfg.speeds]
        t = k * self.cfg.h
        out += [torch.as_tensor(fish_surface(f, t)[0], dtype=torch.float32, device=self.device)[None]
                for f in self.fish]
        return out


def reference_fluid(grid, refinement: int = 1):
    """The numerical fluid at `fishsim simulate`'s defaults (``NumericalConfig``: the joint stage)
    on ``grid``, refined ``refinement`` times: the reference HydroNet is trained against
    (train-hydronet's teacher) and judged against (``fishsim validate suite=hydronet``)."""
    from fishsim.config import NumericalConfig
    from fishsim.fluid.factory import numerical_stepping
    from fishsim.fluid.numerical import NumericalFluid

    return NumericalFluid(grid, refinement=refinement, **numerical_stepping(NumericalConfig()))


def relative_errors(net: FluidState, ref: FluidState, mask: Tensor, dx: float) -> tuple[Tensor, Tensor]:
    """(e_v, e_p) [B]: fluid-weighted relative L2 errors of v and of the mean-free p."""
    wv = fluid_face_masks(mask)
    vn, vr = curl(net.a, dx), curl(ref.a, dx)
    num = sum((w * (a - b) ** 2).flatten(1).sum(1) for a, b, w in zip(vn, vr, wv))
    den = sum((w * b**2).flatten(1).sum(1) for b, w in zip(vr, wv))
    wp = 1 - mask
    pn, pr = mean_free(net.p, wp), mean_free(ref.p, wp)
    e_p = ((wp * (pn - pr) ** 2).flatten(1).sum(1) / (wp * pr**2).flatten(1).sum(1)).sqrt()
    return (num / den).sqrt(), e_p


def body_forces(scenes: Scenes, state: FluidState, boundary: Boundary, k: int) -> Tensor:
    """Total IBM pressure force on each body [B, 2] (N per unit depth; coupling defaults)."""
    out = []
    for n, qs in enumerate(scenes.surfaces(k)):
        f = ibm_force(qs, state.p[n : n + 1], boundary.mask[n : n + 1], scenes.grid)
        out.append(f.sum(1))
    return torch.cat(out)


def common_start(reference: FluidModel, scenes: Scenes, params: FluidParams, each_step=None) -> FluidState:
    """S_0: the ``reference``'s ``warmup`` steps from rest on every scene, the state all models step
    from; ``each_step(k)`` after step k (progress)."""
    state = reference.initial_state(len(scenes.names), device=scenes.device)
    for k in range(1, scenes.cfg.warmup + 1):
        state = reference.step(state, scenes.boundary(k), params)
        if each_step:
            each_step(k)
    return state


@dataclass
class HeldOutStep:
    """The held-out scenes at S_0 (``common_start``), the step's boundary and the reference's step
    from S_0, ``reference``: what every model's one-step error is measured against."""

    scenes: Scenes
    params: FluidParams
    start: FluidState
    boundary: Boundary
    reference: FluidState


@torch.no_grad()
def held_out_step(reference: FluidModel | None = None, cfg: EvalConfig = EvalConfig(), device=None,
                  each_step=None) -> HeldOutStep:
    """``cfg``'s scenes, their common start S_0 by ``reference`` (None: ``reference_fluid`` on the
    scenes' grid) and its one step from there; ``each_step(k)`` after warm-up step k."""
    scenes = Scenes(cfg, device)
    B = len(scenes.names)
    reference = reference_fluid(scenes.grid) if reference is None else reference
    params = FluidParams(torch.full((B,), cfg.rho, device=device), torch.full((B,), cfg.mu, device=device), cfg.h)
    start = common_start(reference, scenes, params, each_step)
    boundary = scenes.boundary(cfg.warmup + 1)
    return HeldOutStep(scenes, params, start, boundary, reference.step(start, boundary, params))


def held_out_rollout(model: FluidModel, held: HeldOutStep, cfg: EvalConfig):
    """``model``'s ``cfg.steps`` steps of the held-out scenes from their common start ``held.start``:
    yields (k, S_k-1, S_k, boundary_k) for k = warmup + 1 .. warmup + steps."""
    state = held.start
    for k in range(cfg.warmup + 1, cfg.warmup + 1 + cfg.steps):
        boundary = held.scenes.boundary(k)
        new = model.step(state, boundary, held.params)
        yield k, state, new, boundary
        state = new


@dataclass
class Evaluation:
    """metrics: {scene: {metric: value}}; final: the last rollout states' pressure and vorticity
    [B, H, W] of "net" and "ref" and the mask, for pictures."""

    metrics: dict
    final: dict


@torch.no_grad()
def evaluate(net: FluidModel, reference: FluidModel, cfg: EvalConfig = EvalConfig(), device=None,
             progress=None) -> Evaluation:
    """Every metric of the module docstring, per scene, and the final fields.

    ``progress``: optional callable(step_done, steps_total) for a progress bar."""
    total = cfg.warmup + 1 + 2 * cfg.steps
    first = held_out_step(reference, cfg, device, lambda k: progress and progress(k, total))
    scenes, params, s0, grid = first.scenes, first.params, first.start, first.scenes.grid
    done = cfg.warmup
    bd = first.boundary
    one_v, one_p = relative_errors(net.step(s0, bd, params), first.reference, bd.mask, grid.dx)
    runs = {}
    for name, model in (("net", net), ("ref", reference)):
        forces, residual, div = [], [], []
        for k, s, new, bd in held_out_rollout(model, first, cfg):
            forces.append(body_forces(scenes, new, bd, k))
            residual.append(momentum_loss(s, new, bd, params, grid))
            div.append(divergence(curl(new.a, grid.dx), grid.dx).abs().flatten(1).amax(1))
            done += 1
            if progress:
                progress(done, total)
        runs[name] = {"state": new, "force": torch.stack(forces).mean(0), "residual": torch.stack(residual).mean(0),
                      "div": torch.stack(div).amax(0)}
    last = scenes.boundary(cfg.warmup + cfg.steps)
    roll_v, roll_p = relative_errors(runs["net"]["state"], runs["ref"]["state"], last.mask, grid.dx)
    out = {}
    for n, name in enumerate(scenes.names):
        fn, fr = runs["net"]["force"][n], runs["ref"]["force"][n]
        out[name] = {
            "one_step_error_v": one_v[n].item(), "one_step_error_p": one_p[n].item(),
            f"rollout{cfg.steps}_error_v": roll_v[n].item(), f"rollout{cfg.steps}_error_p": roll_p[n].item(),
            "residual_Lp_net": runs["net"]["residual"][n].item(), "residual_Lp_ref": runs["ref"]["residual"][n].item(),
            "max_div_net": runs["net"]["div"][n].item(), "max_div_ref": runs["ref"]["div"][n].item(),
            "force_x_net": fn[0].item(), "force_x_ref": fr[0].item(),
            "force_y_net": fn[1].item(), "force_y_ref": fr[1].item(),
        }
        if name.startswith("cylinder"):
            out[name]["drag_ratio"] = fn[0].item() / fr[0].item()
    final = {"mask": last.mask[:, 0].cpu().numpy(), "names": scenes.names}
    for name in ("net", "ref"):
        st = runs[name]["state"]
        final[name] = {"p": st.p[:, 0].cpu().numpy(),
                       "vorticity": vorticity(curl(st.a, grid.dx), grid.dx)[:, 0].cpu().numpy()}
    return Evaluation(out, final)


def kinetic_energy(state: FluidState, mask: Tensor, rho: float, dx: float) -> Tensor:
    """E = rho / 2 sum_f (1 - b_f) v_f^2 dx^2 over the fluid faces, [B] in J/m (per unit depth)."""
    v = curl(state.a, dx)
    return 0.5 * rho * dx**2 * sum((w * c**2).flatten(1).sum(1) for c, w in zip(v, fluid_face_masks(mask)))


@torch.no_grad()
def energy_checks(net: FluidModel, reference: FluidModel, cfg: EvalConfig = EvalConfig(), device=None) -> dict:
    """The still-fish and kinetic-energy checks of the module docstring, as a dict of numbers."""
    scenes = Scenes(cfg, device)
    grid, tank = scenes.grid, scenes.tank
    params = FluidParams(torch.full((1,), cfg.rho, device=device), torch.full((1,), cfg.mu, device=device), cfg.h)

    def rollout(model: FluidModel, fish: Fish, steps: int) -> tuple[FluidState, Boundary]:
        state = model.initial_state(1, device=device)
        for k in range(1, steps + 1):
            bd = union(tank, fish_boundaries([fish], [k * cfg.h], [SIGMA], grid, device)[0])
            state = model.step(state, bd, params)
        return state, bd

    still, _ = rollout(net, scenes.swimmer(1.0, amplitude=0.0), cfg.still_steps)
    speed = max(c.abs().max().item() for c in curl(still.a, grid.dx))
    swimmer = scenes.swimmer(cfg.energy_frequency)
    energy = {}
    for name, model in (("net", net), ("ref", reference)):
        state, bd = rollout(model, swimmer, cfg.energy_steps)
        energy[name] = kinetic_energy(state, bd.mask, cfg.rho, grid.dx).item()
    return {f"still_fish_max_speed_{cfg.still_steps}": speed, f"kinetic_energy_net_{cfg.energy_steps}": energy["net"],
            f"kinetic_energy_ref_{cfg.energy_steps}": energy["ref"], "kinetic_energy_ratio": energy["net"] / energy["ref"]}


def summarise(results: dict) -> dict:
    """Means over the scenes of each error and the worst drag mismatch (for metadata and notes)."""
    keys = [k for k in next(iter(results.values())) if "error" in k]
    summary = {f"mean_{k}": float(np.mean([r[k] for r in results.values()])) for k in keys}
    ratios = [r["drag_ratio"] for r in results.values() if "drag_ratio" in r]
    if ratios:
        summary["worst_drag_error"] = float(max(abs(x - 1) for x in ratios))
    return summary
