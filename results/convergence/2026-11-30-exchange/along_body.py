"""Where along the swimming fish the momentum exchange and the sampled pressure differ.

The default fish (5 Hz, 120 frames, the numerical fluid, coupled by the sampled pressure) is run
once; each frame from 61 on, the fluid step's momentum exchange (``StepDiagnostics``: the
reaction to the penalisation, -rho dx^2 penalty, and the inside fluid's inertia, rho dx^2 b_f
(v' - v) / h, on the faces away from the tank's walls) and the coupling's sampled-pressure force
on the nodes are binned by distance behind the head (5 mm bins). Prints, per bin, the mean x force
and the RMS y force of each (mN/m).

    python results/convergence/2026-11-30-exchange/along_body.py [frequency]
"""
import sys

import numpy as np
import torch

import fishsim.rollout as R
from fishsim.config import load_config
from fishsim.episode import build_episode
from fishsim.rollout import head_node, rollout

torch.set_num_threads(1)
f = float(sys.argv[1]) if len(sys.argv) > 1 else 5.0
sim = load_config("simulate", ["frames=120", f"batch.frequency=[{f}]"])
ep = build_episode(sim)
sw, fl = ep.swimmer, ep.swimmer.fluid
rho, dx, BINS, WALL = float(sim.fluid.rho), fl.grid.dx, 46, 8
head = head_node(sw.solid.mesh)
now: dict = {}
fluid_step, fluid_to_solid, frame = fl.step, R.fluid_to_solid, sw.frame


def step(state, boundary, params, start=None):
    out, d = fl.step_with_diagnostics(state, boundary, params, start=start)
    for axis in (0, 1):            # per face column, the wall bands' rows and columns left out
        pen = -rho * dx**2 * d.penalty[axis][0, 0, WALL:-WALL, WALL:-WALL].sum(0)
        ine = rho * dx**2 * d.inertia[axis][0, 0, WALL:-WALL, WALL:-WALL].sum(0)
        now[axis] = (pen, ine, (torch.arange(pen.shape[0]) + WALL + 0.5 * axis) * dx)
    return out


def sampled(q, *args, **kwargs):
    now["q"] = q[0].clone()
    now["f"] = fluid_to_solid(q, *args, **kwargs)
    return now["f"]


def binned(distance, weights):
    k = np.floor(distance / 0.005).astype(int).clip(-5, BINS - 6) + 5
    return np.bincount(k, weights=weights, minlength=BINS)


rows = []


def recorded_frame(state, params, t, *args, **kwargs):
    out = frame(state, params, t, *args, **kwargs)
    if t >= 60:
        xh = float(now["q"][head, 0])
        row = []
        for axis in (0, 1):
            pen, ine, x = now[axis]
            row += [binned(xh - x.numpy(), pen.numpy()), binned(xh - x.numpy(), ine.numpy())]
            row.append(binned(xh - now["q"][:, 0].numpy(), now["f"][0, :, axis].numpy()))
        rows.append(row)
    return out


fl.step, R.fluid_to_solid, sw.frame = step, sampled, recorded_frame
with torch.no_grad():
    rollout(sw, sw.initial_state(ep.params, ep.origin), ep.params, sim.frames)
a = np.array(rows) * 1e3                       # [frames, 6, BINS] mN/m
mean_x, rms_y = a[:, :3].mean(0), np.sqrt((a[:, 3:] ** 2).mean(0))
ex_x = mean_x[0] + mean_x[1]
ex_y = np.sqrt(((a[:, 3] + a[:, 4]) ** 2).mean(0))
print(f"{f:g} Hz, frames 61-{sim.frames}, mN/m; distance behind the head [mm]")
print("  bin      | mean F_x: -penalty  inertia  exchange  sampled p | RMS F_y: exchange  sampled p")
for i in range(BINS):
    if max(abs(mean_x[:, i]).max(), rms_y[2, i], ex_y[i]) > 0.5:
        print(f"{(i - 5) * 5:4d}-{(i - 4) * 5:4d} | {mean_x[0, i]:+17.1f} {mean_x[1, i]:+8.1f} {ex_x[i]:+9.1f} {mean_x[2, i]:+10.1f}"
              f" | {ex_y[i]:17.1f} {rms_y[2, i]:10.1f}")
tail = slice(5 + 30, BINS)                     # 150 mm behind the head and beyond
print(f"total F_x: exchange {ex_x.sum():+.1f} (-penalty {mean_x[0].sum():+.1f}, inertia {mean_x[1].sum():+.1f}), "
      f"sampled pressure {mean_x[2].sum():+.1f}; of which the last 50 mm: exchange {ex_x[tail].sum():+.1f}, "
      f"sampled pressure {mean_x[2][tail].sum():+.1f}")
