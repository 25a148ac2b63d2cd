"""Where along the held-out fish the network's force departs from the solver's.

The prescribed fish of `fishsim validate suite=hydronet` (held at the tank's centre, 3 / 5 / 7 Hz),
each model rolled out from rest for 150 steps on the same boundaries; the IBM pressure force on
every surface node (coupling defaults) summed over the head (front third), the middle third and
the tail (back third) by the node's body coordinate, time-averaged over steps 50-150: the mean
x force (thrust > 0) and the RMS of the lateral (y) force of each region, net / solver.

    python results/hydronet_shipped/2026-11-30/force_regions.py [model_file] > force_regions.txt
"""
import sys

import numpy as np
import torch

from fishsim.coupling.ibm import ibm_force
from fishsim.fields import FluidParams
from fishsim.fluid.hydronet.config import EvalConfig
from fishsim.fluid.hydronet.model_file import load_hydronet
from fishsim.fluid.hydronet.unet import HydroNetFluid
from fishsim.learn.evaluate import Scenes, reference_fluid
from fishsim.learn.pool import fish_outline

torch.set_num_threads(1)
model_file = sys.argv[1] if len(sys.argv) > 1 else "fishsim/assets/hydronet.pt"
cfg = EvalConfig(speeds=())
scenes = Scenes(cfg)
grid, B = scenes.grid, len(scenes.names)
X = fish_outline()[:, 0]                                  # body coordinate / L, 0 at the tail
regions = {"tail": X < 1 / 3, "middle": (X >= 1 / 3) & (X < 2 / 3), "head": X >= 2 / 3}
params = FluidParams(torch.full((B,), cfg.rho), torch.full((B,), cfg.mu), cfg.h)
out = {}
for name, model in (("net", HydroNetFluid(load_hydronet(model_file), grid)), ("ref", reference_fluid(grid))):
    s, rec = model.initial_state(B), []
    with torch.no_grad():
        for k in range(1, 151):
            bd = scenes.boundary(k)
            s = model.step(s, bd, params)
            if k > 50:
                qs = torch.cat(scenes.surfaces(k))
                rec.append(ibm_force(qs, s.p, bd.mask, grid).numpy())      # [B, S, 2]
    out[name] = np.stack(rec)                                             # [T, B, S, 2]
print(f"model {model_file}; steps 51-150; net / solver (solver's value in N/m)")
print("scene       region   mean F_x            rms F_y")
for b, scene in enumerate(scenes.names):
    for reg, sel in regions.items():
        fx = {m: out[m][:, b, sel, 0].sum(-1).mean() for m in out}
        fy = {m: np.sqrt((out[m][:, b, sel, 1].sum(-1) ** 2).mean()) for m in out}
        print(f"{scene:11s} {reg:7s} {fx['net'] / fx['ref']:6.3f} ({fx['ref']:+.4f})  {fy['net'] / fy['ref']:6.3f} ({fy['ref']:.4f})")
    fx = {m: out[m][:, b, :, 0].sum(-1).mean() for m in out}
    print(f"{scene:11s} {'all':7s} {fx['net'] / fx['ref']:6.3f} ({fx['ref']:+.4f})")
