"""``fishsim train-hydronet``: train HydroNet on the scene pool (``fishsim.learn.train``)."""

from __future__ import annotations

from rich.console import Console

from fishsim.errors import Terminated
from fishsim.fluid.hydronet.config import TrainConfig
from fishsim.learn.train import run as train


def run(cfg: TrainConfig) -> dict:
    """Train as configured and print where the model is; returns the trainer's summary. A stop by
    SIGINT / SIGTERM is re-raised after the save (exit 130 / 143) so that schedulers and scripts
    see it."""
    summary = train(cfg)
    if summary["rank"] == 0:
        Console().print(
            f"train-hydronet {_state(summary)}: iteration {summary['iteration']}, best validation loss "
            f"{summary['best_val']:.3f}, {summary['it_per_s']:.2f} it/s "
            f"({summary['samples_per_s']:.1f} samples/s); outputs in {summary['out_dir']}/ "
            f"(best.pt, ckpt.pt, log.csv, tb/); continue with out_dir={summary['out_dir']} resume=true")
    if summary["interrupted"]:
        how = (f"checkpoint of iteration {summary['iteration']} saved" if summary["saved"] else
               "stopped at once, the last checkpoint saved before kept")
        raise (Terminated if summary["interrupted"] == "SIGTERM" else KeyboardInterrupt)(
            f"train-hydronet stopped by {summary['interrupted']}, {how} in {summary['out_dir']}")
    return summary


def _state(summary: dict) -> str:
    if not summary["interrupted"]:
        return "done"
    return "interrupted, checkpoint saved" if summary["saved"] else "stopped at once by a second signal"
