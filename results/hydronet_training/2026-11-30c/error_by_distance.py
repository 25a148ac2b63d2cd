"""Where the one-step pressure error lies relative to the network's reach: the held-out scenes from `fishsim
validate suite=hydronet`'s common start, one step; the error (net - solver, mean-free on the fluid cells) split
into cells within 32 cells, 32-64 cells and beyond 64 cells of the moving body (the tank's walls excluded), each
band's share of the error's energy and its relative error against the solver's pressure there.

    python results/hydronet_training/2026-11-30c/error_by_distance.py MODEL_FILE [MODEL_FILE ...]
"""
import sys

import torch
from scipy.ndimage import distance_transform_edt

from fishsim.fluid.hydronet.loss import mean_free
from fishsim.fluid.hydronet.model_file import load_hydronet
from fishsim.fluid.hydronet.unet import HydroNetFluid
from fishsim.learn.evaluate import held_out_step

torch.set_num_threads(1)
first = held_out_step()
scenes, grid, params, s, bd, r = first.scenes, first.scenes.grid, first.params, first.start, first.boundary, first.reference
B = len(scenes.names)
w = 1 - bd.mask
tank = bd.mask.amin(0, keepdim=True)            # the walls: solid in every scene
body = ((bd.mask - tank) > 0.5).numpy()
dist = torch.stack([torch.as_tensor(distance_transform_edt(~body[i, 0]), dtype=torch.float32)[None]
                    for i in range(B)])
bands = {"< 32": dist < 32, "32-64": (dist >= 32) & (dist < 64), ">= 64": dist >= 64}

for m in sys.argv[1:]:
    with torch.no_grad():
        n = HydroNetFluid(load_hydronet(m), grid).step(s, bd, params)
    e, q = mean_free(n.p - r.p, w), mean_free(r.p, w)
    total = (w * e**2).flatten(1).sum(1)
    print(f"model {m}\n| band | " + " | ".join(scenes.names) + " |\n|---|" + "---|" * B)
    for name, sel in bands.items():
        ws = w * sel
        share = (ws * e**2).flatten(1).sum(1) / total
        rel = ((ws * e**2).flatten(1).sum(1) / (ws * q**2).flatten(1).sum(1).clamp_min(1e-30)).sqrt()
        print(f"| {name}: share of error / e_p there | " + " | ".join(f"{a:.2f} / {b:.2f}" for a, b in zip(share.tolist(), rel.tolist())) + " |")
