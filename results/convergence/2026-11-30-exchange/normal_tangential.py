"""The swimming fish's momentum exchange split into the part normal to its surface and the part
along it (each cell's exchanged force F_c projected on the outward normal n and tangent t of
the nearest surface node), against the sampled pressure, which is normal by construction.

The default fish (5 Hz by default, 120 frames, the numerical fluid, coupled by the sampled
pressure); means over frames 61-120 of the x forces (mN/m) over the whole fish and over its
last 50 mm, and the RMS of each part's y force.

    python results/convergence/2026-11-30-exchange/normal_tangential.py [frequency]
"""
import sys

import numpy as np
import torch

import fishsim.rollout as R
from fishsim.config import load_config
from fishsim.coupling.layer import surface_index
from fishsim.episode import build_episode
from fishsim.rollout import head_node, rollout

torch.set_num_threads(1)
f = float(sys.argv[1]) if len(sys.argv) > 1 else 5.0
sim = load_config("simulate", ["frames=120", f"batch.frequency=[{f}]"])
ep = build_episode(sim)
sw, fl = ep.swimmer, ep.swimmer.fluid
rho, g, WALL = float(sim.fluid.rho), ep.swimmer.fluid.grid, 8
head, idx = head_node(sw.solid.mesh), surface_index(sw.surface, "cpu")
centres = g.cell_centres(dtype=torch.float64)[WALL:-WALL, WALL:-WALL].reshape(-1, 2)
now: dict = {}
fluid_step, fluid_to_solid, frame = fl.step, R.fluid_to_solid, sw.frame


def step(state, boundary, params, start=None):
    out, d = fl.step_with_diagnostics(state, boundary, params, start=start)
    now["cells"] = d.cell_forces(rho)[0, :, WALL:-WALL, WALL:-WALL].reshape(2, -1).T.double()   # [C, 2]
    return out


def sampled(q, *args, **kwargs):
    now["q"] = q[0].double().clone()
    now["f"] = fluid_to_solid(q, *args, **kwargs)
    return now["f"]


rows = []


def recorded_frame(state, params, t, *args, **kwargs):
    out = frame(state, params, t, *args, **kwargs)
    if t >= 60:
        qs = now["q"][idx]                                            # ccw surface [S, 2]
        tangent = torch.roll(qs, -1, 0) - torch.roll(qs, 1, 0)
        tangent = tangent / tangent.norm(dim=1, keepdim=True)
        normal = torch.stack([tangent[:, 1], -tangent[:, 0]], 1)     # outward for ccw
        F, keep = now["cells"], now["cells"].norm(dim=1) > 0
        near = torch.cdist(centres[keep], qs).argmin(1)
        Fk, n, tt = F[keep], normal[near], tangent[near]
        Fn, Ft = (Fk * n).sum(1, keepdim=True) * n, (Fk * tt).sum(1, keepdim=True) * tt
        behind = float(now["q"][head, 0]) - qs[near, 0]
        tail = (behind > 0.150).double()
        fp, tail_nodes = now["f"][0].double(), (float(now["q"][head, 0]) - now["q"][:, 0] > 0.150).double()
        rows.append([Fk[:, 0].sum(), Fn[:, 0].sum(), Ft[:, 0].sum(), fp[:, 0].sum(),
                     (Fk[:, 0] * tail).sum(), (Fn[:, 0] * tail).sum(), (Ft[:, 0] * tail).sum(), (fp[:, 0] * tail_nodes).sum(),
                     Fk[:, 1].sum(), Fn[:, 1].sum(), Ft[:, 1].sum(), fp[:, 1].sum()])
    return out


fl.step, R.fluid_to_solid, sw.frame = step, sampled, recorded_frame
with torch.no_grad():
    rollout(sw, sw.initial_state(ep.params, ep.origin), ep.params, sim.frames)
a = 1e3 * np.array([[float(x) for x in r] for r in rows])
m, rms = a.mean(0), np.sqrt((a ** 2).mean(0))
print(f"{f:g} Hz, frames 61-{sim.frames}, mN/m: exchange = normal part + tangential part; sampled pressure (normal)")
print(f"mean F_x, whole fish:   exchange {m[0]:+.1f} = normal {m[1]:+.1f} + tangential {m[2]:+.1f}; sampled pressure {m[3]:+.1f}")
print(f"mean F_x, last 50 mm:   exchange {m[4]:+.1f} = normal {m[5]:+.1f} + tangential {m[6]:+.1f}; sampled pressure {m[7]:+.1f}")
print(f"RMS F_y, whole fish:    exchange {rms[8]:.1f} (normal {rms[9]:.1f}, tangential {rms[10]:.1f}); sampled pressure {rms[11]:.1f}")
