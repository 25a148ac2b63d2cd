"""Tests run small problems where torch's and numba's threads only add synchronisation (and
oversubscribe the 2 shared CI cores when pytest-xdist runs two workers): one thread per test."""

import numba
import pytest
import torch


@pytest.fixture(autouse=True)
def _one_thread():
    before = torch.get_num_threads(), numba.get_num_threads()
    torch.set_num_threads(1)
    numba.set_num_threads(1)
    yield
    torch.set_num_threads(before[0])
    numba.set_num_threads(before[1])
