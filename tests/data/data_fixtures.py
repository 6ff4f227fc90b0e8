"""Tiny dataset fixtures written in the real formats with OpenCV (Stanford2D3DS, Matterport3D, image folder)."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

#: a Stanford2D3DS-style label list: index -> "<class>_<instance>_<room>_<n>_<m>"
S2D3DS_LABELS = ["<UNK>_0_<UNK>_0_0", "wall_1_office_1_1", "floor_1_office_1_1", "chair_3_office_1_2",
                 "ceiling_1_office_1_1", "window_2_office_1_3"]
#: the omnidl class ids those labels map to (classes.py order)
S2D3DS_CLASSES = [0, 12, 9, 5, 4, 13]


def write_stanford(root: Path, areas=("1", "5a"), per_area: int = 2, w: int = 64, h: int = 32, seed: int = 0):
    """Write ``per_area`` panoramas per area; returns {name: (rgb uint8 HxWx3 RGB, depth_m, label_index)}."""
    rng = np.random.default_rng(seed)
    (root / "assets").mkdir(parents=True, exist_ok=True)
    (root / "assets" / "semantic_labels.json").write_text(json.dumps(S2D3DS_LABELS))
    truth = {}
    for a in areas:
        pano = root / f"area_{a}" / "pano"
        for k in ("rgb", "depth", "semantic"):
            (pano / k).mkdir(parents=True, exist_ok=True)
        for i in range(per_area):
            stem = f"camera_{a}{i:02d}abc_office_1_frame_equirectangular_domain"
            rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
            units = rng.integers(256, 4096, (h, w)).astype(np.uint16)
            units[0, :5] = 65535  # missing depth
            index = rng.integers(0, len(S2D3DS_LABELS), (h, w))
            index[1, :3] = 0x0D0D0D  # missing-label colour
            sem = np.stack([index % 256, (index // 256) % 256, index // 65536], -1).astype(np.uint8)  # BGR order
            cv2.imwrite(str(pano / "rgb" / f"{stem}_rgb.png"), rgb[..., ::-1])
            cv2.imwrite(str(pano / "depth" / f"{stem}_depth.png"), units)
            cv2.imwrite(str(pano / "semantic" / f"{stem}_semantic.png"), sem)
            truth[f"area_{a}_{stem}"] = (rgb, np.where(units == 65535, 0, units / 512.0), index)
    return truth


def write_matterport(root: Path, scenes=("scA", "scB"), per_scene: int = 2, w: int = 64, h: int = 32, seed: int = 1,
                     semantic: bool = True, splits: dict | None = None):
    rng = np.random.default_rng(seed)
    truth = {}
    for sc in scenes:
        (root / sc).mkdir(parents=True, exist_ok=True)
        for i in range(per_scene):
            stem = f"pano{i:02d}"
            rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
            units = rng.integers(0, 40000, (h, w)).astype(np.uint16)
            sem = rng.integers(0, 14, (h, w)).astype(np.uint8)
            cv2.imwrite(str(root / sc / f"{stem}_rgb.png"), rgb[..., ::-1])
            cv2.imwrite(str(root / sc / f"{stem}_depth.png"), units)
            if semantic:
                cv2.imwrite(str(root / sc / f"{stem}_semantic.png"), sem)
            truth[f"{sc}_{stem}"] = (rgb, units / 4000.0, sem)
    for split, ids in (splits or {}).items():
        (root / f"scenes_{split}.txt").write_text("\n".join(ids) + "\n")
    return truth


def truncate(path: Path, keep: float = 0.5) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])
