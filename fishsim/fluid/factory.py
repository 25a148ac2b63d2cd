"""Build the fluid model and the tank a config asks for (the only place that branches on it)."""

from __future__ import annotations

from pathlib import Path

import torch

from fishsim.fields import Boundary, FluidModel, FluidParams
from fishsim.fluid.grid import channel, closed_tank

SHIPPED_HYDRONET = Path(__file__).resolve().parents[1] / "assets" / "hydronet.pt"


def fluid_dtype(cfg) -> torch.dtype:
    """The torch dtype of a ``FluidConfig``'s ``dtype`` (its fields, boundaries and parameters)."""
    return getattr(torch, cfg.dtype)


def numerical_stepping(cfg) -> dict:
    """The ``NumericalFluid`` keywords of a numerical fluid config (``NumericalConfig``) that set
    its time stepping and penalisation: `fishsim simulate`'s stepping, also for the validation
    cases run "on the fish's stepping" (fishsim.fluid.cases)."""
    return {"substeps": cfg.substeps, "cfl": cfg.cfl, "penalization_iterations": cfg.penalization_iterations,
            "scheme": cfg.scheme, "penalization_rate": cfg.penalization_rate, "brinkman": cfg.brinkman,
            "implicit": cfg.implicit}


def make_fluid(cfg, tank, device=None) -> FluidModel:
    """The ``FluidModel`` of a fluid config (fishsim.config.FLUID_MODELS; ``model=none``: the
    Vacuum) in the tank of a ``TankConfig``, on ``device``.

    hydronet: the model in ``cfg.model_file`` or, when unset, the shipped one, with the pressure
    ``cfg.pressure``; a missing or corrupt file raises InputFileError saying how to train one."""
    if cfg.model == "none":
        from fishsim.fluid.vacuum import Vacuum

        return Vacuum(tank.grid)
    if cfg.model == "numerical":
        from fishsim.fluid.numerical import NumericalFluid

        return NumericalFluid(tank.grid, refinement=cfg.refinement, **numerical_stepping(cfg))
    if cfg.model == "hydronet":
        from fishsim.fluid.hydronet import HydroNetFluid, load_hydronet
        from fishsim.fluid.pressure import RecoveryConfig

        model = load_hydronet(hydronet_file(cfg), device=device or "cpu").to(fluid_dtype(cfg))
        if cfg.bf16:
            warn_slow_bf16(torch.device(device or "cpu").type)
        return HydroNetFluid(model, tank.grid, bf16=cfg.bf16, pressure=cfg.pressure,
                             recovery=RecoveryConfig(tol=cfg.pressure_tol), symmetric=cfg.symmetric,
                             compile=cfg.compile)
    raise ValueError(f"unknown fluid model {cfg.model!r}")


def warn_slow_bf16(device_type: str) -> bool:
    """One line on stderr if ``fluid.bf16=true`` runs on a CPU without bfloat16 instructions,
    where it is ~10x slower than float32 (fishsim.fluid.hydronet.config.cpu_has_bf16); whether
    it warned."""
    from fishsim.fluid.hydronet.config import cpu_has_bf16

    if device_type != "cpu" or cpu_has_bf16():
        return False
    from rich.console import Console

    Console(stderr=True, soft_wrap=True).print(
        "[yellow]warning: fluid.bf16=true on a CPU without bfloat16 instructions (AVX512-BF16 or AMX): HydroNet "
        "runs ~10x slower than in float32 here; drop fluid.bf16 (its results are within 2 % of float32's)[/]")
    return True


def hydronet_file(cfg) -> str | Path:
    """The model file a HydroNetConfig names: its model_file, else the shipped one."""
    return cfg.model_file or SHIPPED_HYDRONET


def make_walls(tank, dtype: torch.dtype, device=None, unit_inflow: bool = False) -> Boundary:
    """The walls [1, ., H, W] of a ``TankConfig`` in ``dtype``: closed, or a channel with
    ``tank.inflow`` m/s at the ends (``unit_inflow``: 1 m/s, a swim tunnel's walls that the rollout
    scales)."""
    grid = tank.grid
    if tank.inflow != 0.0 or unit_inflow:
        return channel(grid, 1.0 if unit_inflow else tank.inflow, tank.wall_y, tank.wall_x, 1, device, dtype)
    return closed_tank(grid, tank.wall_y, tank.wall_x, 1, device, dtype)


def fluid_params(cfg, batch: int, h: float, device=None) -> FluidParams:
    """rho, mu as [B] tensors (in the fluid's ``cfg.dtype``; 0 in the vacuum) and the time step h."""
    vacuum = cfg.model == "none"
    full = lambda name: torch.full((batch,), 0.0 if vacuum else float(getattr(cfg, name)), device=device,
                                   dtype=fluid_dtype(cfg))
    return FluidParams(rho=full("rho"), mu=full("mu"), h=h)
