"""Forward time of a 100-frame full-scale episode (default fish and tank, numerical fluid, float32)
at several solid tolerances: the phase times, the solves that stalled, the mean x of the fish."""
import sys
import time
import warnings

import torch

from fishsim.config import load_config
from fishsim.episode import build_episode
from fishsim.rollout import PhaseTimer, rollout

torch.set_num_threads(1)
for atol in sys.argv[2:]:
    cfg = load_config("simulate", [f"solid.pd.atol={atol}", f"fluid={sys.argv[1]}"])
    ep = build_episode(cfg)
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        t = time.time()
        with torch.no_grad():
            timer = PhaseTimer()
            st, out = rollout(ep.swimmer, ep.swimmer.initial_state(ep.params, ep.origin), ep.params, 100, timer=timer)
        wall = time.time() - t
        stalls = [x for x in w if "did not converge" in str(x.message)]
    print(sys.argv[1], atol, f"wall {wall:.1f}s", {k: round(v, 2) for k, v in timer.seconds.items()}, "stalls", len(stalls), repr(float(st.q[..., 0].mean())), flush=True)
