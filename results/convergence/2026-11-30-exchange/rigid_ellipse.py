"""The momentum exchange on a rigid, fish-sized body: a 10 x 1 cm ellipse (soft mask, one-cell
ramp) in the paper's fluid on the fish's grid and stepping (2.5 mm cells, h = 0.01 s, the
defaults of `fishsim simulate`), either held in a stream U (`fixed`: inflow and outflow bands,
free-slip walls, 0.6 x 0.25 m) or moved at U through still fluid (`moving`: a closed
0.8 x 0.25 m tank). Drag over the second half of T seconds: the exchange (``cell_forces``:
-penalty + the inside fluid's inertia, within 1.5 cm of the body), the membership term the
exchange leaves out (rho dx^2 sum_f v_f (b_f^k - b_f^k-1) / h: the momentum of the fluid the
moving mask takes in or lets go between steps) and laminar flat-plate friction on both sides
(Blasius, 2 x 1.328 / sqrt(Re_L) rho U^2 L / 2), in mN/m.

    python results/convergence/2026-11-30-exchange/rigid_ellipse.py U fixed|moving [mu] [T]
"""
import math
import sys

import numpy as np
import torch
import torch.nn.functional as F

from fishsim.config import load_config
from fishsim.fields import Boundary, FluidParams, FluidState, Grid
from fishsim.fluid import grid as G
from fishsim.fluid.factory import numerical_stepping
from fishsim.fluid.numerical import NumericalFluid
from fishsim.learn.pool import Motion, Rigid, rigid_distance

torch.set_num_threads(1)
U, mode = float(sys.argv[1]), sys.argv[2]
mu = float(sys.argv[3]) if len(sys.argv) > 3 else 1.25e-4
T = float(sys.argv[4]) if len(sys.argv) > 4 else 2.0
rho, a, c, h, dx = 50.0, 0.05, 0.005, 0.01, 2.5e-3
g = Grid(100, 320 if mode == "moving" else 240, dx)
m = NumericalFluid(g, walls=G.FREE_SLIP, **numerical_stepping(load_config("simulate", []).fluid))
cc = g.cell_centres(dtype=torch.float64)


def ellipse(x0):
    """Soft mask (b = 1/2 + s / dx, s the training pool's first-order signed distance, > 0 inside)
    and a region 1.5 cm around it."""
    at = Motion((x0, 0.125), (0.0, 0.0), (0.0, 0.0), (0.0, 0.0), (0.0, 0.0), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, (a, c))
    s = rigid_distance(Rigid("ellipse", (a, c), at), cc)
    x, y = cc[..., 0] - x0, cc[..., 1] - 0.125
    region = ((x / (a + 0.015)) ** 2 + (y / (c + 0.015)) ** 2 < 1).float()[None, None]
    return (0.5 + s / dx).clamp(0, 1)[None, None].float(), region


params = FluidParams(torch.tensor([rho]), torch.tensor([mu]), h)
if mode == "fixed":
    outer = G.channel(g, U, thickness_y=0, thickness_x=4)
    y = (torch.arange(g.H + 1, dtype=torch.float32) * dx)[None, None, :, None]
    a0 = (U * y).expand(1, 1, g.H + 1, g.W + 1)
    state = FluidState(a0 - a0.mean(), torch.zeros(1, 1, g.H, g.W))
else:
    outer, state = G.closed_tank(g, 2, 2, dtype=torch.float32), m.initial_state(1)
rows, before = [], None
for k in range(round(T / h)):
    body, region = ellipse(0.2 if mode == "fixed" else 0.1 + U * (k + 1) * h)
    speed = 0.0 if mode == "fixed" else U
    state, d = m.step_with_diagnostics(state, G.union(outer, Boundary(body, torch.cat([body * 0 + speed, body * 0], 1))), params)
    exchange = float((d.cell_forces(rho)[0, 0] * region[0, 0]).sum())
    faces = torch.maximum(F.pad(region, (1, 0)), F.pad(region, (0, 1)))
    membership = 0.0 if before is None else float((rho * dx**2 * (d.mask[0] - before) * d.start[0] * faces).sum() / h)
    rows.append((exchange, membership))
    before = d.mask[0]
r = -1e3 * np.array(rows)[len(rows) // 2:].mean(0) * (1 if mode == "fixed" else -1)   # drag > 0
Re = U * 2 * a * rho / mu
blasius = 2 * 1.328 / math.sqrt(Re) * 0.5 * rho * U**2 * 2 * a
print(f"{mode} U = {U} m/s, mu = {mu:g} Pa s (Re_L {Re:.0f}): drag by exchange {abs(r[0]):.2f}, membership term "
      f"{r[1]:+.2f}, Blasius friction {1e3 * blasius:.2f} mN/m")
