"""Tests run small problems where torch's intra-op threading only adds synchronisation (and
oversubscribes the 2 shared CI cores when pytest-xdist runs two workers): one thread per test."""

import pytest
import torch


@pytest.fixture(autouse=True)
def _one_torch_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
