"""A user's thread limit holds for torch after the solid's numba kernels have run."""

import os
import subprocess
import sys

PROBE = """
import fishsim, numba, numpy as np, torch

@numba.njit(parallel=True)
def total(x):
    s = 0.0
    for i in numba.prange(x.size):
        s += x[i]
    return s

total(np.ones(100))
print(torch.get_num_threads())
"""


def test_omp_num_threads_also_limits_numba_and_so_torch():
    """numba's OpenMP layer sets the process-wide OpenMP count to NUMBA_NUM_THREADS (all cores by
    default) at its first parallel call, which torch then uses; fishsim passes OMP_NUM_THREADS on."""
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_NUM_THREADS"}
    env["OMP_NUM_THREADS"] = "1"
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip().splitlines()[-1] == "1"
