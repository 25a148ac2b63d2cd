"""Does the network compute its pressure or carry it forward?

From the common start state S_0 of `fishsim validate suite=hydronet` (the solver's 50 warm-up steps),
one step of the network (symmetric, as shipped) and of the solver; on the fluid cells, with every
pressure made mean free:

* e_p of the network, of the network given p_t = 0 or 2 p_t as input, and of persistence
  (p_t+1 = p_t) against the solver's p_t+1;
* d p_out / d p_in: the least-squares slope of the network's output change on p_t when p_t is doubled;
* the one-step change dp = p_t+1 - p_t: the least-squares scale and the correlation of the network's
  on the solver's (the solver's |dp| / |p_t+1| is persistence's e_p).

    python results/hydronet_shipped/2026-11-30/pressure_persistence.py [model_file] > pressure_persistence.txt
"""
import sys

import torch

from fishsim.fields import FluidParams, FluidState
from fishsim.fluid.hydronet.config import EvalConfig
from fishsim.fluid.hydronet.model_file import load_hydronet
from fishsim.fluid.hydronet.unet import HydroNetFluid
from fishsim.learn.evaluate import Scenes, common_start, reference_fluid

torch.set_num_threads(1)
model_file = sys.argv[1] if len(sys.argv) > 1 else "fishsim/assets/hydronet.pt"
cfg = EvalConfig()
scenes = Scenes(cfg)
grid, B = scenes.grid, len(scenes.names)
net, ref = HydroNetFluid(load_hydronet(model_file), grid), reference_fluid(grid)
params = FluidParams(torch.full((B,), cfg.rho), torch.full((B,), cfg.mu), cfg.h)
with torch.no_grad():
    s = common_start(ref, scenes, params)
    bd = scenes.boundary(cfg.warmup + 1)
    n, r = net.step(s, bd, params), ref.step(s, bd, params)
    n0 = net.step(FluidState(s.a, torch.zeros_like(s.p)), bd, params)
    n2 = net.step(FluidState(s.a, 2 * s.p), bd, params)
w = 1 - bd.mask


def free(p):
    return p - (w * p).flatten(1).sum(1).view(-1, 1, 1, 1) / w.flatten(1).sum(1).view(-1, 1, 1, 1)


def dot(x, y):
    return (w * x * y).flatten(1).sum(1)


def err(x):
    return (dot(free(x) - free(r.p), free(x) - free(r.p)) / dot(free(r.p), free(r.p))).sqrt()


dn, dr, q = free(n.p) - free(s.p), free(r.p) - free(s.p), free(s.p)
rows = {"e_p, network": err(n.p), "e_p, network given p_t = 0": err(n0.p), "e_p, network given 2 p_t": err(n2.p),
        "e_p, persistence (p_t+1 = p_t)": err(s.p),
        "d p_out / d p_in": dot(free(n2.p) - free(n.p), q) / dot(q, q),
        "dp: scale, network on solver": dot(dn, dr) / dot(dr, dr),
        "dp: correlation": dot(dn, dr) / (dot(dn, dn) * dot(dr, dr)).sqrt()}
print(f"model {model_file}\n| quantity | " + " | ".join(scenes.names) + " |\n|---|" + "---|" * B)
for name, v in rows.items():
    print(f"| {name} | " + " | ".join(f"{x:.3f}" for x in v.tolist()) + " |")
