"""The dense sweep behind `fishsim optimize experiment=codesign`: the objective of the co-design
experiment (head distance after 120 frames, numerical fluid, free swimming) on a grid of
frequency x amplitude C x Young's modulus E, evaluated batch by batch through the same
``Problem`` the optimisers use, so the README can say where the optimum is and whether each
optimiser found it.

    python -m benchmarks.study_codesign                        # 8 x 4 x 3 = 96 episodes (~26 min on 1 core)
    python -m benchmarks.study_codesign --out outputs/codesign_sweep.json --batch 12

Prints the best grid points and writes every (f, C, E, J) to --out (JSON).
"""

from __future__ import annotations

import argparse
import itertools
import json
import time

import torch

FREQUENCIES = (2.0, 4.0, 6.0, 8.0, 9.0, 10.0, 11.0, 12.0)
AMPLITUDES = (6.0, 10.0, 14.0, 18.0)
MODULI = (3.0e5, 6.0e5, 1.2e6)


def main() -> None:
    from fishsim.config import load_config
    from fishsim.optimize.problem import Problem, Space

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="outputs/codesign_sweep.json")
    ap.add_argument("--batch", type=int, default=12)
    ap.add_argument("overrides", nargs="*", help="more `fishsim optimize` overrides")
    args = ap.parse_args()
    cfg = load_config("optimize", ["experiment=codesign", *args.overrides])
    space = Space(list(cfg.params), list(cfg.params.values()))
    problem = Problem(cfg, space, cfg.objective)
    grid = [dict(zip(("frequency", "amplitude", "youngs_modulus"), p))
            for p in itertools.product(FREQUENCIES, AMPLITUDES, MODULI)]
    rows, t0 = [], time.perf_counter()
    for i in range(0, len(grid), args.batch):
        chunk = grid[i:i + args.batch]
        x = torch.tensor([[g[n] for n in space.names] for g in chunk], dtype=torch.float64)
        ev = problem.evaluate(space.to_z(x))
        rows += [{**g, "J": float(j)} for g, j in zip(chunk, ev.J.tolist())]
        print(f"{len(rows)}/{len(grid)} episodes, {time.perf_counter() - t0:.0f} s", flush=True)
    rows.sort(key=lambda r: -r["J"] if r["J"] == r["J"] else float("inf"))
    with open(args.out, "w") as f:
        json.dump({"objective": cfg.objective.name, "frames": cfg.frames, "fluid": cfg.fluid.model,
                   "wall_s": time.perf_counter() - t0, "rows": rows}, f, indent=1)
    print("best grid points (J = head distance [mm]):")
    for r in rows[:8]:
        print(f"  f {r['frequency']:.1f} Hz  C {r['amplitude']:.1f} 1/m  E {r['youngs_modulus']:.3g} Pa  J {1e3 * r['J']:.1f}")


if __name__ == "__main__":
    main()
