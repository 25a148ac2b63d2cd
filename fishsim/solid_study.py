"""Mesh convergence of the swimming solid and its passive validation against beam theory: the
studies behind ``fishsim validate suite=solid`` and benchmarks/study_solid_convergence.py
(docs/validation.md).

`stroke_study`: the same fish, controller and fluid at several element sizes, with the default
muscle layer and with the paper's station muscles. Each run is `fishsim simulate fluid=<fluid>
frames=<frames> fish.edge_length=<edge> fish.muscles=<model>` in memory (no files): 5 Hz, the
default material and controller (C calibrated per muscle model). Reported per run: the tail
tip's peak-to-peak lateral excursion over the second half of the episode (as `fishsim
simulate`'s summary), the head's x displacement over the episode and its lateral peak-to-peak
over the second half, the mesh size, and the solid's wall time per step (the PD step alone:
the rollout's PhaseTimer's solid phase over the frames, so the first compiled call is included once).
Deviations are relative to the finest mesh of the same muscle model.

`beam_study`: a clamped 100 x 5 mm cantilever of the fish's material (fishsim/solid/beam.py)
under a tip load giving 1 mm of deflection: static tip deflection and first bending frequency
against Euler-Bernoulli at n elements across the thickness.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

import numpy as np
import torch

EDGES = (3e-3, 2e-3, 1.4e-3, 1e-3)
MUSCLE_MODELS = ("layer", "paper")
BEAM_ACROSS = (2, 4, 8, 16)


def simulate_stroke(edge_length: float, muscles: str = "layer", fluid: str = "none", frames: int = 120,
                    overrides: Sequence[str] = ()) -> dict:
    """One in-memory `fishsim simulate` run; its stroke and cost numbers (module docstring):
    edge_mm, muscles, fluid, nodes, n_act, tail_p2p_mm, head_dx_mm, head_y_p2p_mm,
    solid_ms_per_step, wall_s."""
    from fishsim.config import load_config
    from fishsim.episode import build_episode
    from fishsim.rollout import PhaseTimer, rollout

    cfg = load_config("simulate", [f"fluid={fluid}", f"frames={frames}", f"fish.edge_length={edge_length}",
                                   f"fish.muscles={muscles}", *overrides])
    episode = build_episode(cfg)
    sw = episode.swimmer
    state = sw.initial_state(episode.params, episode.origin)
    t0 = time.perf_counter()
    timer = PhaseTimer()
    with torch.no_grad():
        _, metrics = rollout(sw, state, episode.params, cfg.frames, timer=timer)
    wall = time.perf_counter() - t0
    m = {k: v[:, 0].cpu().numpy() for k, v in metrics.items()}
    half = frames // 2
    tail, head_y = m["tail_y"][half:], m["head_y"][half:]
    return {"edge_mm": 1e3 * edge_length, "muscles": muscles, "fluid": fluid, "nodes": sw.solid.n_nodes,
            "n_act": sw.solid.n_muscles, "tail_p2p_mm": 1e3 * float(tail.max() - tail.min()),
            "head_dx_mm": 1e3 * float(m["head_x"][-1] - episode.origin[0] - sw.solid.mesh.length),
            "head_y_p2p_mm": 1e3 * float(head_y.max() - head_y.min()),
            "solid_ms_per_step": 1e3 * timer.seconds["solid"] / frames, "wall_s": wall}


def stroke_study(edges: Sequence[float] = EDGES, models: Sequence[str] = MUSCLE_MODELS, fluid: str = "none",
                 frames: int = 120, overrides: Sequence[str] = (),
                 progress: Callable[[int, int], None] | None = None) -> list[dict]:
    """simulate_stroke for every muscle model and edge length (m), each row with its deviation
    from the finest mesh of its model (tail_dev, head_dev: relative). progress(done, total) is
    called after each run."""
    rows, total = [], len(models) * len(edges)
    for model in models:
        runs = []
        for e in edges:
            runs.append(simulate_stroke(e, model, fluid, frames, overrides))
            if progress is not None:
                progress(len(rows) + len(runs), total)
        finest = min(runs, key=lambda r: r["edge_mm"])
        for r in runs:
            r["tail_dev"] = r["tail_p2p_mm"] / finest["tail_p2p_mm"] - 1
            r["head_dev"] = (r["head_dx_mm"] - finest["head_dx_mm"]) / max(abs(finest["head_dx_mm"]), 1e-12)
        rows += runs
    return rows


def beam_study(across: Sequence[int] = BEAM_ACROSS, volume_term: bool = False) -> list[dict]:
    """Cantilever tip deflection and first bending frequency against Euler-Bernoulli (relative
    errors static_err, frequency_err) at each number of elements across the thickness."""
    from fishsim.solid.beam import Cantilever
    from fishsim.solid.config import SolidMaterial

    beam = Cantilever(material=SolidMaterial(volume_term=volume_term))
    load = 3 * beam.bending_stiffness * 1e-3 / beam.length**3          # 1 mm tip deflection
    rows = []
    for n in across:
        deflection, q = beam.static_deflection(beam.thickness / n, load)
        frequency = beam.vibration_frequency(beam.thickness / n, load)
        rows.append({"across": int(n), "edge_mm": 1e3 * beam.thickness / n, "nodes": int(q.shape[1]),
                     "static_err": deflection / beam.tip_deflection(load) - 1,
                     "frequency_err": frequency / beam.first_frequency() - 1})
    return rows


def stroke_markdown(rows: list[dict]) -> str:
    """The stroke study as a markdown table (the docs' layout)."""
    lines = [("| muscles | edge | nodes | muscles (elements) | tail peak-to-peak | vs finest | head x displacement "
              "| vs finest | head y peak-to-peak | solid step |"),
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['muscles']} | {r['edge_mm']:.1f} mm | {r['nodes']} | {r['n_act']} | "
                     f"{r['tail_p2p_mm']:.1f} mm | {100 * r['tail_dev']:+.1f} % | {r['head_dx_mm']:+.2f} mm | "
                     f"{100 * r['head_dev']:+.1f} % | {r['head_y_p2p_mm']:.2f} mm | "
                     f"{r['solid_ms_per_step']:.1f} ms |")
    return "\n".join(lines)


