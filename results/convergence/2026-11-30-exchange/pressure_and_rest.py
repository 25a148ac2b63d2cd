"""The swimming fish's momentum exchange split exactly into the solver's own pressure force and
the rest.

Per face the exchange is rho dx^2 (b_f (v' - v) / h - penalty) and the step's momentum balance is
(v' - v) / h = -grad p / rho + A + penalty (A: advection and viscous terms, p the pressure whose
gradient the step applied), so over any set of faces R

    exchange = -dx^2 sum_R grad p  +  rho dx^2 sum_R ((b_f - 1) (v' - v) / h + A)

The first sum telescopes to the pressure on R's edge (a pressure force on a contour around the
body, like the sampled pressure the coupling reads); the second is the rest: the viscous stress
and the momentum advected through the band. R: the faces away from the tank's walls where b_f
exceeds 0 / 1e-3 / 1e-2 / 0.1 / 0.5. The default fish at 5 Hz, 120 frames, coupled by the
sampled pressure, with the overrides given; means of F_x over frames 61-120 in mN/m.

    python results/convergence/2026-11-30-exchange/pressure_and_rest.py [override ...]
"""
import sys

import numpy as np
import torch
import torch.nn.functional as F

import fishsim.rollout as R
from fishsim.config import load_config
from fishsim.episode import build_episode
from fishsim.rollout import rollout

torch.set_num_threads(1)
overrides = sys.argv[1:]
sim = load_config("simulate", ["frames=120", "batch.frequency=[5.0]", *overrides])
ep = build_episode(sim)
sw, fl = ep.swimmer, ep.swimmer.fluid
rho, r, WALL, EDGES = float(sim.fluid.rho), fl.refinement, 8, (0.0, 1e-3, 1e-2, 0.1, 0.5)
now: dict = {}
fluid_to_solid, frame = R.fluid_to_solid, sw.frame


def step(state, boundary, params, start=None):
    out, d = fl.step_with_diagnostics(state, boundary, params, start=start)
    p = F.interpolate(out.p.double(), scale_factor=r, mode="nearest")[0, 0] if r > 1 else out.p[0, 0].double()
    bx = d.mask[0][0, 0].double()                                    # x faces [H, W + 1] (fine grid)
    gx = torch.zeros_like(bx)
    gx[:, 1:-1] = (p[:, 1:] - p[:, :-1]) / d.dx
    inner = torch.zeros_like(bx)
    inner[WALL * r:-WALL * r, WALL * r:-WALL * r] = 1
    cells = d.cell_forces(rho)[0, 0, WALL:-WALL, WALL:-WALL].double().sum()
    now["row"] = [float(cells)] + [float(-(d.dx**2 * gx * (bx > e) * inner).sum()) for e in EDGES]
    return out


def sampled(q, *args, **kwargs):
    now["f"] = fluid_to_solid(q, *args, **kwargs)
    return now["f"]


rows = []


def recorded_frame(state, params, t, *args, **kwargs):
    out = frame(state, params, t, *args, **kwargs)
    if t >= 60:
        rows.append(now["row"] + [float(now["f"][0, :, 0].sum())])
    return out


fl.step, R.fluid_to_solid, sw.frame = step, sampled, recorded_frame
with torch.no_grad():
    rollout(sw, sw.initial_state(ep.params, ep.origin), ep.params, sim.frames)
m = 1e3 * np.array(rows).mean(0)
pressure = " / ".join(f"{x:+.1f}" for x in m[1:-1])
rest = " / ".join(f"{m[0] - x:+.1f}" for x in m[1:-1])
print(f"{' '.join(overrides) or 'defaults'}: exchange {m[0]:+.1f}; pressure on R's edge {pressure}; "
      f"rest {rest} (b_f > {' / '.join(f'{e:g}' for e in EDGES)}); sampled pressure {m[-1]:+.1f} mN/m")
