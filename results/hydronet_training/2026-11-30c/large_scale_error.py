"""Share of the one-step pressure error (net - solver, mean-free on fluid cells) at large scales:
energy of the error blurred by a Gaussian of std 8 cells over the error's energy, per held-out scene,
from `fishsim validate suite=hydronet`'s common start (the solver's warm-up), one step.

    python results/hydronet_training/2026-11-30c/large_scale_error.py MODEL_FILE [MODEL_FILE ...]
"""
import sys

import torch
import torch.nn.functional as F

from fishsim.fluid.hydronet.loss import mean_free
from fishsim.fluid.hydronet.model_file import load_hydronet
from fishsim.fluid.hydronet.unet import HydroNetFluid
from fishsim.learn.evaluate import held_out_step

torch.set_num_threads(1)
first = held_out_step()
grid, params, s, bd, r = first.scenes.grid, first.params, first.start, first.boundary, first.reference
with torch.no_grad():
    w = 1 - bd.mask
    x = torch.arange(-24, 25, dtype=torch.float32)
    g = torch.exp(-x**2 / (2 * 8.0**2)); g = g / g.sum()
    def blur(f):
        f = F.conv2d(F.pad(f, (24, 24, 0, 0), mode="replicate"), g.view(1, 1, 1, -1))
        return F.conv2d(F.pad(f, (0, 0, 24, 24), mode="replicate"), g.view(1, 1, -1, 1))
    for m in sys.argv[1:]:
        n = HydroNetFluid(load_hydronet(m), grid).step(s, bd, params)
        e = mean_free(n.p - r.p, w)
        eb = mean_free(blur(e), w)
        tot = (w * e**2).flatten(1).sum(1); low = (w * eb**2).flatten(1).sum(1)
        ep = (tot / (w * mean_free(r.p, w)**2).flatten(1).sum(1)).sqrt()
        print(m, "e_p", " ".join(f"{v:.3f}" for v in ep.tolist()), "| large-scale share", " ".join(f"{v:.2f}" for v in (low / tot).tolist()))
