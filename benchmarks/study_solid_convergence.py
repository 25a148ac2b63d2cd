"""Mesh convergence of the swimming solid: the same fish, controller and fluid at several element
sizes, with the default muscle layer and with the paper's station muscles.

    python benchmarks/study_solid_convergence.py                          # vacuum, both muscle models
    python benchmarks/study_solid_convergence.py --fluid numerical        # in the numerical fluid (slow)
    python benchmarks/study_solid_convergence.py --edges 3e-3 2e-3 --muscles layer --frames 60

Each run is `fishsim simulate fluid=<fluid> frames=<frames> fish.edge_length=<edge>
fish.muscles=<model>` in memory (no files): 5 Hz, the default material and controller. Reported
per run: the tail tip's peak-to-peak lateral excursion over the second half of the episode (as
`fishsim simulate`'s summary), the head's x displacement over the episode and its lateral
peak-to-peak over the second half, the mesh size, and the solid's wall time per step (the PD
step alone: `Swimmer.timer`'s solid phase over the frames, so the first compiled call is
included once; run on an otherwise idle machine for timings worth quoting). Deviations are
relative to the finest mesh of the same muscle model.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

EDGES = (3e-3, 2e-3, 1.4e-3, 1e-3)


def simulate_stroke(edge_length: float, muscles: str = "layer", fluid: str = "none", frames: int = 120,
                    overrides: tuple[str, ...] = ()) -> dict:
    """One in-memory `fishsim simulate` run; returns its stroke and cost numbers (module doc)."""
    from fishsim.commands.simulate import build_episode
    from fishsim.config import load_config
    from fishsim.rollout import rollout

    cfg = load_config("simulate", [f"fluid={fluid}", f"frames={frames}", f"fish.edge_length={edge_length}",
                                   f"fish.muscles={muscles}", *overrides])
    episode = build_episode(cfg)
    sw = episode.swimmer
    state = sw.initial_state(episode.params, episode.origin)
    t0 = time.perf_counter()
    with torch.no_grad():
        _, metrics = rollout(sw, state, episode.params, cfg.frames)
    wall = time.perf_counter() - t0
    m = {k: v[:, 0].numpy() for k, v in metrics.items()}
    half = frames // 2
    tail, head_y = m["tail_y"][half:], m["head_y"][half:]
    return {"edge_mm": 1e3 * edge_length, "muscles": muscles, "fluid": fluid, "nodes": sw.solid.n_nodes,
            "n_act": sw.solid.n_muscles, "tail_p2p_mm": 1e3 * float(tail.max() - tail.min()),
            "head_dx_mm": 1e3 * float(m["head_x"][-1] - episode.origin[0] - sw.solid.mesh.length),
            "head_y_p2p_mm": 1e3 * float(head_y.max() - head_y.min()),
            "solid_ms_per_step": 1e3 * sw.timer.seconds["solid"] / frames, "wall_s": wall}


def study(edges=EDGES, models=("layer", "paper"), fluid: str = "none", frames: int = 120,
          overrides: tuple[str, ...] = ()) -> list[dict]:
    """simulate_stroke for every muscle model and edge length, with each run's deviation from the
    finest mesh of its model (tail_dev, head_dev: relative)."""
    rows = []
    for model in models:
        runs = [simulate_stroke(e, model, fluid, frames, overrides) for e in edges]
        finest = min(runs, key=lambda r: r["edge_mm"])
        for r in runs:
            r["tail_dev"] = r["tail_p2p_mm"] / finest["tail_p2p_mm"] - 1
            r["head_dev"] = (r["head_dx_mm"] - finest["head_dx_mm"]) / max(abs(finest["head_dx_mm"]), 1e-12)
        rows += runs
    return rows


def to_markdown(rows: list[dict]) -> str:
    lines = [("| muscles | edge | nodes | muscles (elements) | tail peak-to-peak | vs finest | head x displacement "
              "| head y peak-to-peak | solid step |"),
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['muscles']} | {r['edge_mm']:.1f} mm | {r['nodes']} | {r['n_act']} | "
                     f"{r['tail_p2p_mm']:.1f} mm | {100 * r['tail_dev']:+.1f} % | {r['head_dx_mm']:+.2f} mm | "
                     f"{r['head_y_p2p_mm']:.2f} mm | {r['solid_ms_per_step']:.1f} ms |")
    return "\n".join(lines)


def main(argv=None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--edges", type=float, nargs="+", default=list(EDGES), help="edge lengths (m)")
    parser.add_argument("--muscles", nargs="+", default=["layer", "paper"], choices=["layer", "paper"])
    parser.add_argument("--fluid", default="none", choices=["none", "numerical", "hydronet"])
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("overrides", nargs="*", help="further `key=value` config overrides")
    args = parser.parse_args(argv)
    rows = study(tuple(args.edges), tuple(args.muscles), args.fluid, args.frames, tuple(args.overrides))
    print(f"fluid={args.fluid}, {args.frames} frames, 5 Hz unless overridden\n")
    print(to_markdown(rows))
    return rows


if __name__ == "__main__":
    np.set_printoptions(precision=4)
    main()
