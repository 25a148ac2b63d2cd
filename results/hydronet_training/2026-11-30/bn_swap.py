"""Swim the 120-frame frequency study (3-7 Hz, own pressure) with the weights of model file A and
the BatchNorm running statistics of model file B:

    python results/hydronet_training/2026-11-30/bn_swap.py A.pt B.pt mixed.pt

Prints the displacements [mm] and their errors against the numerical fluid at r = 2
(results/paper_fig4/frames120-b0-ratio6.75/)."""
import sys

import torch

from fishsim.swim_study import episode

R2 = [46.925407408503375, 84.25415217286897, 132.752173026506, 189.55091977758292, 266.1414666301343]

if __name__ == "__main__":
    torch.set_num_threads(1)
    a_file, b_file, out = sys.argv[1:4]
    a = torch.load(a_file, map_location="cpu", weights_only=False)
    b = torch.load(b_file, map_location="cpu", weights_only=False)
    torch.save({**a, "model": {k: b["model"][k] if "running" in k else v for k, v in a["model"].items()}}, out)
    d = episode(["fluid=hydronet", f"fluid.model_file={out}"], [3.0, 4.0, 5.0, 6.0, 7.0], 120)["displacement_mm"]
    print(" / ".join(f"{x:.1f}" for x in d), "|", " / ".join(f"{100 * (x / r - 1):+.1f} %" for x, r in zip(d, R2)))
