"""Corrupt-input handling shared by the dataset loaders."""
from __future__ import annotations

import logging

from torch.utils.data import Dataset

log = logging.getLogger("omnidl.data")


class CorruptSampleError(RuntimeError):
    """A sample's files exist but cannot be used (truncated PNG, wrong size, missing label file ...).

    The message names the file and what was expected.
    """


class SkipCorrupt(Dataset):
    """Wrap a dataset so that :class:`CorruptSampleError` items become ``None`` (with a warning naming the
    file) instead of stopping training; :func:`omnidl.data.collate.collate_samples` drops them.

    ``max_skips`` caps how many different samples may be skipped before the error is raised after all.
    """

    def __init__(self, dataset, max_skips: int = 1000):
        self.dataset = dataset
        self.max_skips = max_skips
        self.skipped: set[int] = set()

    def __len__(self) -> int:
        return len(self.dataset)

    def __getattr__(self, name):
        if name == "dataset":
            raise AttributeError(name)
        return getattr(self.dataset, name)

    def __getitem__(self, index: int):
        try:
            return self.dataset[index]
        except CorruptSampleError as e:
            self.skipped.add(index)
            if len(self.skipped) > self.max_skips:
                raise
            log.warning("skipping sample %d: %s", index, e)
            return None
