"""The coupled system a config describes: the fish mesh and its muscles, the solid, the fluid,
the tank and the batch's parameters (``build_episode``), shared by ``fishsim simulate``,
``fishsim optimize``, the studies and the benchmarks."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from fishsim.config import FishConfig, SimulateConfig
from fishsim.errors import ConfigError
from fishsim.fluid.factory import fluid_dtype, fluid_params, hydronet_file, make_fluid, make_walls
from fishsim.fluid.hydronet.trained_range import check_channel, check_fluid
from fishsim.resources import check_memory
from fishsim.rollout import Swimmer, SwimParams
from fishsim.solid import SolidModel
from fishsim.solid.controller import WaveController, calibrated_amplitude


def build_fish_mesh(fish: FishConfig):
    """The fish mesh a config asks for: read from ``fish.mesh_file`` or generated."""
    from fishsim.io.mesh_io import read_mesh
    from fishsim.mesh import make_fish_mesh

    if fish.mesh_file:
        return read_mesh(fish.mesh_file)
    return make_fish_mesh(
        length=fish.length,
        profile=fish.profile,
        poly_coeffs=list(fish.poly_coeffs) or None,
        edge_length=fish.edge_length,
        min_angle=fish.min_angle,
        actuator_spacing=fish.actuator_spacing,
        actuator_x_range=tuple(fish.actuator_x_range),
        tail_tip_width=fish.tail_tip_width,
        elements_across=fish.mesh_elements_across(),
    )


def build_muscles(fish: FishConfig, mesh):
    """The muscle layout a config asks for (fishsim.solid.muscles): ``fish.muscles=layer`` (the
    default, a layer of ``fish.muscle_thickness`` times the local half-width along each side within
    ``fish.actuator_x_range``) or ``paper`` (the mesher's stations)."""
    from fishsim.solid.muscles import layer_muscles, station_muscles

    if fish.muscles == "paper":
        return station_muscles(mesh)
    return layer_muscles(mesh, fish.muscle_thickness, tuple(fish.actuator_x_range))


@dataclass
class Episode:
    """Everything one simulation needs, built from a config."""

    swimmer: Swimmer
    params: SwimParams
    origin: tuple[float, float]
    device: torch.device


def build_episode(cfg: SimulateConfig) -> Episode:
    """Mesh, solid, fluid, tank, coupling and the batch's parameters from the config."""
    device = torch.device(cfg.device)
    check_memory(cfg, cfg.batch.size)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device=cuda but torch sees no CUDA device (install a CUDA build of torch: see README)")
    if device.type == "cuda":
        full_float32_on_cuda()
    mesh = build_fish_mesh(cfg.fish)
    fluid = make_fluid(cfg.fluid, cfg.tank, device)
    if cfg.fluid.model == "hydronet":
        check_fluid(fluid.model, hydronet_file(cfg.fluid), cfg.fluid.rho, cfg.fluid.mu,
                    cfg.tank.dx, cfg.h, cfg.fluid.strict_range)
        if cfg.tunnel or cfg.tank.inflow:
            check_channel(fluid.model, hydronet_file(cfg.fluid), fluid.grid.W, cfg.fluid.strict_range)
    solid = SolidModel(mesh, cfg.solid.material, h=cfg.h, options=cfg.solid.pd,
                       added_mass_ratio=cfg.coupling.stabilisation_ratio if fluid.exerts_force else 0.0,
                       muscles=build_muscles(cfg.fish, mesh))
    walls = make_walls(cfg.tank, fluid_dtype(cfg.fluid), device, unit_inflow=cfg.tunnel) if fluid.exerts_force else None
    swimmer = Swimmer(solid, fluid, cfg.coupling, walls, fluid_dtype=fluid_dtype(cfg.fluid),
                      hold_x=cfg.hold_x, hold_y=cfg.hold_y, tunnel=cfg.tunnel)
    params = batch_params(cfg, mesh.length, device)
    peak = params.controller.peak_contraction(solid)
    if bool((peak >= 1).any()):
        worst = float(peak.max())
        raise ConfigError(f"controller amplitude C = {float(params.controller.C.max()):g} 1/m contracts a muscle by "
                          f"{worst:.2f} >= 1 (a muscle would vanish); use amplitude < "
                          f"{float(params.controller.C.max()) / worst:.4g}")
    return Episode(swimmer, params, tuple(cfg.origin), device)


def full_float32_on_cuda() -> None:
    """Turn TF32 off for CUDA convolutions and matrix products (cuDNN's default is on): TF32 keeps
    10 of float32's 23 mantissa bits. Measured on an H200 (benchmarks.cuda_check, 100 frames at
    5 Hz): with TF32 HydroNet's frequency gradient is 20 % off the CPU's, without it 0.03 %, at
    the same speed (21.8 against 20.7 s forward + backward)."""
    torch.backends.cudnn.allow_tf32 = False
    torch.backends.cuda.matmul.allow_tf32 = False


def batch_params(cfg: SimulateConfig, length: float, device) -> SwimParams:
    """Per-fish controller, E and fluid parameters as [B] tensors (config ``batch`` lists)."""
    B, c, b = cfg.batch.size, cfg.controller, cfg.batch

    def per_fish(values, default) -> torch.Tensor:
        values = list(values) or [default]
        return torch.tensor(values * (B // len(values)), dtype=torch.float64, device=device)

    gamma = c.wave_number if c.wave_number is not None else 2 * math.pi / length
    C = c.amplitude if c.amplitude is not None else calibrated_amplitude(cfg.fish.muscles)
    controller = WaveController(C=per_fish(b.amplitude, C),
                                omega=2 * math.pi * per_fish(b.frequency, c.frequency),
                                gamma=per_fish(b.wave_number, gamma), t_a=c.t_a)
    E = per_fish(b.youngs_modulus, cfg.solid.material.youngs_modulus)
    return SwimParams(controller=controller, E=E, fluid=fluid_params(cfg.fluid, B, cfg.h, device))
