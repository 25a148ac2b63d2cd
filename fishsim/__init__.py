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


def _keep_freed_memory() -> None:
    """Keep the memory a step frees in the process's heap for the next step (glibc only).

    glibc's malloc serves a block of >= 128 kB (a field of the paper's grid is 120 kB; a U-Net
    activation 2-16 MB) from a fresh mmap and returns it to the kernel when freed, and trims the
    heap's free top likewise, so every step's arrays page-fault on each 4 kB page they first touch.
    With the mmap threshold at its maximum (32 MiB) and the trim threshold at 1 GiB they are reused
    instead. Measured (2026-12-01, two threads, AMD EPYC): HydroNet's step at B = 1 14.6-15.7 ms
    against 17.7-22.7, the paper's Table 1 forward with HydroNet 6.0-6.1 s against 8.0-8.1, at B =
    16 15.6-16.7 ms a fish and frame against 21.8-22.8; peak RSS unchanged (1.08 / 3.26 GB).
    Either setting alone is slower than neither (setting one turns off glibc's adaptive
    threshold: the trim threshold alone 40 ms a HydroNet step). Backward passes and the numerical
    fluid's episodes change by little."""
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("c")
    libc = ctypes.CDLL(name) if name and _sys.platform.startswith("linux") else None
    if libc is not None and hasattr(libc, "gnu_get_libc_version") and hasattr(libc, "mallopt"):
        m_trim_threshold, m_mmap_threshold = -1, -3
        libc.mallopt(m_mmap_threshold, 32 << 20)
        libc.mallopt(m_trim_threshold, 1 << 30)


_keep_freed_memory()
