"""A user's thread limit holds for torch after the solid's numba kernels have run."""

import os
import subprocess
import sys

import pytest

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


LATE_IMPORT = """
import sys, numba
if sys.argv[1] == "launched":
    numba.get_num_threads()             # numba's threads launched before fishsim is imported
import fishsim

@numba.njit
def one(x):
    return x + 1

print(one(1), numba.get_num_threads())  # a compilation re-reads numba's environment
"""


@pytest.mark.parametrize("numba_state", ["idle", "launched"])
def test_importing_fishsim_after_numba_leaves_numba_working(numba_state, tmp_path):
    """numba imported first (a test's conftest, a user's own numba code) has read its thread count:
    idle, it must take OMP_NUM_THREADS; with its threads running, setting NUMBA_NUM_THREADS makes its
    next compilation raise, so fishsim must leave it be. A fresh cache makes the compilation happen."""
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_NUM_THREADS"}
    env.update(OMP_NUM_THREADS="1", NUMBA_CACHE_DIR=str(tmp_path))
    out = subprocess.run([sys.executable, "-c", LATE_IMPORT, numba_state], check=False, env=env,
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stderr.strip().splitlines()[-1]
    result, threads = out.stdout.split()
    assert result == "2"
    if numba_state == "idle":
        assert threads == "1"


SET_IN_PYTHON = """
import numba, numpy as np, torch
import fishsim.compiled
torch.set_num_threads(1)
torch.get_num_threads()                 # torch's pool in use, as after any op

@numba.njit(parallel=True)
def ids(n):
    out = np.zeros(n, np.int64)
    for i in numba.prange(n):
        out[i] = numba.get_thread_id()
    return out

ids(1000)
print(torch.get_num_threads(), numba.get_num_threads())
"""


def test_torch_set_num_threads_holds_after_numbas_threads_start():
    """numba's OpenMP layer sets the shared OpenMP count when its pool starts; fishsim starts the
    pool on import and gives torch its count back, so a torch.set_num_threads(1) made in Python
    (no environment variable) still holds after a parallel kernel, and numba keeps its 2 threads."""
    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
    env["NUMBA_NUM_THREADS"] = "2"
    out = subprocess.run([sys.executable, "-c", SET_IN_PYTHON], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["1", "2"]
