"""A dense sweep of an optimisation's objective: J on a grid of parameter values, evaluated batch
by batch through the same ``Problem`` the optimisers use, so the README can say where the optimum
is and whether each optimiser found it.

    python -m benchmarks.sweep experiment=codesign                 # the co-design grid, 96 episodes (~35 min, 1 core)
    python -m benchmarks.sweep experiment=paper_fig5 --grid frequency=1,2,3,4,5,6,7,8,9,10,10.5 \\
        --batch 11 --out outputs/fig5_sweep.json                   # the Fig. 5 thrust curve (~8 min, 1 core)

--grid name=v1,v2,... (repeatable) gives the values of each optimised parameter (``params``);
the default grid is the co-design one (frequency x amplitude C x Young's modulus E). Members of a
batch are independent fish (each runs its own sub-step count in the numerical fluid; HydroNet's
round-off differs with the batch, README "Measured: the paper's Fig. 5").
Prints the best grid points and writes every (parameters, J) to --out (JSON).
"""

from __future__ import annotations

import argparse
import itertools
import json
import time

import torch

CODESIGN_GRID = {"frequency": (2.0, 4.0, 6.0, 8.0, 9.0, 10.0, 11.0, 12.0), "amplitude": (6.0, 10.0, 14.0, 18.0),
                 "youngs_modulus": (3.0e5, 6.0e5, 1.2e6)}


def parse_grid(items: list[str] | None) -> dict[str, tuple[float, ...]]:
    """``["frequency=1,2", ...]`` -> {"frequency": (1.0, 2.0), ...}; None: the co-design grid."""
    if not items:
        return CODESIGN_GRID
    grid = {}
    for item in items:
        name, _, values = item.partition("=")
        grid[name] = tuple(float(v) for v in values.split(","))
    return grid


def main() -> None:
    from fishsim.config import load_config
    from fishsim.optimize.problem import Problem, Space

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grid", action="append", help="name=v1,v2,... for one optimised parameter (repeatable)")
    ap.add_argument("--out", default="outputs/sweep.json")
    ap.add_argument("--batch", type=int, default=12)
    ap.add_argument("overrides", nargs="*", help="`fishsim optimize` overrides, e.g. experiment=codesign")
    args = ap.parse_args()
    cfg = load_config("optimize", args.overrides)
    space = Space(list(cfg.params), list(cfg.params.values()))
    grid = parse_grid(args.grid)
    if sorted(grid) != sorted(space.names):
        ap.error(f"--grid names {sorted(grid)} must be the optimised parameters {sorted(space.names)}")
    problem = Problem(cfg, space, cfg.objective)
    points = [dict(zip(grid, p)) for p in itertools.product(*grid.values())]
    rows, t0 = [], time.perf_counter()
    for i in range(0, len(points), args.batch):
        chunk = points[i:i + args.batch]
        x = torch.tensor([[g[n] for n in space.names] for g in chunk], dtype=torch.float64)
        ev = problem.evaluate(space.to_z(x))
        rows += [{**g, "J": float(j)} for g, j in zip(chunk, ev.J.tolist())]
        print(f"{len(rows)}/{len(points)} episodes, {time.perf_counter() - t0:.0f} s", flush=True)
    with open(args.out, "w") as f:
        json.dump({"objective": cfg.objective.name, "frames": cfg.frames, "fluid": cfg.fluid.model,
                   "wall_s": time.perf_counter() - t0, "rows": rows}, f, indent=1)
    best = sorted(rows, key=lambda r: -r["J"] if r["J"] == r["J"] else float("inf"))
    print(f"best grid points ({cfg.objective.name} J):")
    for r in best[:8]:
        print("  " + "  ".join(f"{n} {r[n]:.4g}" for n in grid) + f"  J {r['J']:.5g}")


if __name__ == "__main__":
    main()
