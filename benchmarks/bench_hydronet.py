"""HydroNet speed: inference ms/step at the paper's 100 x 300 grid (B = 1, 16; fp32, bf16
autocast; hidden 16 (our default) and 20 (Wandel's UNet2); the network alone, and the default
symmetric step, network and mirror image), forward + backward ms/step, the bf16
error, and training iterations/s (pool + step + loss + Adam) for the default TrainConfig.
All CPU runs use channels_last; the step is the network alone (its own pressure output: the
recovered pressure's PCG is timed in the coupled rollout, bench_rollout). Target: <= 20 ms
forward per step at B = 1 on 2 cores."""

from __future__ import annotations

import tempfile
import time
from dataclasses import replace

import torch

from fishsim.fields import Boundary, FluidParams, FluidState, Grid
from fishsim.fluid.grid import closed_tank
from fishsim.fluid.hydronet.config import NETWORK, NetConfig, TrainConfig, resolve_bf16
from fishsim.fluid.hydronet.unet import HydroNet, HydroNetFluid
from fishsim.learn import train as T

GRID = Grid(100, 300, 2.5e-3)


def _inputs(batch: int, device="cpu"):
    g = torch.Generator().manual_seed(0)
    state = FluidState(1e-4 * torch.randn(batch, 1, GRID.H + 1, GRID.W + 1, generator=g),
                       torch.randn(batch, 1, GRID.H, GRID.W, generator=g))
    tank = closed_tank(GRID, 3, 5, batch)
    boundary = Boundary(tank.mask, 0.1 * tank.mask.expand(-1, 2, -1, -1).clone())
    params = FluidParams(torch.full((batch,), 50.0), torch.full((batch,), 1.25e-4), 0.01)
    return state, boundary, params


def _ms(fn, reps: int) -> float:
    for _ in range(3):  # oneDNN builds its kernels for each new shape on the first calls
        fn()
    t0 = time.perf_counter()
    for _ in range(reps):
        fn()
    return 1e3 * (time.perf_counter() - t0) / reps


def _fluid(hidden: int, bf16: bool, symmetric: bool = False) -> HydroNetFluid:
    """A fresh network as HydroNetFluid steps it (its own pressure; the network alone, or with its
    mirror image if ``symmetric``)."""
    torch.manual_seed(0)
    model = HydroNet(NetConfig(hidden=hidden))          # HydroNetFluid runs it channels_last on the CPU
    return HydroNetFluid(model, GRID, bf16=bf16, pressure=NETWORK, symmetric=symmetric)


def inference(hidden: int, batch: int, bf16: bool, symmetric: bool = False) -> float:
    """ms per HydroNetFluid.step under no_grad (eval mode); ``symmetric``: the default step, the
    network and its mirror image."""
    fluid, (state, boundary, params) = _fluid(hidden, bf16, symmetric), _inputs(batch)
    with torch.no_grad():
        return _ms(lambda: fluid.step(state, boundary, params), 10 if batch == 1 else 3)


def forward_backward(hidden: int, bf16: bool) -> float:
    """ms per step forward + backward to the state (one step of back-propagation through time)."""
    fluid, (state, boundary, params) = _fluid(hidden, bf16), _inputs(1)

    def step():
        a = state.a.clone().requires_grad_()
        new = fluid.step(FluidState(a, state.p), boundary, params)
        (new.a.sum() + new.p.sum()).backward()

    return _ms(step, 5)


def bf16_error(hidden: int) -> float:
    """max |a_bf16 - a_fp32| / max |a_fp32 - a_t|: error relative to the step's update."""
    state, boundary, params = _inputs(1)
    with torch.no_grad():
        ref = _fluid(hidden, False).step(state, boundary, params)
        low = _fluid(hidden, True).step(state, boundary, params)
    return float((low.a - ref.a).abs().max() / (ref.a - state.a).abs().max())


def training(iterations: int = 20) -> dict:
    """Iterations/s and samples/s of the default TrainConfig (its crop, batch, net, bf16 as ``bf16=auto`` resolves it, compiled
    Koren loss; the one-off compilation is excluded)."""
    with tempfile.TemporaryDirectory() as tmp:
        cfg = replace(TrainConfig(), out_dir=tmp, iterations=iterations, progress=False,
                      val_every=10**9, ckpt_every=10**9, ckpt_minutes=1e9, bf16=resolve_bf16("auto", "cpu"))
        run, net = T.build(cfg, 0, 1, torch.device("cpu"))
        for _ in range(2):  # compiles the loss (forward and backward)
            T.train_step(run, cfg, net)
        t0 = time.perf_counter()
        for _ in range(iterations):
            T.train_step(run, cfg, net)
        dt = (time.perf_counter() - t0) / iterations
    return {"config": f"{cfg.pool.H}x{cfg.pool.W} crop, batch {cfg.batch_size}, hidden {cfg.net.hidden}, "
                      f"bf16 {cfg.bf16}, channels_last {cfg.channels_last}",
            "ms_per_iteration": 1e3 * dt, "it_per_s": 1 / dt, "samples_per_s": cfg.batch_size / dt}


def run() -> dict:
    """All HydroNet timings at the current torch thread count."""
    out: dict = {"grid": f"{GRID.H} x {GRID.W}", "threads": torch.get_num_threads()}
    for hidden in (16, 20):
        for prec in ("fp32", "bf16"):
            key = f"hidden{hidden}_{prec}"
            bf16 = prec == "bf16"
            out[key] = {"forward_ms_B1": inference(hidden, 1, bf16),
                        "forward_ms_per_sample_B16": inference(hidden, 16, bf16) / 16,
                        "forward_backward_ms_B1": forward_backward(hidden, bf16)}
        out[f"hidden{hidden}_bf16"]["relative_error_vs_fp32"] = bf16_error(hidden)
    out["hidden16_fp32_symmetric"] = {"forward_ms_B1": inference(16, 1, False, symmetric=True),
                                      "forward_ms_per_sample_B16": inference(16, 16, False, symmetric=True) / 16}
    out["training"] = training()
    return out


if __name__ == "__main__":
    import json

    print(json.dumps(run(), indent=1))
