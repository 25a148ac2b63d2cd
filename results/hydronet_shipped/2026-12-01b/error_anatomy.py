"""Where the shipped HydroNet's one-step error lies on the held-out scenes of `fishsim validate
suite=hydronet` (its common start S_0 and the reference's step from it), and what a penalised
projection of the network's velocity (the numerical fluid's joint stage, ``numerical.immerse``)
would remove of it.

Run from the repository root: PYTHONPATH=. .venv/bin/python results/hydronet_shipped/2026-12-01b/error_anatomy.py
"""
import numpy as np
import torch
from scipy import ndimage

from fishsim.config import HydroNetConfig
from fishsim.fields import FluidState
from fishsim.fluid.factory import make_fluid
from fishsim.fluid.grid import curl, face_masks, faces_to_centres, stream_function, vector_to_faces
from fishsim.fluid.hydronet.config import EvalConfig
from fishsim.fluid.numerical import immerse, rate_weight
from fishsim.learn.evaluate import held_out_step, relative_errors

torch.set_num_threads(2)
cfg = EvalConfig()
dx, h = cfg.tank.dx, cfg.h
held = held_out_step(cfg=cfg)
net = make_fluid(HydroNetConfig(), cfg.tank)
with torch.no_grad():
    out = net.step(held.start, held.boundary, held.params)


e_v, e_p = relative_errors(out, held.reference, held.boundary.mask, dx)
print("scenes", held.scenes.names)
print("one-step e_v", e_v.numpy().round(3), "e_p", e_p.numpy().round(3))
v_net, v_ref, v_0 = (faces_to_centres(curl(a, dx)).numpy() for a in (out.a, held.reference.a, held.start.a))
bands = ((0, 1), (1, 2), (2, 4), (4, 8), (8, 1e9))
print("per scene: e_v at cell centres; the reference's own one-step change |v_1 - v_0| / |v_1|; the error's share"
      " by distance from the body and walls (cells, b > 1/2) 0-1 / 1-2 / 2-4 / 4-8 / > 8")
for n, name in enumerate(held.scenes.names):
    b = held.boundary.mask[n, 0].numpy()
    distance = ndimage.distance_transform_edt(b <= 0.5)
    fluid = 1 - b
    err = ((v_net[n] - v_ref[n]) ** 2).sum(0) * fluid
    norm = ((v_ref[n] ** 2).sum(0) * fluid).sum()
    change = (((v_ref[n] - v_0[n]) ** 2).sum(0) * fluid).sum()
    shares = [err[(distance > lo) & (distance <= hi)].sum() / err.sum() for lo, hi in bands]
    print(f"{name:14s} e_v {np.sqrt(err.sum() / norm):.3f}  change {np.sqrt(change / norm):.3f}  shares",
          np.round(shares, 2))

print("the network's velocity projected by the joint penalisation + projection (lambda dt), its pressure"
      " as it is or plus rho phi / h")
rho = held.params.rho.view(-1, 1, 1, 1)
with torch.no_grad():
    weight = rate_weight(face_masks(held.boundary.mask))
    v_d = vector_to_faces(held.boundary.velocity)
    for lam_dt in (2400 * h, 2400 * h / 4):
        v, phi, _ = immerse(curl(out.a, dx), weight, v_d, lam_dt, dx)
        a = stream_function(v, dx)
        for label, p in (("p", out.p), ("p + rho phi / h", out.p + rho * phi / h)):
            e_v2, e_p2 = relative_errors(FluidState(a=a, p=p), held.reference, held.boundary.mask, dx)
            print(f"lambda dt {lam_dt:g}, {label:16s} e_v", e_v2.numpy().round(3), "e_p", e_p2.numpy().round(3))
