"""How far does the fish swim, and how does that change with its stroke frequency?

Builds the episode of ``fishsim simulate`` from the same config (any ``key=value`` override on the
command line), rolls it out with gradient checkpointing and back-propagates the head's distance
to the controller frequency, the amplitude C and Young's modulus E.

    python examples/gradient_of_distance.py frames=60 fluid=numerical
"""

import math
import sys

import torch

from fishsim.config import load_config
from fishsim.episode import build_episode
from fishsim.rollout import SwimParams, rollout


def main(overrides: list[str]) -> dict:
    cfg = load_config("simulate", overrides)
    ep = build_episode(cfg)
    ctrl = ep.params.controller
    omega, C, E = (x.clone().requires_grad_() for x in (ctrl.omega, ctrl.C, ep.params.E))
    params = SwimParams(type(ctrl)(C, omega, ctrl.gamma, ctrl.t_a), E, ep.params.fluid)
    state = ep.swimmer.initial_state(params, ep.origin)
    head0 = state.q[:, ep.swimmer.solid.mesh.points[:, 0].argmax(), 0]
    _, metrics = rollout(ep.swimmer, state, params, cfg.frames, segment=10)
    distance = metrics["head_x"][-1] - head0
    d_omega, d_C, d_E = torch.autograd.grad(distance.sum(), [omega, C, E])
    out = {"distance_m": distance.tolist(), "d_distance_d_frequency_m_per_Hz": (2 * math.pi * d_omega).tolist(),
           "d_distance_d_C_m2": d_C.tolist(), "d_distance_d_E_m_per_Pa": d_E.tolist()}
    for k, v in out.items():
        print(f"{k:34s} {v}")
    return out


if __name__ == "__main__":
    main(sys.argv[1:])
