"""``fishsim validate``: comparisons against the numerical reference solver.

suite=hydronet: the HydroNet model against the numerical solver on held-out scenes
(``fishsim.fluid.hydronet.evaluate``): metrics.json, a printed table, and a picture of the final
vorticity of both models side by side (comparison.png/.svg).
"""

from __future__ import annotations

import json
import re
from dataclasses import asdict, dataclass, field

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from rich.table import Table

from fishsim.errors import ConfigError
from fishsim.fluid.hydronet.evaluate import EvalConfig, evaluate, summarise
from fishsim.fluid.pressure import PRESSURES
from fishsim.io.outdir import make_out_dir

SUITES = ("hydronet",)


@dataclass
class ValidateConfig:
    """suite: hydronet (the only one so far). model_file: the HydroNet to judge (null: shipped).
    bf16: run it in bfloat16. pressure: recovered | network (``fishsim.fluid.pressure``).
    device: cpu | cuda. scenes: the held-out scenes and protocol."""

    suite: str = "hydronet"
    model_file: str | None = None
    bf16: bool = False
    pressure: str = "recovered"
    device: str = "cpu"
    scenes: EvalConfig = field(default_factory=EvalConfig)
    out_dir: str | None = None

    def validate(self) -> None:
        if self.suite not in SUITES:
            raise ConfigError(f"suite must be one of {SUITES} (got '{self.suite}')")
        if self.pressure not in PRESSURES:
            raise ConfigError(f"pressure must be recovered or network (got '{self.pressure}')")
        s = self.scenes
        if not (s.warmup >= 0 and s.steps >= 1 and s.radius > 0 and s.fish_amp > 0 and s.h > 0):
            raise ConfigError("scenes.warmup >= 0, scenes.steps >= 1 and radius, fish_amp, h > 0 are required")
        if not (s.speeds or s.frequencies):
            raise ConfigError("give at least one of scenes.speeds or scenes.frequencies")


def run(cfg: ValidateConfig) -> dict:
    """Evaluate, write metrics.json and the comparison picture, print the table."""
    import torch

    from fishsim.fluid.base import Grid
    from fishsim.fluid.factory import SHIPPED_HYDRONET
    from fishsim.fluid.hydronet import HydroNetFluid, load_hydronet
    from fishsim.fluid.numerical import NumericalFluid
    from fishsim.render.plots import plot_fluid_comparison

    out_dir = make_out_dir("validate", cfg.out_dir)
    s = cfg.scenes
    grid, device = Grid(s.H, s.W, s.dx), torch.device(cfg.device)
    path = cfg.model_file or SHIPPED_HYDRONET
    net = HydroNetFluid(load_hydronet(path, device), grid, bf16=cfg.bf16, pressure=cfg.pressure)
    columns = (TextColumn("validate hydronet"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    with Progress(*columns, console=Console(stderr=True), transient=True) as bar:
        task = bar.add_task("steps", total=None)
        result = evaluate(net, NumericalFluid(grid), s, device,
                          progress=lambda done, total: bar.update(task, completed=done, total=total))
    summary = {"model_file": str(path), "scenes": asdict(s), "metrics": result.metrics,
               "summary": summarise(result.metrics)}
    (out_dir / "metrics.json").write_text(json.dumps(summary, indent=2))
    pictures = plot_fluid_comparison(result.final, out_dir / "comparison")
    _print(result.metrics, summary["summary"])
    Console().print(f"metrics: {out_dir / 'metrics.json'}   picture: {pictures[0]}")
    return summary


COLUMNS = {"one_step_error_v": "1-step e_v", "one_step_error_p": "1-step e_p", "rollout_error_v": "N-step e_v",
           "rollout_error_p": "N-step e_p", "residual_Lp_net": "L_p net", "residual_Lp_ref": "L_p ref",
           "max_div_net": "max div net", "force_x_net": "F_x net [N]", "force_x_ref": "F_x ref [N]"}


def _print(metrics: dict, summary: dict) -> None:
    """One row per scene (N-step: the rollout length), then the means."""
    table = Table(title="HydroNet vs numerical solver (held-out scenes)")
    table.add_column("scene")
    for label in COLUMNS.values():
        table.add_column(label, justify="right")
    for name, m in metrics.items():
        m = {re.sub(r"^rollout\d+_", "rollout_", k): v for k, v in m.items()}
        table.add_row(name, *(f"{m[k]:.3g}" for k in COLUMNS))
    Console(width=max(Console().width, 150)).print(table)
    Console().print("  ".join(f"{k} {v:.3g}" for k, v in summary.items()))
