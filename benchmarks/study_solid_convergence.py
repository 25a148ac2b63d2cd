"""Mesh convergence of the swimming solid: the same fish, controller and fluid at several element
sizes, with the default muscle layer and with the paper's station muscles.

    python -m benchmarks.study_solid_convergence                          # vacuum, both muscle models
    python -m benchmarks.study_solid_convergence --fluid numerical        # in the numerical fluid (~1 min)
    python -m benchmarks.study_solid_convergence --edges 3e-3 2e-3 --muscles layer --frames 60
    python -m benchmarks.study_solid_convergence --beam                   # the cantilever against beam theory
    python -m benchmarks.study_solid_convergence --timing                 # PD step cost per edge length

Each run is `fishsim simulate fluid=<fluid> frames=<frames> fish.edge_length=<edge>
fish.muscles=<model>` in memory (no files): 5 Hz, the default material and controller. Reported
per run: the tail tip's peak-to-peak lateral excursion over the second half of the episode (as
`fishsim simulate`'s summary), the head's x displacement over the episode and its lateral
peak-to-peak over the second half, the mesh size, and the solid's wall time per step (the PD
step alone: `Swimmer.timer`'s solid phase over the frames, so the first compiled call is
included once; run on an otherwise idle machine for timings worth quoting). Deviations are
relative to the finest mesh of the same muscle model.

`--timing`: the solid step alone per edge length (default muscle layer, 5 Hz, vacuum, B = 1,
after 40 warm-up steps): forward and backward ms per step, best of 5 repeats of 20 steps, with
benchmarks/bench_solid.py's timers.

`--beam`: the passive validation of fishsim/solid/beam.py (a clamped 100 x 5 mm cantilever of
the fish's material under a tip load giving 1 mm of deflection): static tip deflection and first
bending frequency against Euler-Bernoulli at 2, 4, 8 and 16 elements across the thickness.
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


def beam_study(across=(2, 4, 8, 16), volume_term: bool = False) -> list[dict]:
    """Cantilever tip deflection and first frequency against Euler-Bernoulli (relative errors)."""
    from fishsim.solid.beam import Cantilever
    from fishsim.solid.model import SolidMaterial

    beam = Cantilever(material=SolidMaterial(volume_term=volume_term))
    load = 3 * beam.bending_stiffness * 1e-3 / beam.length**3          # 1 mm tip deflection
    rows = []
    for n in across:
        deflection, q = beam.static_deflection(beam.thickness / n, load)
        frequency = beam.vibration_frequency(beam.thickness / n, load)
        rows.append({"across": n, "edge_mm": 1e3 * beam.thickness / n, "nodes": q.shape[1],
                     "static_err": deflection / beam.tip_deflection(load) - 1,
                     "frequency_err": frequency / beam.first_frequency() - 1})
    return rows


def beam_markdown(rows: list[dict]) -> str:
    lines = ["| elements across | edge | nodes | tip deflection error | first frequency error |", "|---|---|---|---|---|"]
    lines += [f"| {r['across']} | {r['edge_mm']:.3g} mm | {r['nodes']} | {100 * r['static_err']:+.2f} % | "
              f"{100 * r['frequency_err']:+.2f} % |" for r in rows]
    return "\n".join(lines)


def timing_study(edges=EDGES, steps: int = 20, warmup: int = 40, repeats: int = 5) -> list[dict]:
    """Forward / backward ms per PD step and L-BFGS iterations at B = 1 for each edge length."""
    from benchmarks.bench_solid import _controller, _time_backward, _time_forward, _warm_state
    from fishsim.mesh import make_fish_mesh
    from fishsim.solid import SolidModel
    from fishsim.solid.muscles import layer_muscles

    torch.set_num_threads(1)
    rows = []
    for e in edges:
        mesh = make_fish_mesh(edge_length=e)
        model = SolidModel(mesh, muscles=layer_muscles(mesh, 0.3))
        ctrl = _controller(1, mesh.length)
        q, qdot, qdot_prev = _warm_state(model, ctrl, warmup)
        fwd, its, _ = min(_time_forward(model, ctrl, q, qdot, qdot_prev, warmup, steps) for _ in range(repeats))
        bwd, _ = min(_time_backward(model, ctrl, q, qdot, warmup, steps) for _ in range(repeats))
        rows.append({"edge_mm": 1e3 * e, "nodes": model.n_nodes, "half_bandwidth": model.newton_band.layout.width,
                     "forward_ms": fwd, "backward_ms": bwd, "iterations": its})
    return rows


def timing_markdown(rows: list[dict]) -> str:
    lines = ["| edge | nodes | Newton half-bandwidth | forward per step | backward per step | L-BFGS iterations |",
             "|---|---|---|---|---|---|"]
    lines += [f"| {r['edge_mm']:.1f} mm | {r['nodes']} | {r['half_bandwidth']} | {r['forward_ms']:.1f} ms | "
              f"{r['backward_ms']:.1f} ms | {r['iterations']:.1f} |" for r in rows]
    return "\n".join(lines)


def main(argv=None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--edges", type=float, nargs="+", default=list(EDGES), help="edge lengths (m)")
    parser.add_argument("--muscles", nargs="+", default=["layer", "paper"], choices=["layer", "paper"])
    parser.add_argument("--fluid", default="none", choices=["none", "numerical", "hydronet"])
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--beam", action="store_true", help="the cantilever validation instead")
    parser.add_argument("--timing", action="store_true", help="the PD step's cost per edge length instead")
    parser.add_argument("overrides", nargs="*", help="further `key=value` config overrides")
    args = parser.parse_args(argv)
    if args.timing:
        rows = timing_study(tuple(args.edges))
        print(timing_markdown(rows))
        return rows
    if args.beam:
        rows = beam_study()
        print(beam_markdown(rows))
        return rows
    rows = study(tuple(args.edges), tuple(args.muscles), args.fluid, args.frames, tuple(args.overrides))
    print(f"fluid={args.fluid}, {args.frames} frames, 5 Hz unless overridden\n")
    print(to_markdown(rows))
    return rows


if __name__ == "__main__":
    np.set_printoptions(precision=4)
    main()
