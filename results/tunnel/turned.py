"""A fish turned by DEG degrees about its centroid in the swim tunnel (held in y or not), 40 frames:
`PYTHONPATH=. python results/tunnel/turned.py DEG true|false`; prints the largest tunnel speed or
where the run blew up (output turned.txt)."""
import dataclasses
import math
import sys

import torch

from fishsim.config import load_config
from fishsim.episode import build_episode
from fishsim.errors import SimulationBlowUp
from fishsim.rollout import rollout

deg = float(sys.argv[1])
cfg = load_config("simulate", ["tank.H=120", "tank.W=160", "origin=[0.12,0.15]", "frames=40", "tunnel=true", f"hold_y={sys.argv[2]}",
                               "controller.frequency=5"])
ep = build_episode(cfg)
state = ep.swimmer.initial_state(ep.params, ep.origin)
c = state.q.mean(1, keepdim=True)
a = math.radians(deg)
R = torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]], dtype=state.q.dtype)
state = dataclasses.replace(state, q=(state.q - c) @ R.T + c)
try:
    with torch.no_grad():
        _, m = rollout(ep.swimmer, state, ep.params, 40)
    print(deg, "U max", float(m["tunnel_u"].abs().max()), "last", float(m["tunnel_u"][-1, 0]))
except SimulationBlowUp as e:
    print(deg, "blew up:", str(e)[:120])
