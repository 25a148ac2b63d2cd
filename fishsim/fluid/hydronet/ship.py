"""Ship a trained HydroNet: ``python -m fishsim.fluid.hydronet.ship RUN_DIR VALIDATE_DIR [LINEAGE.json]``.

* ``fishsim/assets/hydronet.pt``: the weights of RUN_DIR/best.pt (``export_model``), the model
  ``fishsim simulate fluid=hydronet`` uses by default;
* ``fishsim/assets/hydronet.json``: its metadata: net and training config, the commands that
  produced it (LINEAGE.json: every training command in order, with the iterations and wall time
  of runs before RUN_DIR, which it was initialised from), iterations, wall time, the
  final training losses (log.csv), and the evaluation against the numerical solver
  (VALIDATE_DIR/metrics.json, written by ``fishsim validate model_file=RUN_DIR/best.pt``);
* ``training/hydronet/ckpt.pt`` + ``log.csv``: the compact checkpoint to continue training from
  in a later sitting (``compact_checkpoint``; see the metadata's "continue" entry).
"""

from __future__ import annotations

import csv
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

from fishsim.fluid.factory import SHIPPED_HYDRONET
from fishsim.fluid.hydronet.train import compact_checkpoint, export_model

TRAINING = Path("training/hydronet")
TARGETS = {"one_step_error_v": 0.05, "one_step_error_p": 0.15, "cylinder_mean_drag_error_100_steps": 0.20,
           "forward_ms_B1": 20.0}


def final_losses(log: Path, last: int = 200) -> dict:
    """Means over the last ``last`` logged iterations of the training loss terms."""
    rows = list(csv.DictReader(log.open()))[-last:]
    mean = lambda k: float(np.mean([float(r[k]) for r in rows]))
    return {"iterations_averaged": f"{rows[0]['iteration']}-{rows[-1]['iteration']}", "log_loss": mean("loss"),
            "L_p": mean("L_p"), "L_b": mean("L_b"), "last_validation_log_loss": float(rows[-1]["val"]),
            "it_per_s": mean("it_per_s"), "samples_per_s": mean("samples_per_s")}


def ship(run_dir: Path, validate_dir: Path, lineage: list) -> dict:
    ckpt = torch.load(run_dir / "ckpt.pt", map_location="cpu", weights_only=False)
    best = torch.load(run_dir / "best.pt", map_location="cpu", weights_only=False)
    evaluation = json.loads((validate_dir / "metrics.json").read_text())
    earlier = sum(r.get("iterations", 0) for r in lineage)
    meta = {
        "what": "HydroNet for the paper's fluid: rho = 50 kg/m^3, mu = 0.125 mPa s, dx = 2.5 mm, h = 0.01 s",
        "net": best["net"],
        "train_config": ckpt["config"],
        "lineage": lineage,
        "commands": [r["command"] for r in lineage],
        "iterations": int(best["iteration"]) + earlier,
        "iterations_this_run_at_best": int(best["iteration"]),
        "iterations_this_run_total": int(ckpt["iteration"]),
        "best_validation_log_loss": float(best["val"]),
        "wall_time_s": float(ckpt["elapsed"]) + sum(r.get("wall_time_s", 0) for r in lineage),
        "final_losses": final_losses(run_dir / "log.csv"),
        "evaluation": evaluation,
        "targets": TARGETS,
        "machine": {"cpu": platform.processor() or platform.machine(), "torch": torch.__version__,
                    "threads": ckpt["config"].get("threads")},
        "date": time.strftime("%Y-%m-%d"),
        "continue": f"mkdir -p runs/hydronet && cp {TRAINING}/ckpt.pt runs/hydronet/ && "
                    "fishsim train-hydronet out_dir=runs/hydronet resume=true",
        "shipped_by": f"python -m fishsim.fluid.hydronet.ship {run_dir} {validate_dir} runs/lineage.json",
    }
    export_model(run_dir / "best.pt", SHIPPED_HYDRONET, meta)
    compact_checkpoint(run_dir / "ckpt.pt", TRAINING / "ckpt.pt")
    (TRAINING / "log.csv").write_text((run_dir / "log.csv").read_text())
    return meta


if __name__ == "__main__":
    args = sys.argv[1:]
    lineage = json.loads(Path(args[2]).read_text()) if len(args) > 2 else []
    print(json.dumps(ship(Path(args[0]), Path(args[1]), lineage)["evaluation"]["summary"], indent=1))
