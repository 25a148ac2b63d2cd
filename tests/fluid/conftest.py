"""The fluid tests run small grids where torch's intra-op threading only adds synchronisation
(and oversubscribes the 2 shared CI cores): run them on one thread, restoring it afterwards."""

import pytest
import torch


@pytest.fixture(autouse=True)
def _one_torch_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
