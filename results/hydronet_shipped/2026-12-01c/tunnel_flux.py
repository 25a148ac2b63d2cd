"""The flux across columns of the tank over the fluid rows, in U x the fluid's height, a 5 Hz fish
in the swim tunnel after FRAMES frames.

    PYTHONPATH=. python tunnel_flux.py FRAMES FLUID [OVERRIDES...]
"""
import sys, torch
from fishsim.config import load_config
from fishsim.episode import build_episode
from fishsim.rollout import rollout
from fishsim.fluid.grid import curl
torch.set_num_threads(2)
frames = int(sys.argv[1]); fluid = sys.argv[2]; extra = sys.argv[3:]
sim = load_config("simulate", [f"fluid={fluid}", f"frames={frames}", "tunnel=true", "batch.frequency=[5]", *extra])
ep = build_episode(sim)
sw = ep.swimmer
s0 = sw.initial_state(ep.params, ep.origin)
with torch.no_grad():
    s, m = rollout(sw, s0, ep.params, frames)
U = float(m["tunnel_u"][-1, 0])
a = s.fluid.a
vx = curl(a, sw.fluid.grid.dx)[0][0, 0]          # [H, W+1]
walls = sw.walls.mask[0, 0]
H, W = walls.shape
print(fluid, "U", round(U, 4), "grid", H, W, "fish x at cols", [round(float(v), 3) for v in s.q[0, :, 0].aminmax()], "dx", sw.fluid.grid.dx)
for j in (10, 50, 100, 150, 200, 250, 290):
    col = vx[:, j]
    fluid_rows = walls[:, min(j, W - 1)] < 0.5
    print(" col", j, "mean v_x over fluid rows", round(float(col[fluid_rows].mean()), 4), "flux/(U*h_fluid)", round(float(col[fluid_rows].sum() / (-U * fluid_rows.sum())), 3))
