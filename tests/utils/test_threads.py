import pytest
import torch

from omnidl.utils import threads as T


def test_limit_threads_caps_and_restores():
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        with T.limit_threads(1):
            assert torch.get_num_threads() == 1
        assert torch.get_num_threads() == 2
        with T.limit_threads(None), T.limit_threads(8):  # None / more than now: unchanged
            assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_auto_threads_follows_the_runnable_tasks(monkeypatch):
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        monkeypatch.setattr(T, "usable_cpus", lambda: 2)
        monkeypatch.setattr(T, "runnable_tasks", lambda: 2.0)
        assert T.auto_threads() == 2
        monkeypatch.setattr(T, "runnable_tasks", lambda: 5.0)
        assert T.auto_threads() == 1
        with T.limit_threads("auto"):
            assert torch.get_num_threads() == 1
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
    assert T.runnable_tasks() >= 0 and T.usable_cpus() >= 1


def test_limit_threads_rejects_unknown_words():
    with pytest.raises(ValueError, match="n must be an int, None or 'auto', got 'many'"):
        with T.limit_threads("many"):
            pass
