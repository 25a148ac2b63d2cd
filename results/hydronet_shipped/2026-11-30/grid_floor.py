"""The reference's own grid error on the held-out scenes of `fishsim validate suite=hydronet`:
the numerical fluid at r = 2 judged exactly as HydroNet is (fishsim.learn.evaluate.evaluate: the
r = 1 solver's 50 warm-up steps, one step of each from that state (the r = 2 fluid prolongs it
and restricts its step), then 100-step rollouts), against the r = 1 reference. Its one-step and
force errors are what the r = 1 reference itself is uncertain by.

    python results/hydronet_shipped/2026-11-30/grid_floor.py > grid_floor.txt
"""
import json

import torch

from fishsim.fluid.hydronet.config import EvalConfig
from fishsim.learn.evaluate import evaluate, reference_fluid, summarise

torch.set_num_threads(1)
cfg = EvalConfig()
grid = cfg.tank.grid
result = evaluate(reference_fluid(grid, 2), reference_fluid(grid), cfg)
for name, m in result.metrics.items():
    print(f"{name:14s} one-step e_v {m['one_step_error_v']:.4f} e_p {m['one_step_error_p']:.4f}  "
          f"rollout e_v {m['rollout100_error_v']:.3f} e_p {m['rollout100_error_p']:.3f}  "
          f"F_x r2 {m['force_x_net']:.4g} r1 {m['force_x_ref']:.4g} ({m['force_x_net'] / m['force_x_ref'] - 1:+.1%})")
print(json.dumps(summarise(result.metrics)))
