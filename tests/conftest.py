"""Shared test fixtures."""

import pytest
import torch


@pytest.fixture
def one_torch_thread():
    """Run a test with one torch intra-op thread and restore the setting afterwards.

    The simulators' tensors are tiny: on a shared 2-core machine a second thread only adds contention
    (a 6×6 matmul took 25 ms with two contended threads, 20 µs with one).
    """
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)
