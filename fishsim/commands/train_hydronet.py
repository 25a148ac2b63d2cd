"""``fishsim train-hydronet``: train HydroNet on the scene pool (``fishsim.fluid.hydronet.train``)."""

from __future__ import annotations

from rich.console import Console

from fishsim.errors import Terminated
from fishsim.fluid.hydronet.train import TrainConfig
from fishsim.fluid.hydronet.train import run as train


def run(cfg: TrainConfig) -> dict:
    """Train as configured and print where the model is; returns the trainer's summary."""
    summary = train(cfg)
    if summary["rank"] == 0:
        state = "interrupted, checkpoint saved" if summary["interrupted"] else "done"
        Console().print(
            f"train-hydronet {state}: iteration {summary['iteration']}, best validation loss "
            f"{summary['best_val']:.3f}, {summary['it_per_s']:.2f} it/s "
            f"({summary['samples_per_s']:.1f} samples/s); outputs in {summary['out_dir']}/ "
            f"(best.pt, ckpt.pt, log.csv, tb/); continue with resume=true")
    if summary["interrupted"]:      # saved; now exit 130 / 143 so that schedulers and scripts see the stop
        raise (Terminated if summary["interrupted"] == "SIGTERM" else KeyboardInterrupt)(
            f"train-hydronet stopped by {summary['interrupted']} at iteration {summary['iteration']}, checkpoint saved")
    return summary
