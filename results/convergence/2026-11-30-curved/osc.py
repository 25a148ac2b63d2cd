"""The oscillating cylinder of `benchmarks.bench_fluid._oscillating` (the fish's grid, stepping and
fluid; 60 cm box), its C_m read by the coupling's linear fit and by curved.py's fit:
`PYTHONPATH=. python results/convergence/2026-11-30-curved/osc.py 4 8` (radii in cells). Output osc.txt."""
import math
import sys
from functools import partial
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
from curved import curved_force

from benchmarks.bench_fluid import FISH_STEPPING, OSCILLATING_FISH_GRID
from fishsim.coupling.ibm import ibm_force
from fishsim.fluid import cases

torch.set_num_threads(1)
def probe(g, s, bd, centre, velocity, acceleration, radius):
    qs = cases.disc_polyline(*centre, radius, max(31, round(2 * math.pi * radius / (0.8 * g.dx))))
    lin = ibm_force(qs, s.p, bd.mask, g, sigma_prime=g.dx**2).sum(1)[0, 1]
    cur = curved_force(qs, s.p, bd.mask, g, g.dx**2).sum(1)[0, 1]
    return torch.stack([lin, cur])
kw = OSCILLATING_FISH_GRID
for rc in [int(a) for a in sys.argv[1:]]:
    res = cases.oscillating_cylinder(rc, **kw, probe=partial(probe, radius=rc * kw["dx"]), stepping=FISH_STEPPING)
    ref = res.stokes_wang * res.confinement
    print(f"{2*rc} cells/D: ref {ref:.4f} exchange {res.exchange:.4f} linear {res.probe[0]:.4f} ({res.probe[0]/ref-1:+.1%}, {res.probe[0]/res.exchange-1:+.1%}) "
          f"curved {res.probe[1]:.4f} ({res.probe[1]/ref-1:+.1%} ref, {res.probe[1]/res.exchange-1:+.1%} exch)", flush=True)
