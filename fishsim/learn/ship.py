"""Ship a trained HydroNet:
``python -m fishsim.learn.ship CHECKPOINT VALIDATE_DIR LINEAGE.json [SWIM_DIR ...]``; record
frequency studies of the shipped model re-measured since: ``python -m fishsim.learn.ship --record
SWIM_DIR ...`` (``record_swim_studies``).

* ``fishsim/assets/hydronet.pt``: the weights of CHECKPOINT (a ckpt.pt or best.pt;
  ``export_model``: the moving average of an ``ema`` run's ckpt.pt), the model ``fishsim simulate
  fluid=hydronet`` uses by default;
* ``fishsim/assets/hydronet.json``: its metadata: net and training config, the commands that
  produced it (LINEAGE.json: every training command in order, with the iterations and wall time
  of runs before CHECKPOINT's, which started from their weights), iterations, wall time, the
  final training losses (``log.csv`` beside CHECKPOINT), the evaluation against the numerical
  solver (VALIDATE_DIR/metrics.json, written by ``fishsim validate suite=hydronet
  hydronet.model_file=CHECKPOINT``), the frequency studies (each SWIM_DIR/metrics.json, written by
  ``fishsim validate suite=swim hydronet.model_file=CHECKPOINT``) and the targets it is judged
  against;
* ``training/hydronet/ckpt.pt`` + ``log.csv``: the compact checkpoint to continue training from
  in a later sitting (``compact_checkpoint``; see the metadata's "continue" entry).

CHECKPOINT may also be a model file a run kept (``best_swim.pt``, or a swim check's weights copied
aside) in its run folder: the config and log are then that run's (its ckpt.pt and log.csv, up to
the model's iteration), no optimiser state goes with it (training/hydronet/ckpt.pt is removed, the
log kept up to the model's iteration) and training continues from the shipped weights
(``init_from``, a fresh optimiser, ``freeze_norm``).
"""

from __future__ import annotations

import csv
import json
import platform
import re
import sys
import time
from pathlib import Path

import numpy as np
import torch

from fishsim.fluid.factory import SHIPPED_HYDRONET
from fishsim.learn.train import compact_checkpoint, export_model

TRAINING = Path("training/hydronet")
TARGETS = {  # the fidelity targets of the surrogate (README, "The shipped HydroNet")
    "frequency_study_120_frames_vs_numerical_r2": 0.10, "frequency_study_milestone": 0.25,
    "frames_300_displacement_vs_numerical_r2": 0.15, "frames_300_lateral_drift_mm": 10.0,
    "still_fish_max_speed_300_steps": 1e-3, "kinetic_energy_ratio_150_steps": [0.9, 1.1],
    "one_step_error_v": 0.03, "one_step_error_p": 0.10, "mean_force_error_100_steps": 0.10,
    "gradient_120_frames_vs_numerical": 0.20, "forward_ms_B1": 20.0, "forward_ms_per_fish_B16": 10.0,
    "model_file_MB": 20.0,
}


def log_rows(log: Path, until: int) -> list[dict]:
    """The rows of a training log.csv up to iteration ``until``."""
    return [r for r in csv.DictReader(log.open()) if int(r["iteration"]) <= until]


def final_losses(rows: list[dict], last: int = 200) -> dict:
    """Means over the last ``last`` of a training log's ``rows`` (``log_rows``) of the loss terms."""
    rows = rows[-last:]
    mean = lambda k: float(np.mean([float(r[k]) for r in rows if r.get(k) not in (None, "")]))
    out = {"iterations_averaged": f"{rows[0]['iteration']}-{rows[-1]['iteration']}", "log_loss": mean("loss"),
           "L_p": mean("L_p"), "L_b": mean("L_b"), "last_validation_log_loss": float(rows[-1]["val"]),
           "it_per_s": mean("it_per_s"), "samples_per_s": mean("samples_per_s")}
    if rows[-1].get("L_t") not in (None, ""):
        out["L_t"] = mean("L_t")
    return out


def continue_command(lineage: list, training: Path = TRAINING, model: Path | None = None) -> str:
    """The last training command, resumed from the committed compact checkpoint in ``training``,
    or, when a model file was shipped (``model``), started from its weights."""
    last = re.sub(r"out_dir=\S+", "out_dir=runs/hydronet", lineage[-1]["command"])
    last = re.sub(r" (init_from|resume|overwrite|freeze_norm)=\S+", "", last)
    if model is not None:
        here = Path.cwd()
        model = model.resolve().relative_to(here) if model.resolve().is_relative_to(here) else model
        return f"{last} init_from={model} freeze_norm=true"
    return f"mkdir -p runs/hydronet && cp {training}/ckpt.pt runs/hydronet/ && {last} resume=true"


