"""Where the shipped HydroNet's one-step error on the held-out scenes lives.

The protocol of `fishsim validate suite=hydronet` (fishsim.learn.evaluate.evaluate: the numerical
solver's 50 warm-up steps, then one step of each model from that state), with the squared error
of v split by region: the mask's band (0.01 < b < 0.99 at either adjacent cell), the fluid within
3 / 10 cells of the band, and the rest. Prints, per scene, the relative error e_v and the share of
its squared numerator in each region; likewise for the mean-free p.

    python results/hydronet_shipped/2026-11-30/error_regions.py [model_file] [symmetric]
"""
import sys

import torch
import torch.nn.functional as F

from fishsim.fields import FluidParams
from fishsim.fluid.grid import curl
from fishsim.fluid.hydronet.config import EvalConfig
from fishsim.fluid.hydronet.model_file import load_hydronet
from fishsim.fluid.hydronet.unet import HydroNetFluid
from fishsim.fluid.residual import fluid_face_masks
from fishsim.learn.evaluate import Scenes, common_start, reference_fluid

torch.set_num_threads(1)
model_file = sys.argv[1] if len(sys.argv) > 1 else "fishsim/assets/hydronet.pt"
symmetric = (sys.argv[2] != "false") if len(sys.argv) > 2 else True
cfg = EvalConfig()
scenes = Scenes(cfg)
grid, B = scenes.grid, len(scenes.names)
net = HydroNetFluid(load_hydronet(model_file), grid, symmetric=symmetric)
ref = reference_fluid(grid)
params = FluidParams(torch.full((B,), cfg.rho), torch.full((B,), cfg.mu), cfg.h)
with torch.no_grad():
    s = common_start(ref, scenes, params)
    bd = scenes.boundary(cfg.warmup + 1)
    n, r = net.step(s, bd, params), ref.step(s, bd, params)

b = bd.mask
band = ((b > 0.01) & (b < 0.99)).float()
def dilate(m, k):
    return (F.max_pool2d(m, 2 * k + 1, 1, k) > 0).float()
# bodies only: the tank's walls are in b too; the region counts from any band (walls included)
regions = {"band": band, "near3": dilate(band, 3) - band, "near10": dilate(band, 10) - dilate(band, 3)}
regions["far"] = 1 - dilate(band, 10)
def to_faces(m):
    fx = torch.maximum(F.pad(m, (1, 0)), F.pad(m, (0, 1)))
    fy = torch.maximum(F.pad(m, (0, 0, 1, 0)), F.pad(m, (0, 0, 0, 1)))
    return fx, fy
wv = fluid_face_masks(b)
vn, vr = curl(n.a, grid.dx), curl(r.a, grid.dx)
num = [w * (x - y) ** 2 for x, y, w in zip(vn, vr, wv)]
den = sum((w * y**2).flatten(1).sum(1) for y, w in zip(vr, wv))
total = sum(q.flatten(1).sum(1) for q in num)
wp = 1 - b
def free(p):
    return p - (wp * p).flatten(1).sum(1).view(-1, 1, 1, 1) / wp.flatten(1).sum(1).view(-1, 1, 1, 1)
pn, pr = free(n.p), free(r.p)
nump = wp * (pn - pr) ** 2
denp = (wp * pr**2).flatten(1).sum(1)
print(f"model {model_file} symmetric={symmetric}")
print("scene            e_v    " + "  ".join(f"{k:>7}" for k in regions) + "  |  e_p    " + "  ".join(f"{k:>7}" for k in regions))
for i, name in enumerate(scenes.names):
    sv, sp = [], []
    for m in regions.values():
        fx, fy = to_faces(m)
        # a face's region: the nearer of its two cells' (max of indicator for band/near, consistent enough)
        sv.append(((num[0][i] * fx[i]).sum() + (num[1][i] * fy[i]).sum()).item() / total[i].item())
        sp.append((nump[i] * m[i]).sum().item() / nump[i].sum().item())
    print(f"{name:14s} {(total[i] / den[i]).sqrt().item():6.3f}  " + "  ".join(f"{x:7.2f}" for x in sv)
          + f"  | {(nump[i].sum() / denp[i]).sqrt().item():6.3f}  " + "  ".join(f"{x:7.2f}" for x in sp))

if len(sys.argv) > 3:   # a picture: p_ref, p_net - p_ref and |v_net - v_ref| of the fish scenes
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from fishsim.fluid.grid import faces_to_centres
    fish = [i for i, name in enumerate(scenes.names) if name.startswith("fish")]
    fig, ax = plt.subplots(len(fish), 3, figsize=(15, 2.2 * len(fish)))
    for row, i in enumerate(fish):
        e = (pn - pr)[i, 0] * wp[i, 0]
        lim = pr[i, 0].abs().max().item()
        for col, (field, title) in enumerate(((pr[i, 0] * wp[i, 0], "p_ref"), (e, "p_net - p_ref"))):
            ax[row, col].imshow(field.numpy(), origin="lower", cmap="RdBu_r", vmin=-lim, vmax=lim)
            ax[row, col].set_title(f"{scenes.names[i]}: {title} (+-{lim:.3g} Pa)", fontsize=8)
        ev = (faces_to_centres(vn)[i] - faces_to_centres(vr)[i]).norm(dim=0) * wp[i, 0]
        im = ax[row, 2].imshow(ev.numpy(), origin="lower", cmap="magma")
        ax[row, 2].set_title(f"|v_net - v_ref| (max {ev.max().item():.3g} m/s)", fontsize=8)
    for a in ax.flat:
        a.set_xticks([]); a.set_yticks([])
    fig.tight_layout()
    fig.savefig(sys.argv[3], dpi=90)
