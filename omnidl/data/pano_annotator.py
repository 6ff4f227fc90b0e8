"""PanoAnnotator / LayoutMP3D JSON layouts (MatterportLayout, as used by DuLa-Net, LGT-Net and others).

Format (PanoAnnotator's ``saveSceneAsJson``; the MatterportLayout release ships one file per panorama)::

    {"cameraHeight": 1.6, "layoutHeight": 2.9, "cameraCeilingHeight": 1.3,
     "layoutPoints": {"num": K, "points": [{"xyz": [x, y, z], "coords": [cx, cy], "id": ...}, ...]},
     "layoutWalls":  {"num": K, "walls":  [{"pointsIdx": [i, j], "normal": [...], ...}, ...]}}

PanoAnnotator's frame: ``coords (cx, cy) in [0, 1]`` -> longitude ``(cx - 0.5) 2 pi``, latitude
``(0.5 - cy) pi`` (up positive), ``xyz = (cos lat sin lon, sin lat, -cos lat cos lon)`` scaled: x right,
y **up**, z **backward**. omnidl's camera frame is x right, y down, z forward with the same longitude, so
a point maps as ``x_cam = x``, ``z_cam = -z`` (and ``y_cam = -y``); in the layout frame the corner is
``(x, -z)``. Like LGT-Net's reader, only the horizontal position of each point is used: the floor is put
``cameraHeight`` below the camera and the ceiling ``cameraCeilingHeight`` above it (``layoutHeight -
cameraHeight`` when that key is absent). The corner order is the wall order: corner ``k`` is
``pointsIdx[0]`` of wall ``k``.

Folder (LGT-Net's ``mp3d`` layout; the release's ``<scene>_<pano>_label.json`` names are accepted too)::

    <root>/image/<scene>_<pano>.png|jpg
    <root>/label/<scene>_<pano>.json      (or <scene>_<pano>_label.json)
    <root>/split/{train,val,test}.txt     (or <root>/mp3d_{train,val,test}.txt; lines "<scene> <pano>")

Samples: :func:`omnidl.data.layout_sample.layout_sample` (``camera_height`` from the file). Units are metres:
a ``cameraHeight`` outside 0.3..5 m (centimetres), a room over 100 m across or a ceiling over 100 m are
errors naming the file (:func:`~omnidl.data.layout_sample.check_room_units`).
"""
from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .layout_sample import MAX_WALLS, check_room, check_room_units, layout_sample, read_panorama
from .splits import find_split_file, read_split_list
from .validate import UnreadableFileError, invalid, read_text

IMAGE_EXTS = (".png", ".jpg", ".jpeg")
SPLIT_PATTERNS = ("split/{split}.txt", "mp3d_{split}.txt", "data_list/mp3d_{split}.txt")


@dataclass(frozen=True)
class PanoAnnotatorLabel:
    """A parsed label: ``polygon (K, 2)`` in the layout frame (units of the file, metres), heights above/below
    the camera."""

    polygon: np.ndarray
    camera_height: float
    ceiling_height: float


