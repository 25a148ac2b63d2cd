"""fishsim: a fast, fully differentiable simulator for soft swimming robots in water.

A 2D soft fish (FEM, differentiable projective dynamics) swims in a fluid computed either by a
physics-trained U-Net (HydroNet) or by a numerical Navier-Stokes solver on the same MAC grid,
linked by a differentiable immersed-boundary coupling layer (Nava et al., ICML 2022).
"""

import os as _os

__version__ = "0.1.0"

# numba's OpenMP threading layer sets the process-wide OpenMP thread count to NUMBA_NUM_THREADS
# (default: every core) when the solid's first parallel kernel runs, and torch shares that count:
# a user's OMP_NUM_THREADS=1 was silently raised to the core count for torch too (on a machine
# shared with another job, a 48 x 144 frame of 6 fish took 1040 ms instead of 114 ms).
if "OMP_NUM_THREADS" in _os.environ and "NUMBA_NUM_THREADS" not in _os.environ:
    _os.environ["NUMBA_NUM_THREADS"] = _os.environ["OMP_NUM_THREADS"]
