"""Model selection by swimming (``fishsim train-hydronet swim_every=N``).

The training loss does not single out the swimming answer: with the solver as a teacher, the
frequency study's distances move by 10-30 % between checkpoints 50 iterations apart (README, "The
shipped HydroNet"). So every ``swim_every`` iterations the network swims the paper's frequency
study (``fishsim.swim_study.episode``: the default tank and fish, B = one fish per frequency in
``swim_frequencies``, ``swim_frames`` frames, its own pressure), and its error

    e = max_f |d_net(f) / d_ref(f) - 1|      (d: head x displacement; e = inf if a fish fails)

against the numerical fluid's d_ref (at refinement ``swim_refinement``; run once per training
folder, ``swim_reference.json``) is
logged to ``swim.csv``; ``best_swim.pt`` keeps the weights of the lowest e. One check costs one
HydroNet episode (~50 s for 5 fish x 120 frames on one CPU thread).
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

from fishsim.fluid.hydronet.config import TrainConfig
from fishsim.io.atomic import atomic_text


def _episode(overrides: list[str], cfg: TrainConfig) -> list[float]:
    from fishsim.swim_study import episode

    return episode(overrides, list(cfg.swim_frequencies), cfg.swim_frames, cfg.device)["displacement_mm"]


def reference(out: Path, cfg: TrainConfig) -> list[float]:
    """The numerical fluid's displacements [mm] for the check (refined ``swim_refinement``
    times), computed once per folder (again when the study or the refinement changes)."""
    path = out / "swim_reference.json"
    study = {"frequencies": list(cfg.swim_frequencies), "frames": cfg.swim_frames, "refinement": cfg.swim_refinement}
    if path.exists():
        stored = json.loads(path.read_text())
        if {k: stored.get(k, 1) for k in study} == study:      # a file without "refinement": r = 1
            return stored["displacement_mm"]
    d = _episode(["fluid=numerical", f"fluid.refinement={cfg.swim_refinement}"], cfg)
    atomic_text(path, json.dumps(study | {"displacement_mm": d}) + "\n")
    return d


def swim_error(displacements: list[float], ref: list[float]) -> float:
    """e = max |d / d_ref - 1| (inf when a fish failed, NaN)."""
    errors = [abs(d / r - 1) for d, r in zip(displacements, ref)]
    return math.inf if any(math.isnan(e) for e in errors) else max(errors)


def check(model_file: Path, out: Path, cfg: TrainConfig, iteration: int) -> float:
    """Swim the study with the model in ``model_file``, append a row to out/swim.csv; returns
    its error e (the caller keeps the best weights, as for best.pt)."""
    ref = reference(out, cfg)
    d = _episode(["fluid=hydronet", f"fluid.model_file={model_file}"], cfg)
    error = swim_error(d, ref)
    path = out / "swim.csv"
    new = not path.exists()
    with open(path, "a", newline="") as f:
        w = csv.writer(f)
        if new:
            w.writerow(["iteration", "error", *(f"d_{x:g}Hz_mm" for x in cfg.swim_frequencies)])
        w.writerow([iteration, error, *d])
    return error
