"""tests/ibr: tiny tensors, so one intra-op thread (two threads on a loaded 2-core machine spend
more time waiting on each other than computing)."""

from __future__ import annotations

import pytest
import torch


@pytest.fixture(autouse=True)
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
