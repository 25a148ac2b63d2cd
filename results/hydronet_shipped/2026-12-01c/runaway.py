"""The swim tunnel's speed U [m/s] every 50 frames, fish at 3 / 4 / 5 / 5.5 / 6 / 7 Hz held in y.

    PYTHONPATH=. python runaway.py FRAMES FLUID [OVERRIDES...]
"""
import sys, torch
from fishsim.config import load_config
from fishsim.episode import build_episode
from fishsim.rollout import rollout
torch.set_num_threads(2)
frames = int(sys.argv[1]); fluid = sys.argv[2]; extra = sys.argv[3:]
sim = load_config("simulate", [f"fluid={fluid}", f"frames={frames}", "tunnel=true", "hold_y=true",
                               "batch.frequency=[3,4,5,5.5,6,7]", *extra])
ep = build_episode(sim)
s0 = ep.swimmer.initial_state(ep.params, ep.origin)
with torch.no_grad():
    _, m = rollout(ep.swimmer, s0, ep.params, frames)
u = m["tunnel_u"]
for t in range(49, frames, 50):
    print(t + 1, [round(float(x), 3) for x in u[t]])
