"""The frequency study (120 frames, 3 / 5 / 7 Hz) with the stroke mirrored (the controller's
amplitude C negated after the episode is built: the fish first beats the other way), for HydroNet
and the numerical fluid: a y-symmetric fluid mirrors the lateral drift, an asymmetric one keeps
its sign.

    python results/hydronet_shipped/2026-11-30/mirror_stroke.py plain|flip [more overrides for HydroNet, e.g.
    fluid.symmetric=false: the network alone, as measured on 2026-11-30]
"""
import dataclasses
import sys

import torch

import fishsim.swim_study as S
from fishsim import episode as E

if __name__ == "__main__":
    torch.set_num_threads(1)
    build = E.build_episode

    def flipped(sim):
        ep = build(sim)
        ctrl = dataclasses.replace(ep.params.controller, C=-ep.params.controller.C)
        return dataclasses.replace(ep, params=dataclasses.replace(ep.params, controller=ctrl))

    if sys.argv[1] == "flip":
        E.build_episode = flipped
    for overrides in (["fluid=hydronet", *sys.argv[2:]], ["fluid=numerical"]):
        r = S.episode(overrides, [3.0, 5.0, 7.0], 120)
        fluid = " ".join(overrides)
        print(sys.argv[1], fluid, "displacement", [round(x, 1) for x in r["displacement_mm"]],
              "drift", [round(x, 1) for x in r["lateral_drift_mm"]], flush=True)