def _number(path: Path, field: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise invalid(path, field, repr(v), "a number")
    if not math.isfinite(v):
        raise invalid(path, field, v, "a finite number")
    return float(v)


def _section(path: Path, data: dict, key: str, items: str) -> list:
    sec = data.get(key)
    if not isinstance(sec, dict) or not isinstance(sec.get(items), list):
        raise invalid(path, key, "missing" if sec is None else repr(sec)[:60], f'an object {{"num": K, "{items}": [...]}}')
    lst = sec[items]
    if "num" in sec and sec["num"] != len(lst):
        raise invalid(path, f"{key}.num", sec["num"], f"the number of {items} listed ({len(lst)})")
    return lst


def read_pano_annotator_json(path: str | Path) -> PanoAnnotatorLabel:
    """Parse and check one PanoAnnotator JSON label; errors name the file, the field and the value."""
    path = Path(path)
    try:
        data = json.loads(read_text(path, "PanoAnnotator label"))
    except json.JSONDecodeError as e:
        raise UnreadableFileError(f"cannot parse {path} (PanoAnnotator label: {e.msg} at line {e.lineno}; "
                                  "expected JSON)") from e
    if not isinstance(data, dict):
        raise invalid(path, "PanoAnnotator label", f"a JSON {type(data).__name__}", "a JSON object")
    if "cameraHeight" not in data:
        raise invalid(path, "cameraHeight", "missing", "the camera height above the floor")
    cam_h = _number(path, "cameraHeight", data["cameraHeight"])
    if "cameraCeilingHeight" in data:
        ceil_h = _number(path, "cameraCeilingHeight", data["cameraCeilingHeight"])
    elif "layoutHeight" in data:
        ceil_h = _number(path, "layoutHeight", data["layoutHeight"]) - cam_h
    else:
        raise invalid(path, "cameraCeilingHeight", "missing (and no layoutHeight)", "the ceiling height above the camera")
    if cam_h <= 0:
        raise invalid(path, "cameraHeight", cam_h, "a positive height (metres)")
    if ceil_h <= 0:
        raise invalid(path, "cameraCeilingHeight", ceil_h, "a positive height of the ceiling above the camera")
    points = _section(path, data, "layoutPoints", "points")
    walls = _section(path, data, "layoutWalls", "walls")
    xyz = []
    for i, p in enumerate(points):
        v = p.get("xyz") if isinstance(p, dict) else None
        if not isinstance(v, list) or len(v) != 3:
            raise invalid(path, f"layoutPoints.points[{i}].xyz", repr(v)[:60], "a list of 3 numbers")
        xyz.append([_number(path, f"layoutPoints.points[{i}].xyz", c) for c in v])
    if len(walls) != len(points):
        raise invalid(path, "layoutWalls", f"{len(walls)} walls for {len(points)} points",
                      "one wall per corner (a closed room)")
    order = []
    for k, w in enumerate(walls):
        idx = w.get("pointsIdx") if isinstance(w, dict) else None
        if (not isinstance(idx, list) or len(idx) != 2 or not all(isinstance(i, int) and not isinstance(i, bool)
                                                                   for i in idx)):
            raise invalid(path, f"layoutWalls.walls[{k}].pointsIdx", repr(idx)[:60], "two integer point indices")
        for i in idx:
            if not 0 <= i < len(points):
                raise invalid(path, f"layoutWalls.walls[{k}].pointsIdx", idx, f"indices in 0..{len(points) - 1}")
        order.append(idx[0])
    if sorted(order) != list(range(len(points))):
        raise invalid(path, "layoutWalls.walls[*].pointsIdx[0]", order, "each point starting exactly one wall")
    pts = np.asarray(xyz, dtype=np.float64)[order] if order else np.zeros((0, 3))
    polygon = np.stack([pts[:, 0], -pts[:, 2]], -1) if len(pts) else np.zeros((0, 2))
    check_room(polygon, path, "layoutPoints (top view)")
    check_room_units(polygon, cam_h, ceil_h, path, "cameraHeight / layoutPoints")
    return PanoAnnotatorLabel(polygon, cam_h, ceil_h)


class PanoAnnotatorLayout(torch.utils.data.Dataset):
    """MatterportLayout-style folder of panoramas + PanoAnnotator JSON labels (module docstring).

    Args:
        root: dataset folder.
        split: ``train`` / ``val`` / ``test`` (read from the split file) or ``None`` (every image with a label).
        split_file: explicit split list (overrides the search in ``root``).
        height, width: network input size (``None`` keeps each file's size; targets are made at this size).
        max_walls: padding of ``corners_cam``.
        max_samples: keep the first N samples (quick runs).
    """

    def __init__(self, root: str | Path, split: str | None = "train", split_file: str | Path | None = None,
                 height: int | None = 512, width: int | None = 1024, max_walls: int = MAX_WALLS,
                 max_samples: int | None = None) -> None:
        self.root = Path(root).expanduser()
        img_dir, lab_dir = self.root / "image", self.root / "label"
        for d in (img_dir, lab_dir):
            if not d.is_dir():
                raise FileNotFoundError(f"PanoAnnotatorLayout: {d} not found; expected <root>/image and <root>/label "
                                        "(set data.root=<folder>)")
        images = {p.stem: p for p in sorted(img_dir.iterdir()) if p.suffix.lower() in IMAGE_EXTS}
        if split_file is not None:
            names = read_split_list(split_file)
        elif split is not None:
            names = read_split_list(find_split_file(self.root, split, SPLIT_PATTERNS, "PanoAnnotatorLayout"))
        else:
            names = sorted(images)
        self.items: list[tuple[str, Path, Path]] = []
        unlabelled: list[str] = []
        for n in names:
            if n not in images:
                raise FileNotFoundError(f"PanoAnnotatorLayout: split panorama {n!r} has no image {img_dir}/{n}.png|jpg")
            lab = next((c for c in (lab_dir / f"{n}.json", lab_dir / f"{n}_label.json") if c.is_file()), None)
            if lab is None:
                if split is None and split_file is None:
                    unlabelled.append(n)                            # an image outside any split: left out, said
                    continue
                raise FileNotFoundError(f"PanoAnnotatorLayout: no label for {n!r} ({lab_dir}/{n}.json or "
                                        f"{n}_label.json)")
            self.items.append((n, images[n], lab))
        if unlabelled:
            warnings.warn(f"PanoAnnotatorLayout: left out {len(unlabelled)} image(s) without a label in {lab_dir}: "
                          f"{unlabelled[:10]}", stacklevel=2)
        if not self.items:
            raise FileNotFoundError(f"PanoAnnotatorLayout: no labelled panoramas in {self.root}")
        if max_samples:
            self.items = self.items[: int(max_samples)]
        self.height, self.width, self.max_walls = height, width, int(max_walls)
        self.camera = None
        if height is not None and width is not None:
            from ..cameras import Equirectangular
            self.camera = Equirectangular(width=width, height=height)

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> dict[str, Any]:
        name, img, lab = self.items[i]
        label = read_pano_annotator_json(lab)
        image = read_panorama(img, self.width, self.height)
        return layout_sample(image, label.polygon, label.camera_height, label.ceiling_height, name, img,
                             self.max_walls, label_file=lab, meta={"dataset": "pano_annotator"})
