"""One torch thread for the short training runs: their tensors are small, and on a shared CPU
more threads only contend (a run took 20x longer)."""

from __future__ import annotations

import pytest
import torch


@pytest.fixture
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
