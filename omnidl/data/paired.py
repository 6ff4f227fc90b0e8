"""A dataset over lists of panorama files (RGB + optional depth + optional semantic), shared by the real loaders."""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch.utils.data import Dataset

from .readers import array_to_tensor, read_rgb_array
from .validate import check_size  # noqa: F401  (re-exported: the loaders import it from here)

log = logging.getLogger("omnidl.data")


@dataclass(frozen=True)
class PanoramaFiles:
    """The files of one sample; ``depth``/``semantic`` are None for unlabelled data."""

    name: str
    image: Path
    depth: Path | None = None
    semantic: Path | None = None


def check_folder(root: str | Path, required: list[str], what: str) -> Path:
    """Raise ``FileNotFoundError`` naming every missing sub-folder of ``root`` (relative paths in ``required``)."""
    root = Path(root).expanduser()
    if not root.is_dir():
        raise FileNotFoundError(f"{what}: dataset root {root} does not exist (set data.root=<folder>)")
    missing = [r for r in required if not (root / r).is_dir()]
    if missing:
        present = sorted(p.name for p in root.iterdir())[:20]
        raise FileNotFoundError(f"{what}: {root} lacks {missing} (it contains {present}); see docs/engine.md "
                                "'Datasets' for the expected layout")
    return root


def drop_incomplete(samples: list[PanoramaFiles], need_depth: bool, need_semantic: bool, what: str
                    ) -> list[PanoramaFiles]:
    """Remove samples whose label files are missing, with one warning that names them."""
    keep, bad = [], []
    for s in samples:
        missing = []
        if need_depth and (s.depth is None or not s.depth.is_file()):
            missing.append(str(s.depth) if s.depth else f"depth of {s.image.name}")
        if need_semantic and (s.semantic is None or not s.semantic.is_file()):
            missing.append(str(s.semantic) if s.semantic else f"semantic of {s.image.name}")
        (bad if missing else keep).append((s, missing) if missing else s)
    if bad:
        listed = "; ".join(f"{s.image}: missing {m}" for s, m in bad[:10])
        log.warning("%s: skipping %d sample(s) with missing label files: %s%s", what, len(bad), listed,
                    " ..." if len(bad) > 10 else "")
    return keep


class PairedPanoramas(Dataset):
    """Samples ``{"image", "depth"?, "semantic"?, "meta"}`` (docs/extending.md) from :class:`PanoramaFiles`.

    Args:
        samples: the files.
        height, width: output size (RGB resized with area/linear, labels with nearest); None keeps the file size.
        decode_depth: ``path, expect_wh, out_wh -> (1, H, W)`` metres (0 = invalid).
        decode_semantic: ``path, expect_wh, out_wh -> (H, W)`` int64 class ids of :mod:`omnidl.classes`.
        what: the dataset name used in messages.
    Depth and semantic maps must have the RGB image's size; a mismatch, an unreadable or truncated file raises
    :class:`CorruptSampleError` naming the file (the engine then skips the sample with a warning).
    """

    def __init__(self, samples: list[PanoramaFiles], height: int | None, width: int | None,
                 decode_depth: Callable | None, decode_semantic: Callable | None, what: str):
        if not samples:
            raise FileNotFoundError(f"{what}: no samples found")
        self.samples, self.what = samples, what
        self.size = (int(width), int(height)) if height and width else None
        self.decode_depth, self.decode_semantic = decode_depth, decode_semantic

    def __len__(self) -> int:
        return len(self.samples)

    def __getitem__(self, index: int) -> dict:
        s = self.samples[index]
        rgb = read_rgb_array(s.image)            # the reading policy (readers.py); a bad file: CorruptSampleError
        wh = (rgb.shape[1], rgb.shape[0])
        out_wh = self.size or wh
        sample = {"image": array_to_tensor(rgb, size=out_wh)}
        if s.depth is not None and self.decode_depth is not None:
            sample["depth"] = self.decode_depth(s.depth, wh, out_wh)
        if s.semantic is not None and self.decode_semantic is not None:
            sample["semantic"] = self.decode_semantic(s.semantic, wh, out_wh)
        sample["meta"] = {"name": s.name, "image": str(s.image), "index": int(index), "dataset": self.what,
                          "stored_size": list(wh)}
        return sample


def to_tensor_labels(labels: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(labels.astype(np.int64)))
