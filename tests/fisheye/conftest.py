import pytest
import torch


@pytest.fixture(autouse=True)
def single_thread():
    """Small tensors: one thread is faster (and much faster on a busy shared CPU)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
