"""Distance through the water (head x + h sum U) in the swim tunnel, and head x swimming free, [mm]
at 3 / 5 / 7 Hz.

    PYTHONPATH=. python tunnel_vs_free.py FRAMES FLUID [OVERRIDES...]
"""
import sys, torch, json
from fishsim.config import load_config
from fishsim.episode import build_episode
from fishsim.rollout import rollout, head_node
torch.set_num_threads(2)
frames = int(sys.argv[1]); fluid = sys.argv[2]; extra = sys.argv[3:]
out = {}
for mode in (["tunnel=true"], []):
    sim = load_config("simulate", [f"fluid={fluid}", f"frames={frames}", *mode, "batch.frequency=[3,5,7]", *extra])
    ep = build_episode(sim)
    s0 = ep.swimmer.initial_state(ep.params, ep.origin)
    h0 = s0.q[:, head_node(ep.swimmer.solid.mesh), 0]
    with torch.no_grad():
        _, m = rollout(ep.swimmer, s0, ep.params, frames)
    d = m["head_x"][-1] - h0 + (ep.swimmer.h * m["tunnel_u"].sum(0) if mode else 0)
    out["tunnel" if mode else "free"] = [round(1e3 * float(x), 1) for x in d]
print(fluid, extra, json.dumps(out))
