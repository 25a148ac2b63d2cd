"""The swim tunnel against the free fish (speed through the water over the last two beats, and
distance), on a 15 cm channel (80 frames) and the paper's tank (120 frames), 5 Hz, numerical fluid:
`PYTHONPATH=. python results/tunnel/tunfree.py` (output tunfree.txt: the code before and after the
tunnel's added-mass stabilisation, 2026-11-30)."""
import torch

from fishsim.config import load_config
from fishsim.episode import build_episode
from fishsim.optimize.problem import mean_speed, travel
from fishsim.rollout import rollout

torch.set_num_threads(1)
for tank, frames in ((["tank.H=60", "tank.W=180", "origin=[0.06,0.075]"], 80), ([], 120)):
    speed = {}
    for tunnel in (True, False):
        cfg = load_config("simulate", [*tank, f"frames={frames}", "controller.frequency=5", f"tunnel={tunnel}"])
        ep = build_episode(cfg)
        state = ep.swimmer.initial_state(ep.params, ep.origin)
        with torch.no_grad():
            _, m = rollout(ep.swimmer, state, ep.params, frames)
        cx = m["centroid_x"][:, 0]
        speed[tunnel] = float(mean_speed(travel(m, cfg.h), cx[:1], cfg.h, torch.tensor([2 / 5.0])))
        if tunnel:
            dist_t = float(travel(m, cfg.h)[-1, 0] - cx[0])
        else:
            dist_f = float(cx[-1] - cx[0])
    print(tank or "paper tank", frames, "speed tunnel / free", speed[True], speed[False], f"{speed[True]/speed[False]-1:+.1%}",
          "distance tunnel / free", dist_t, dist_f, f"{dist_t/dist_f-1:+.1%}", flush=True)
