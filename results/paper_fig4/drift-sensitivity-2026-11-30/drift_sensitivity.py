"""How sensitive the 300-frame lateral drift of the numerical reference is to the gait's frequency:
the study's 300-frame episode (2 x 0.5 m tank, r = 1, the defaults) for fish at f, f (1 + 1e-5) and
f (1 + 1e-4), f = 3, 5, 7 Hz, batched (each fish's sub-steps are its own, so batch mates do not
matter); prints each fish's head x displacement and centroid drift (mm).

    python results/paper_fig4/drift-sensitivity-2026-11-30/drift_sensitivity.py
"""
import torch

from fishsim.swim_study import episode

torch.set_num_threads(1)
freqs = [f * (1 + e) for f in (3.0, 5.0, 7.0) for e in (0.0, 1e-5, 1e-4)]
r = episode(["tank=long", "origin=[0.06,0.25]"], freqs, 300)
for f, x, y in zip(freqs, r["displacement_mm"], r["lateral_drift_mm"]):
    print(f"f = {f:.6f} Hz: head x {x:8.2f} mm, drift {y:+8.2f} mm")
print("failures:", r["failures"], " wall", round(r["wall_s"]), "s")
