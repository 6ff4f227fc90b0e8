"""Matterport3D equirectangular panoramas (the stitched 360 release used by depth-estimation work).

Expected layout::

    <root>/<scene_id>/<name>_rgb.png          8-bit RGB panorama (2:1)
    <root>/<scene_id>/<name>_depth.png        16-bit depth, metres = value / 4000, 0 = missing
    <root>/<scene_id>/<name>_semantic.png     optional: class ids of omnidl.classes (8/16-bit grey or palette
                                              indices; other ids: an error)
    <root>/scenes_<split>.txt                 optional: scene ids of a split, one per line

Without ``scenes_<split>.txt`` every scene folder is used for every split (and a warning says so).
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch

from omnidl.classes import NUM_CLASSES
from .paired import PairedPanoramas, PanoramaFiles, check_folder, drop_incomplete, to_tensor_labels
from .readers import read_depth_png, read_label_map, resize_labels
from .splits import check_relative_path
from .validate import check_class_ids, read_text

log = logging.getLogger("omnidl.data")
DEPTH_SCALE = 4000.0


def decode_class_png(path: Path, expect_wh, out_wh) -> torch.Tensor:
    raw = read_label_map(path, "semantic map", dtypes=(np.uint8, np.uint16), size=expect_wh)
    labels = check_class_ids(raw.astype(np.int64), path, "semantic map", NUM_CLASSES)
    return to_tensor_labels(resize_labels(labels, out_wh))


class Matterport3D(PairedPanoramas):
    """Matterport3D panoramas as sample dicts (``image``, ``depth``, optional ``semantic``, ``meta``).

    Args:
        root: dataset root (see module docstring); split: name of ``scenes_<split>.txt``; scenes: explicit ids.
        height, width: output size (default 256x512); semantic: also load ``*_semantic.png`` (required then).
        max_samples: keep only the first N panoramas.
    """

    def __init__(self, root: str, split: str = "train", scenes: list[str] | None = None, height: int | None = 256,
                 width: int | None = 512, semantic: bool = False, max_samples: int | None = None):
        root_p = check_folder(root, [], "Matterport3D")
        if scenes is None:
            split_file = root_p / f"scenes_{split}.txt"
            if split_file.is_file():
                scenes = [check_relative_path(s.strip(), f"{split_file}:{i}")
                          for i, s in enumerate(read_text(split_file, "scene list").splitlines(), 1) if s.strip()]
            else:
                scenes = sorted(p.name for p in root_p.iterdir() if p.is_dir())
                log.warning("Matterport3D: %s not found; using all %d scene folders for split %r", split_file,
                            len(scenes), split)
        root_p = check_folder(root, list(scenes), "Matterport3D")
        samples = []
        for sc in scenes:
            for rgb in sorted((root_p / sc).glob("*_rgb.png")):
                stem = rgb.name[: -len("_rgb.png")]
                samples.append(PanoramaFiles(name=f"{sc}_{stem}", image=rgb, depth=rgb.with_name(f"{stem}_depth.png"),
                                             semantic=rgb.with_name(f"{stem}_semantic.png") if semantic else None))
        if not samples:
            raise FileNotFoundError(f"Matterport3D: no *_rgb.png panoramas in the scene folders {scenes[:5]} of {root_p}")
        samples = drop_incomplete(samples, True, semantic, "Matterport3D")
        if max_samples:
            samples = samples[: int(max_samples)]

        def dec_depth(path, expect_wh, out_wh):
            return read_depth_png(path, DEPTH_SCALE, None, size=out_wh, expect=expect_wh)

        super().__init__(samples, height, width, dec_depth, decode_class_png if semantic else None, "Matterport3D")
