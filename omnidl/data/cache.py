"""In-memory sample cache for datasets that are expensive to produce (on-the-fly rendering)."""
from __future__ import annotations

from torch.utils.data import Dataset


class MemoryCache(Dataset):
    """Keep every sample of ``dataset`` after its first access (per process: with ``num_workers > 0``
    each worker holds its own copy, so use it with ``num_workers=0``).

    ``keys`` (optional) keeps only those entries of each sample dict (plus ``meta``), to save memory.
    Samples must be deterministic in their index (the synthetic datasets are).
    """

    def __init__(self, dataset, keys: list[str] | None = None):
        self.dataset = dataset
        self.keys = set(keys) | {"meta"} if keys else None
        self._store: dict[int, object] = {}

    def __len__(self) -> int:
        return len(self.dataset)

    def __getattr__(self, name):
        if name in ("dataset", "_store", "keys"):
            raise AttributeError(name)
        return getattr(self.dataset, name)

    def __getitem__(self, index: int):
        index = int(index)
        if index not in self._store:
            sample = self.dataset[index]
            if self.keys is not None and isinstance(sample, dict):
                sample = {k: v for k, v in sample.items() if k in self.keys}
            self._store[index] = sample
        return self._store[index]
