"""The frequency study (120 frames, 3 / 5 / 7 Hz) with the shipped HydroNet's velocity projected
each step by the numerical fluid's joint penalisation + projection (a prototype: HydroNetFluid.step
wrapped here, nothing in the package). Argument: none (the shipped model as it is), v (velocity
projected), vp (and the pressure corrected by rho phi / h); then lambda dt (default 24).

Run from the repository root: PYTHONPATH=. .venv/bin/python results/hydronet_shipped/2026-12-01b/projected_study.py v 24
"""
import json
import sys

import torch

from fishsim.fields import FluidState
from fishsim.fluid.grid import curl, face_masks, stream_function, vector_to_faces
from fishsim.fluid.hydronet import unet
from fishsim.fluid.numerical import immerse, rate_weight
from fishsim.swim_study import episode

torch.set_num_threads(1)
mode = sys.argv[1]
lam_dt = float(sys.argv[2]) if len(sys.argv) > 2 else 24.0
network_step = unet.HydroNetFluid.step


def projected_step(self, state, boundary, params, start=None):
    new = network_step(self, state, boundary, params, start)
    if mode == "none":
        return new
    dx = self.grid.dx
    weight = rate_weight(face_masks(boundary.mask.to(new.a.dtype)))
    v, phi, _ = immerse(curl(new.a, dx), weight, vector_to_faces(boundary.velocity.to(new.a.dtype)), lam_dt, dx)
    p = new.p
    if mode == "vp":
        p = p + torch.as_tensor(params.rho, dtype=p.dtype).reshape(-1, 1, 1, 1) * phi / params.h
        p = p - p.mean(dim=(-2, -1), keepdim=True)
    return FluidState(a=stream_function(v, dx), p=p)


unet.HydroNetFluid.step = projected_step
r = episode(["fluid=hydronet"], [3.0, 5.0, 7.0], 120)
print(mode, lam_dt, json.dumps({k: r[k] for k in ("displacement_mm", "lateral_drift_mm", "mean_thrust_mN", "wall_s")}))