def beam_markdown(rows: list[dict]) -> str:
    """The beam study as a markdown table."""
    lines = ["| elements across | edge | nodes | tip deflection error | first frequency error |", "|---|---|---|---|---|"]
    lines += [f"| {r['across']} | {r['edge_mm']:.3g} mm | {r['nodes']} | {100 * r['static_err']:+.2f} % | "
              f"{100 * r['frequency_err']:+.2f} % |" for r in rows]
    return "\n".join(lines)


def summary(rows: list[dict], beam_rows: list[dict]) -> dict:
    """Per muscle model, the tail and head deviations (%) of the second-finest and the 2 mm
    (default) mesh from the finest; the finest beam's errors (%)."""
    out = {}
    for model in dict.fromkeys(r["muscles"] for r in rows):
        runs = sorted((r for r in rows if r["muscles"] == model), key=lambda r: r["edge_mm"])
        entry = {}
        if len(runs) > 1:
            entry["tail_dev_second_finest_pct"] = 100 * runs[1]["tail_dev"]
            entry["head_dev_second_finest_pct"] = 100 * runs[1]["head_dev"]
        default = [r for r in runs if np.isclose(r["edge_mm"], 2.0)]
        if default and default[0] is not runs[0]:
            entry["tail_dev_default_pct"] = 100 * default[0]["tail_dev"]
            entry["head_dev_default_pct"] = 100 * default[0]["head_dev"]
        out[model] = entry
    if beam_rows:
        finest = max(beam_rows, key=lambda r: r["across"])
        out["beam"] = {"across": finest["across"], "static_err_pct": 100 * finest["static_err"],
                       "frequency_err_pct": 100 * finest["frequency_err"]}
    return out