def ship(checkpoint: Path, validate_dir: Path, lineage: list, swim_dirs: tuple[Path, ...] = (),
         asset: Path = SHIPPED_HYDRONET, training: Path = TRAINING) -> dict:
    """Write ``asset`` (+ .json) and the training state under ``training`` (module docstring)."""
    ckpt = torch.load(checkpoint, map_location="cpu", weights_only=False)
    model_file = "optimizer" not in ckpt
    run = ckpt if not model_file else torch.load(checkpoint.parent / "ckpt.pt", map_location="cpu",
                                                 weights_only=False)
    config = run.get("config") or {}
    log = checkpoint.parent / "log.csv"
    iteration = int(ckpt["iteration"])
    rows = log_rows(log, iteration)
    elapsed = float(rows[-1]["seconds"]) if model_file else float(ckpt.get("elapsed", 0.0))
    earlier = sum(r.get("iterations", 0) for r in lineage)
    swims = {}
    for d in swim_dirs:
        metrics = json.loads((d / "metrics.json").read_text())
        swims[f"frames_{metrics['swim']['frames']}"] = metrics
    meta = {
        "what": "HydroNet for the paper's fluid: rho = 50 kg/m^3, mu = 0.125 mPa s, dx = 2.5 mm, h = 0.01 s",
        "net": ckpt["net"],
        "train_config": config,
        "lineage": lineage,
        "commands": [r["command"] for r in lineage],
        "iterations": iteration + earlier,
        "iterations_last_run": iteration,
        "wall_time_s": elapsed + sum(r.get("wall_time_s", 0) for r in lineage),
        "final_losses": final_losses(rows),
        "evaluation": json.loads((validate_dir / "metrics.json").read_text()),
        "swim_studies": swims,
        "targets": TARGETS,
        "machine": {"cpu": platform.processor() or platform.machine(), "torch": torch.__version__,
                    "threads": config.get("threads")},
        "date": time.strftime("%Y-%m-%d"),
        "continue": continue_command(lineage, training, asset if model_file else None),
        "shipped_by": f"python -m fishsim.learn.ship {checkpoint} {validate_dir} LINEAGE.json "
                      + " ".join(str(d) for d in swim_dirs),
    }
    export_model(checkpoint, asset, meta)
    if model_file:                              # no optimiser state: the shipped weights are the start
        (training / "ckpt.pt").unlink(missing_ok=True)
    elif checkpoint.resolve() != (training / "ckpt.pt").resolve():
        compact_checkpoint(checkpoint, training / "ckpt.pt")
    if log.resolve() != (training / "log.csv").resolve():
        lines = log.read_text().splitlines(keepends=True)
        (training / "log.csv").write_text("".join(lines[:1 + len(rows)]))
    return meta


def record_swim_studies(swim_dirs: tuple[Path, ...], meta_path: Path | None = None) -> dict:
    """Frequency studies of the shipped model re-measured after shipping (each SWIM_DIR/metrics.json,
    from ``fishsim validate suite=swim`` at that day's defaults and reference) into its metadata's
    "swim_studies", each stamped with the date it was recorded; the entries they replace move to
    "swim_studies_earlier" (newest last); meta_path: default the shipped model's. Returns the
    metadata written."""
    meta_path = SHIPPED_HYDRONET.with_suffix(".json") if meta_path is None else meta_path
    meta = json.loads(meta_path.read_text())
    for d in swim_dirs:
        metrics = json.loads((d / "metrics.json").read_text())
        key = f"frames_{metrics['swim']['frames']}"
        if key in meta["swim_studies"]:
            meta.setdefault("swim_studies_earlier", {}).setdefault(key, []).append(meta["swim_studies"][key])
        meta["swim_studies"][key] = {**metrics, "recorded": time.strftime("%Y-%m-%d"), "from": str(d)}
    meta_path.write_text(json.dumps(meta, indent=2, default=str) + "\n")
    return meta


if __name__ == "__main__":
    args = sys.argv[1:]
    if args[:1] == ["--record"] and len(args) > 1:
        record_swim_studies(tuple(Path(a) for a in args[1:]))
        sys.exit(0)
    if len(args) < 3:
        sys.exit(__doc__)
    meta = ship(Path(args[0]), Path(args[1]), json.loads(Path(args[2]).read_text()), tuple(Path(a) for a in args[3:]))
    print(json.dumps(meta["evaluation"]["summary"], indent=1))
