"""Pano3D / 3D60-style panoramas: an RGB PNG and a float depth map in EXR per view.

Files (3D60's naming, which Pano3D keeps)::

    <root>/<part>/.../<id>_color_0_Left_Down_0.0.png
    <root>/<part>/.../<id>_depth_0_Left_Down_0.0.exr       float32 metres along the ray (single channel)

A split is a list file of ``<rgb path> <depth path>`` lines relative to ``root`` (the lists UniFuse and others
ship, e.g. ``3d60_test.txt``); without one, every ``*_color_*.png`` under ``root`` with its ``_depth_`` EXR
twin is used. EXR files are read with :mod:`omnidl.data.exr` (the OpenEXR package: every compression; no
OpenCV EXR support needed). Paths of a list must stay inside ``root`` (no absolute paths, no ``..``).

Depth: values above ``max_depth`` (3D60: 10 m, the far-away / outside-the-mesh pixels) and non-finite values
become 0 = invalid; ``meta["invalid_depth"]`` counts them (so nothing is dropped silently). A map whose median
valid depth is outside 0.05..100 m is in another unit (e.g. millimetres) and is an error naming the file.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from .exr import read_exr
from .readers import array_to_tensor, read_rgb_array
from .splits import check_relative_path
from .validate import DataValidationError, check_depth_units, check_size, invalid, read_text


def read_pair_list(path: str | Path) -> list[tuple[str, str]]:
    """``(rgb, depth)`` relative paths of a split list (two fields per line; blank lines skipped). A path that is
    absolute or climbs out of the dataset root with ``..`` is an error naming the file and line."""
    path = Path(path)
    out = []
    for i, line in enumerate(read_text(path, "split list").splitlines(), 1):
        parts = line.split()
        if not parts:
            continue
        if len(parts) != 2:
            raise DataValidationError(f"{path}:{i}: split line is {line!r}, expected '<rgb path> <depth path>'")
        out.append((check_relative_path(parts[0], f"{path}:{i}"), check_relative_path(parts[1], f"{path}:{i}")))
    if not out:
        raise DataValidationError(f"{path}: split list is empty, expected '<rgb path> <depth path>' lines")
    return out


def read_depth_exr(path: str | Path, max_depth: float | None, channel: str | None = None
                   ) -> tuple[np.ndarray, int]:
    """``(H, W)`` float32 metres with 0 where invalid (non-finite, <= 0 or above ``max_depth``) and the count of
    pixels made invalid that way. A map whose median valid depth is not a plausible indoor depth in metres
    (:func:`~omnidl.data.validate.check_depth_units`, e.g. millimetres) is an error naming the file."""
    planes = read_exr(path)
    if channel is None:
        if len(planes) != 1:
            channel = next((c for c in ("Y", "R", "Z", "depth") if c in planes), None)
            if channel is None:
                raise invalid(path, "EXR channels", sorted(planes), "a single depth channel (or Y, R, Z, depth)")
        else:
            channel = next(iter(planes))
    if channel not in planes:
        raise invalid(path, "EXR channel", repr(channel), f"one of {sorted(planes)}")
    d = planes[channel].astype(np.float32)
    check_depth_units(d, path, f"EXR depth channel {channel!r}")
    bad = ~np.isfinite(d) | (d < 0)
    if max_depth is not None:
        bad |= d > max_depth
    return np.where(bad, 0.0, d).astype(np.float32), int(bad.sum())


class Pano3D(torch.utils.data.Dataset):
    """Pano3D / 3D60 RGB + EXR depth samples ``{"image" (3,H,W), "depth" (1,H,W), "meta"}``.

    Args:
        root: dataset root; split_file: ``<rgb> <depth>`` list relative to ``root`` (``None``: every view found).
        height, width: output size (RGB area/linear, depth nearest; ``None`` keeps the file size).
        max_depth: depth above this is invalid (3D60: 10 m; ``None`` keeps every finite positive value).
        channel: EXR channel of the depth (default: the only one, else Y/R/Z/depth).
        max_samples: keep the first N views.
    """

    def __init__(self, root: str | Path, split_file: str | Path | None = None, height: int | None = 256,
                 width: int | None = 512, max_depth: float | None = 10.0, channel: str | None = None,
                 max_samples: int | None = None) -> None:
        self.root = Path(root).expanduser()
        if not self.root.is_dir():
            raise FileNotFoundError(f"Pano3D: dataset root {self.root} does not exist (set data.root=<folder>)")
        if split_file is not None:
            pairs = [(self.root / a, self.root / b) for a, b in read_pair_list(split_file)]
        else:
            pairs = [(p, p.with_name(p.name.replace("_color_", "_depth_")).with_suffix(".exr"))
                     for p in sorted(self.root.rglob("*_color_*.png"))]
        if not pairs:
            raise FileNotFoundError(f"Pano3D: no *_color_*.png views under {self.root}")
        for rgb, dep in pairs:
            for f in (rgb, dep):
                if not f.is_file():
                    raise FileNotFoundError(f"Pano3D: missing file {f} (of view {rgb.name})")
        self.pairs = pairs[: int(max_samples)] if max_samples else pairs
        self.height, self.width, self.max_depth, self.channel = height, width, max_depth, channel

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, i: int) -> dict[str, Any]:
        rgb_p, dep_p = self.pairs[i]
        size = (self.width, self.height) if self.width and self.height else None
        rgb = read_rgb_array(rgb_p)
        depth, n_bad = read_depth_exr(dep_p, self.max_depth, self.channel)
        check_size(depth, (rgb.shape[1], rgb.shape[0]), dep_p, "EXR depth")
        img = array_to_tensor(rgb, size)
        if size is not None and (depth.shape[1], depth.shape[0]) != size:
            depth = cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST)
        return {"image": img, "depth": torch.from_numpy(np.ascontiguousarray(depth))[None],
                "meta": {"name": rgb_p.stem.split("_color_")[0], "image": str(rgb_p), "depth_file": str(dep_p),
                         "invalid_depth": n_bad, "index": int(i), "dataset": "pano3d"}}
