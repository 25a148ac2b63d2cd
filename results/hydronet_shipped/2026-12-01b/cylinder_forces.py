"""The IBM pressure force (F_x, N/m) on each held-out body over the 100-step rollouts of `fishsim
validate suite=hydronet`, the shipped HydroNet against the numerical reference, every 10 steps.

Run from the repository root: PYTHONPATH=. .venv/bin/python results/hydronet_shipped/2026-12-01b/cylinder_forces.py
"""
import numpy as np
import torch

from fishsim.config import HydroNetConfig
from fishsim.fluid.factory import make_fluid
from fishsim.fluid.hydronet.config import EvalConfig
from fishsim.learn.evaluate import body_forces, held_out_rollout, held_out_step, reference_fluid

torch.set_num_threads(2)
cfg = EvalConfig()
held = held_out_step(cfg=cfg)
scenes = held.scenes
forces = {}
with torch.no_grad():
    for name, model in (("net", make_fluid(HydroNetConfig(), cfg.tank)), ("ref", reference_fluid(cfg.tank.grid))):
        history = [body_forces(scenes, new, boundary, k)[:, 0] for k, _, new, boundary in held_out_rollout(model, held, cfg)]
        forces[name] = torch.stack(history).numpy()
print("scenes", scenes.names)
print("mean F_x net", forces["net"].mean(0).round(5))
print("mean F_x ref", forces["ref"].mean(0).round(5))
print("ratio      ", (forces["net"].mean(0) / forces["ref"].mean(0)).round(2))
for k in range(0, cfg.steps, 10):
    print(f"step {k:3d} cylinders net", np.round(forces["net"][k, :3], 5), "ref", np.round(forces["ref"][k, :3], 5))
