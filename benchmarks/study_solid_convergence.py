"""Mesh convergence of the swimming solid (fishsim/solid_study.py: the studies, also run by
`fishsim validate suite=solid`): the same fish, controller and fluid at several element sizes,
with the default muscle layer and with the paper's station muscles.

    python -m benchmarks.study_solid_convergence                          # vacuum, both muscle models
    python -m benchmarks.study_solid_convergence --fluid numerical        # in the numerical fluid (minutes)
    python -m benchmarks.study_solid_convergence --edges 3e-3 2e-3 --muscles layer --frames 60
    python -m benchmarks.study_solid_convergence --beam                   # the cantilever against beam theory
    python -m benchmarks.study_solid_convergence --timing                 # PD step cost per edge length

The stroke table's columns are those of fishsim.solid_study.stroke_study (its solid step
includes the first compiled call once; run on an otherwise idle machine for timings worth
quoting).

`--timing`: the solid step alone per edge length (default muscle layer, 5 Hz, vacuum, B = 1,
after 40 warm-up steps): forward and backward ms per step, best of 5 repeats of 20 steps, with
benchmarks/bench_solid.py's timers.

`--beam`: fishsim.solid_study.beam_study: the clamped 100 x 5 mm cantilever's static tip
deflection and first bending frequency against Euler-Bernoulli at 2, 4, 8 and 16 elements
across the thickness.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from fishsim.solid_study import EDGES, beam_markdown, beam_study, stroke_markdown, stroke_study


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
    rows = stroke_study(tuple(args.edges), tuple(args.muscles), args.fluid, args.frames, tuple(args.overrides))
    print(f"fluid={args.fluid}, {args.frames} frames, 5 Hz unless overridden\n")
    print(stroke_markdown(rows))
    return rows


if __name__ == "__main__":
    np.set_printoptions(precision=4)
    main()
