"""Shared test fixtures."""
import pytest
import torch


@pytest.fixture
def single_thread():
    """Run a test on one intra-op thread: the tests use small tensors, for which thread-pool overhead dominates
    (and a busy shared CPU makes 2 threads many times slower than 1)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
