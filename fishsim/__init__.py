"""fishsim: a fast, fully differentiable simulator for soft swimming robots in water.

A 2D soft fish (FEM, differentiable projective dynamics) swims in a fluid computed either by a
physics-trained U-Net (HydroNet) or by a numerical Navier-Stokes solver on the same MAC grid,
linked by a differentiable immersed-boundary coupling layer (Nava et al., ICML 2022).
"""

import os as _os
import sys as _sys

__version__ = "0.1.0"

# numba's OpenMP threading layer sets the process-wide OpenMP thread count to NUMBA_NUM_THREADS
# (default: every core) when the solid's first parallel kernel runs, and torch shares that count:
# a user's OMP_NUM_THREADS=1 was silently raised to the core count for torch too (on a machine
# shared with another job, a 48 x 144 frame of 6 fish took 1040 ms instead of 114 ms).
# Once numba's threads run (numba code that ran before fishsim was imported), their count is fixed
# and a changed NUMBA_NUM_THREADS makes numba's next compilation raise, so it is left alone; a numba
# imported but idle re-reads it now, or it would launch its threads with the count read at import.
_numba_parallel = _sys.modules.get("numba.np.ufunc.parallel")
if ("OMP_NUM_THREADS" in _os.environ and "NUMBA_NUM_THREADS" not in _os.environ
        and not getattr(_numba_parallel, "_is_initialized", False)):
    _os.environ["NUMBA_NUM_THREADS"] = _os.environ["OMP_NUM_THREADS"]
    if _numba_parallel is not None:     # numba imported but idle: it read its count already
        _sys.modules["numba.core.config"].reload_config()
        _numba_parallel.NUM_THREADS = _numba_parallel.get_thread_count()
