import logging

import pytest
import torch

from omnidl.data.collate import batch_files, collate_samples, nonfinite_keys


def _s(i, h=4, w=8):
    return {"image": torch.full((3, h, w), float(i)), "semantic": torch.zeros(h, w, dtype=torch.long),
            "num": 3, "meta": {"name": f"s{i}"}}


def test_stacks_and_keeps_meta():
    b = collate_samples([_s(0), _s(1)])
    assert b["image"].shape == (2, 3, 4, 8) and b["semantic"].dtype == torch.long
    assert b["meta"] == [{"name": "s0"}, {"name": "s1"}] and b["num"].tolist() == [3, 3]
    assert batch_files(b) == ["s0", "s1"]


def test_drops_none_and_all_none(caplog):
    with caplog.at_level(logging.WARNING, logger="omnidl.data"):
        b = collate_samples([None, _s(1)])
    assert b["image"].shape[0] == 1 and "dropped 1" in caplog.text
    assert collate_samples([None, None]) is None


def test_shape_mismatch_names_key_and_files():
    with pytest.raises(ValueError, match=r"'image'.*s0, s1"):
        collate_samples([_s(0), _s(1, h=6)])


def test_nonfinite_keys():
    b = collate_samples([_s(0), _s(1)])
    assert nonfinite_keys(b) == []
    b["image"][1, 0, 0, 0] = float("inf")
    assert nonfinite_keys(b) == ["image"]


def test_memory_cache_keeps_samples_and_selected_keys():
    from omnidl.data.cache import MemoryCache

    class Counting(torch.utils.data.Dataset):
        calls = 0

        def __len__(self):
            return 3

        def __getitem__(self, i):
            Counting.calls += 1
            return _s(i)

    ds = MemoryCache(Counting(), keys=["image"])
    a = ds[1]
    assert ds[1] is a and Counting.calls == 1 and set(a) == {"image", "meta"} and len(ds) == 3
