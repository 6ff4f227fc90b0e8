"""Corrupt-input handling shared by the dataset loaders."""
from __future__ import annotations

import logging
from collections import deque

from torch.utils.data import Dataset

log = logging.getLogger("omnidl.data")


class CorruptSampleError(RuntimeError):
    """A sample's files exist but cannot be used (truncated PNG, wrong size, missing label file ...).

    The message names the file and what was expected.
    """


class TooManyCorruptSamples(RuntimeError):
    """:class:`SkipCorrupt` gave up: too many skips, or a whole pass over the dataset was corrupt.

    Not a :class:`CorruptSampleError`, so no wrapper skips it; the message names the last files."""


class SkipCorrupt(Dataset):
    """Wrap a dataset so that :class:`CorruptSampleError` items become ``None`` (with a warning naming the
    file) instead of stopping training; :func:`omnidl.data.collate.collate_samples` drops them (a batch of
    only skipped samples is ``None``).

    Raises :class:`TooManyCorruptSamples` (naming the last files) when

    * ``len(dataset)`` items in a row were skipped with no good one in between: a whole pass is corrupt;
    * more than ``max_skips`` skips happened in this process (every occurrence counts, so a small dataset read
      for many epochs stops too) while skips outnumber the good samples read (a mostly corrupt dataset; a large
      healthy one with a few bad files, read for many epochs, goes on);
    * more than ``max_skips`` distinct samples were skipped.

    With DataLoader workers each worker counts its own skips (its copy of this object); the trainer's
    ``trainer.max_skipped`` bounds the batches that come out empty.
    """

    def __init__(self, dataset, max_skips: int = 1000):
        self.dataset = dataset
        self.max_skips = int(max_skips)
        self.skipped: set[int] = set()
        self.skip_count = 0
        self.ok_count = 0
        self.in_row = 0
        self._recent: deque[str] = deque(maxlen=5)

    def __len__(self) -> int:
        return len(self.dataset)

    def __getattr__(self, name):
        if name in ("dataset", "_recent"):
            raise AttributeError(name)
        return getattr(self.dataset, name)

    def __getitem__(self, index: int):
        try:
            sample = self.dataset[index]
        except CorruptSampleError as e:
            self.skipped.add(index)
            self.skip_count += 1
            self.in_row += 1
            self._recent.append(str(e))
            whole_pass = self.in_row >= max(1, len(self.dataset))
            mostly = self.skip_count > self.max_skips and self.skip_count > self.ok_count
            if whole_pass or mostly or len(self.skipped) > self.max_skips:
                why = (f"all {self.in_row} samples read in a row were corrupt (a whole pass over the dataset)"
                       if whole_pass else f"{self.skip_count} corrupt samples skipped (max_skips={self.max_skips}) "
                       f"against {self.ok_count} good ones")
                raise TooManyCorruptSamples(f"{why}; {len(self.skipped)} distinct sample(s) failed, the last: "
                                            + " | ".join(self._recent)) from e
            log.warning("skipping sample %d: %s", index, e)
            return None
        self.in_row = 0
        self.ok_count += 1
        return sample
