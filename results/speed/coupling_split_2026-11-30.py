"""One fish's coupling kernels on one core (serial) and cut over the torch threads (split),
alternating in one process: the coupling / fluid / solid phases of a 60-frame episode in the
swim tunnel, ms a frame. `PYTHONPATH=. python results/speed/coupling_split_2026-11-30.py`."""

import torch

import fishsim.coupling.kernels as K
from benchmarks.bench_rollout import _episode
from fishsim.rollout import PhaseTimer, rollout

ep = _episode("numerical", 1, tunnel=True)
sw = ep.swimmer
state = sw.initial_state(ep.params, ep.origin)
with torch.no_grad():
    state, _ = rollout(sw, state, ep.params, 20)
cut = K.serial_here
for _ in range(6):
    for mode in ("serial", "split"):
        K.serial_here = (lambda: True) if mode == "serial" else cut
        timer = PhaseTimer()
        with torch.no_grad():
            rollout(sw, state, ep.params, 60, timer=timer)
        print(mode, {k: round(1e3 * v / 60, 3) for k, v in timer.seconds.items()})
