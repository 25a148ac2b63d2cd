"""PhiFlow 3.4's incompressible step on fishsim's grid, for the side-by-side of the README's
"Measured speed": 100 x 300 cells of 2.5 mm (the paper's 0.75 x 0.25 m tank, closed walls), a
10 x 2 cm box moving at 0.1 m/s through water at rest, nu = 2.5e-6 m^2/s, dt = h = 0.01 s:
semi-Lagrangian advection, explicit diffusion and ``pf.fluid.make_incompressible`` with the moving
obstacle (PhiFlow's ``Solve('auto')`` to 1e-3; its CG does not converge on this closed box with
a moving obstacle). Prints ms per step over steps 10-39 (min and median).

PhiFlow is not a fishsim dependency: run it in its own environment, e.g.

    python -m venv /tmp/pf && /tmp/pf/bin/pip install phiflow==3.4.0 torch==2.13.0
    /tmp/pf/bin/python benchmarks/phiflow_step.py numpy        # or: torch (no jit_compile:
                                                                # phiml's torch tracing fails
                                                                # with torch 2.13)
fishsim's step on the same grid: ``python -m benchmarks.bench_fluid`` (r1_B1 forward_ms)."""

import json
import sys
import time

BACKEND = sys.argv[1] if len(sys.argv) > 1 else "numpy"
if BACKEND == "torch":
    import phi.torch.flow as pf
    import torch

    torch.set_num_threads(2)
else:
    import phi.flow as pf

NU, DT, SPEED = 2.5e-6, 0.01, 0.1


def step(v, p, x0):
    """One step of h with the box's left end at x0 [m]."""
    box = pf.Obstacle(pf.Box(x=(x0, x0 + 0.1), y=(0.115, 0.135)), velocity=pf.vec(x=SPEED, y=0))
    v = pf.advect.semi_lagrangian(v, v, DT)
    v = pf.diffuse.explicit(v, NU, DT)
    return pf.fluid.make_incompressible(v, (box,), pf.Solve("auto", 1e-3, 1e-3, x0=p))


def main() -> None:
    domain = pf.Box(x=0.75, y=0.25)
    v, p = pf.StaggeredGrid(0, 0, domain, x=300, y=100), pf.CenteredGrid(0, 0, domain, x=300, y=100)
    run = step if BACKEND == "torch" else pf.jit_compile(step)
    times = []
    for k in range(40):
        t0 = time.perf_counter()
        v, p = run(v, p, pf.tensor(0.1 + SPEED * DT * k))
        times.append(time.perf_counter() - t0)
    t = sorted(times[10:])
    print(json.dumps({"phiflow_backend": BACKEND, "grid": "100x300", "min_ms": 1e3 * t[0],
                      "median_ms": 1e3 * t[len(t) // 2]}))


if __name__ == "__main__":
    main()
