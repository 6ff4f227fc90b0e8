"""Stanford2D3DS (2D-3D-Semantics) equirectangular panoramas.

Expected layout (as distributed; ``area_5a``/``area_5b`` are the two halves of area 5)::

    <root>/area_1/pano/rgb/camera_<id>_<room>_frame_equirectangular_domain_rgb.png
    <root>/area_1/pano/depth/camera_<id>_<room>_frame_equirectangular_domain_depth.png
    <root>/area_1/pano/semantic/camera_<id>_<room>_frame_equirectangular_domain_semantic.png
    <root>/semantic_labels.json        (or <root>/assets/semantic_labels.json, or labels_json=PATH)

Formats: depth is a 16-bit PNG in 1/512 m, 65535 = missing (range along the ray, as omnidl stores it; an 8-bit
depth PNG is refused).
A semantic PNG encodes an index into ``semantic_labels.json`` as ``R * 65536 + G * 256 + B``; the label
string ``<class>_<instance>_<room>_<n>_<m>`` maps to our classes by its first token (``<UNK>`` and indices
outside the list, e.g. the ``#0D0D0D`` of missing pixels, map to 0 = unknown).

Splits: the standard 3-fold protocol; fold 1 trains on areas 1, 2, 3, 4, 6 and tests on area 5 (5a + 5b).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from omnidl.classes import CLASS_ID
from .paired import PairedPanoramas, PanoramaFiles, check_folder, drop_incomplete, to_tensor_labels
from .readers import read_depth_png, resize_labels
from .validate import read_image

DEPTH_SCALE = 512.0
DEPTH_MISSING = 65535
#: fold -> (train areas, test areas); areas 5a/5b together are "area 5"
FOLDS: dict[int, tuple[tuple[str, ...], tuple[str, ...]]] = {
    1: (("1", "2", "3", "4", "6"), ("5a", "5b")),
    2: (("1", "3", "5a", "5b", "6"), ("2", "4")),
    3: (("2", "4", "5a", "5b"), ("1", "3", "6")),
}


def find_labels_json(root: Path, labels_json: str | None) -> Path:
    cands = [Path(labels_json)] if labels_json else [root / "semantic_labels.json",
                                                     root / "assets" / "semantic_labels.json"]
    for c in cands:
        if c.is_file():
            return c
    raise FileNotFoundError(f"Stanford2D3DS: semantic label list not found (looked for {[str(c) for c in cands]}); "
                            "it is assets/semantic_labels.json of the dataset release; pass data.labels_json=PATH")


def label_lut(labels_json: Path) -> np.ndarray:
    """``(N,)`` int64: label index of ``semantic_labels.json`` -> omnidl class id (0 for unknown names)."""
    try:
        names = json.loads(Path(labels_json).read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"Stanford2D3DS: cannot read the label list {labels_json}: {e}") from e
    if not isinstance(names, list):
        raise ValueError(f"Stanford2D3DS: {labels_json} should hold a JSON list of label strings")
    return np.array([CLASS_ID.get(str(n).split("_")[0], 0) for n in names], dtype=np.int64)


def decode_semantic(path: Path, lut: np.ndarray, expect_wh, out_wh) -> torch.Tensor:
    rgb = read_image(path, "semantic map", channels=3, dtypes=(np.uint8,), size=expect_wh, convert=False)
    r, g, b = rgb[..., 0].astype(np.int64), rgb[..., 1].astype(np.int64), rgb[..., 2].astype(np.int64)
    index = r * 65536 + g * 256 + b
    labels = np.where(index < len(lut), lut[np.minimum(index, len(lut) - 1)], 0)
    return to_tensor_labels(resize_labels(labels, out_wh))


def area_dir(area: str) -> str:
    return f"area_{area}"


class Stanford2D3DS(PairedPanoramas):
    """Stanford2D3DS panoramas as sample dicts (``image``, ``depth``, ``semantic``, ``meta``).

    Args:
        root: dataset root (see module docstring).
        split: ``train`` or ``test`` of ``fold`` (``val`` = ``test``: the dataset has no validation areas).
        fold: 1, 2 or 3 (fold 1: area 5 is the test set).
        areas: explicit area list (e.g. ``["1", "5a"]``), overrides ``split``/``fold``.
        height, width: output size (default 256x512; None keeps 2048x4096 / the stored size).
        labels_json: path of ``semantic_labels.json`` if it is not in ``root`` or ``root/assets``.
        max_samples: keep only the first N panoramas (sorted by name), for quick runs.
    """

    def __init__(self, root: str, split: str = "train", fold: int = 1, areas: list[str] | None = None,
                 height: int | None = 256, width: int | None = 512, labels_json: str | None = None,
                 max_samples: int | None = None):
        if areas is None:
            if fold not in FOLDS:
                raise ValueError(f"Stanford2D3DS: fold={fold}; expected one of {sorted(FOLDS)}")
            if split not in ("train", "val", "test"):
                raise ValueError(f"Stanford2D3DS: split={split!r}; expected train, val or test")
            areas = list(FOLDS[fold][0] if split == "train" else FOLDS[fold][1])
        areas = [str(a) for a in areas]
        root_p = check_folder(root, [f"{area_dir(a)}/pano/{k}" for a in areas for k in ("rgb", "depth", "semantic")],
                              "Stanford2D3DS")
        lut = label_lut(find_labels_json(root_p, labels_json))
        samples = []
        for a in areas:
            pano = root_p / area_dir(a) / "pano"
            for rgb in sorted((pano / "rgb").glob("*_rgb.png")):
                stem = rgb.name[: -len("_rgb.png")]
                samples.append(PanoramaFiles(name=f"area_{a}_{stem}", image=rgb,
                                             depth=pano / "depth" / f"{stem}_depth.png",
                                             semantic=pano / "semantic" / f"{stem}_semantic.png"))
        if not samples:
            raise FileNotFoundError(f"Stanford2D3DS: no *_rgb.png panoramas under {root_p}/area_*/pano/rgb for areas "
                                    f"{areas}")
        samples = drop_incomplete(samples, True, True, "Stanford2D3DS")
        if max_samples:
            samples = samples[: int(max_samples)]

        def dec_depth(path, expect_wh, out_wh):
            return read_depth_png(path, DEPTH_SCALE, DEPTH_MISSING, size=out_wh, expect=expect_wh)

        super().__init__(samples, height, width, dec_depth, lambda p, e, o: decode_semantic(p, lut, e, o),
                         "Stanford2D3DS")
        self.areas = areas
