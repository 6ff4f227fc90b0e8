import pytest
import torch


@pytest.fixture
def gen():
    """A seeded torch generator (each test gets a fresh one)."""
    return torch.Generator().manual_seed(0)
