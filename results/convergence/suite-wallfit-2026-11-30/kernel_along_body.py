"""Where along the fish the IBM force depends on the kernel's width, for the free plane and the
wall fit: the 7 Hz fish coupled by the wall fit (kernel std one cell), and each frame from 61 on
the four forces (fit "linear" or "wall" x kernel std one or two cells) read from the same
pressure; mean F_x and RMS F_y (mN/m) per 20 mm bin behind the head.

    python results/convergence/suite-wallfit-2026-11-30/kernel_along_body.py [frequency]
"""
import sys

import numpy as np
import torch

import fishsim.rollout as R
from fishsim.config import load_config
from fishsim.coupling.ibm import ibm_force
from fishsim.coupling.layer import surface_index
from fishsim.episode import build_episode
from fishsim.rollout import head_node, rollout

torch.set_num_threads(1)
f = float(sys.argv[1]) if len(sys.argv) > 1 else 7.0
sim = load_config("simulate", ["frames=120", f"batch.frequency=[{f}]", "coupling.ibm_fit=wall"])
ep = build_episode(sim); sw = ep.swimmer
g, idx = sw.fluid.grid, surface_index(sw.surface, "cpu")
head = head_node(sw.solid.mesh)
f2s0, frame0 = R.fluid_to_solid, sw.frame
now = {}
def sampled(q, p, boundary, surface, grid, cfg, step=None, mass=None, viscous=None, wall=None):
    now.update(q=q, p=p, mask=boundary.mask, wall=wall)
    return f2s0(q, p, boundary, surface, grid, cfg, step=step, mass=mass, viscous=viscous, wall=wall)
rows = []
def fr(state, params, t, *a, **k):
    out = frame0(state, params, t, *a, **k)
    if t >= 60:
        q = now["q"]; qs = q[0, idx, 0].double().numpy()
        dist = float(q[0, head, 0]) - qs
        bins = np.clip((dist / 0.02).astype(int), 0, 10)
        row = []
        for fit in ("linear", "wall"):
            for sp in (6.25e-6, 2.5e-5):
                fk = ibm_force(q, now["p"], now["mask"], g, sp, fit=fit, surface=idx,
                               wall=now["wall"] if fit == "wall" else None)[0].double().numpy()
                row.append(np.stack([np.bincount(bins, fk[:, 0], 11), np.bincount(bins, fk[:, 1], 11)]))
        rows.append(row)
    return out
R.fluid_to_solid, sw.frame = sampled, fr
with torch.no_grad():
    rollout(sw, sw.initial_state(ep.params, ep.origin), ep.params, 120)
a = 1e3 * np.array(rows)            # [T, 4 (lin1, lin2, wall1, wall2), 2, 11]
mx, ry = a[:, :, 0].mean(0), np.sqrt((a[:, :, 1] ** 2).mean(0))
print(f"{f} Hz, wall-coupled, frames 61-120: mean F_x [mN/m] per 20 mm bin (linear std1 / std2 | wall std1 / std2)")
for b in range(11):
    if abs(mx[:, b]).max() > 0.05:
        print(f"{20*b:4d}-{20*b+20:3d} mm: {mx[0,b]:+7.2f} {mx[1,b]:+7.2f} | {mx[2,b]:+7.2f} {mx[3,b]:+7.2f}   RMS F_y {ry[0,b]:6.1f} {ry[1,b]:6.1f} | {ry[2,b]:6.1f} {ry[3,b]:6.1f}")
print("total F_x:", " ".join(f"{x:+.2f}" for x in mx.sum(1)))
