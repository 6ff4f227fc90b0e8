"""Zillow Indoor Dataset (ZInD) layouts: ``zind_data.json`` per house, upright panoramas as provided.

Folder (as ZInD is distributed; ``zind_partition.json`` is written by ZInD's ``partition_zind.py``)::

    <root>/zind_partition.json                 {"train": [house ids], "val": [...], "test": [...]}
    <root>/room_shape_simplicity_labels.json   optional: {"<house>_..._pano_<id>": true|false}
    <root>/<house>/zind_data.json
    <root>/<house>/panos/floor_<f>_partial_room_<r>_pano_<p>.jpg   (the pano's ``image_path``)

``zind_data.json`` (ZInD's ``data_organization.md``): ``merger -> floor_<f> -> complete_room_<c> ->
partial_room_<r> -> pano_<p>``, each pano with ``camera_height`` (normalised to 1), ``ceiling_height``,
``image_path``, ``is_inside``, ``is_primary``, ``is_ceiling_flat``, ``floor_plan_transformation``
(``translation``, ``rotation``, ``scale``) and the layouts ``layout_raw`` / ``layout_visible`` /
``layout_complete`` (``vertices``: top-view ``(x, y)`` in the pano's local frame, camera at the origin);
top-level ``scale_meters_per_coordinate -> floor_<f>`` (may be ``null``).

Frames: ZInD's azimuth of a local point is ``atan2(-x, y)`` (its ``TransformationSpherical``), omnidl's
longitude is ``atan2(x_cam, z_cam)``, so ``x_cam = -x``, ``z_cam = y`` and the layout-frame corner is
``(-x, y)``. Metres per local unit: ``floor_plan_transformation.scale * scale_meters_per_coordinate[floor]``
(``scale="metric"``); when the floor has no scale, or with ``scale="camera_height"``, the camera is put
``camera_height`` metres above the floor instead (the fixed-height convention of the layout protocols;
``meta["metric"]`` says which).

Panoramas are left out, with one warning naming them, when they lack the chosen layout, are taken outside
it (``is_inside = false``), their layout is not a simple polygon around the camera (a corner listed twice
included), or its units are implausible in metres (camera 0.3..5 m above the floor, room at most 100 m across:
a wrong ``scale_meters_per_coordinate`` or vertex unit); an ``image_path`` that leaves the house folder (absolute,
``..``) is an error. Optional filters keep
primary panoramas, flat ceilings or the "simple" room shapes only.
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
from .splits import check_relative_path, read_zind_partition
from .validate import DataValidationError, UnreadableFileError, invalid, read_text

LAYOUTS = ("visible", "complete", "raw")


@dataclass(frozen=True)
class ZindPano:
    name: str
    image: Path
    label_file: Path
    polygon: np.ndarray          # (K, 2) layout frame, metres
    camera_height: float         # metres
    ceiling_height: float        # above the camera, metres
    metric: bool


def _load_json(path: Path, what: str) -> Any:
    try:
        return json.loads(read_text(path, what))
    except json.JSONDecodeError as e:
        raise UnreadableFileError(f"cannot parse {path} ({what}: {e.msg} at line {e.lineno}; expected JSON)") from e


def _num(path: Path, field: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise invalid(path, field, repr(v), "a finite number")
    return float(v)


def _obj(path: Path, field: str, v: Any) -> dict:
    if not isinstance(v, dict):
        raise invalid(path, field, "missing" if v is None else f"a {type(v).__name__}", "a JSON object")
    return v


def iter_panos(data: dict, path: Path):
    """``(floor_id, pano_key, pano dict)`` of every pano of a parsed ``zind_data.json`` (structure checked)."""
    merger = _obj(path, "merger", data.get("merger"))
    for fid, floor in merger.items():
        for cid, room in _obj(path, f"merger.{fid}", floor).items():
            for pid, partial in _obj(path, f"merger.{fid}.{cid}", room).items():
                for key, pano in _obj(path, f"merger.{fid}.{cid}.{pid}", partial).items():
                    yield fid, key, _obj(path, f"merger.{fid}.{cid}.{pid}.{key}", pano), f"merger.{fid}.{cid}.{pid}.{key}"


def parse_pano(path: Path, house: str, fid: str, key: str, pano: dict, where: str, layout: str, scale: str,
               camera_height: float, floor_scale: float | None) -> tuple[np.ndarray, float, float, bool, str]:
    """``(polygon, camera_height_m, ceiling_above_camera_m, metric, image_path)`` of one pano (checked)."""
    for k in ("camera_height", "ceiling_height", "image_path"):
        if k not in pano:
            raise invalid(path, f"{where}.{k}", "missing", "a field of every pano (ZInD data_organization.md)")
    ch = _num(path, f"{where}.camera_height", pano["camera_height"])
    ceil = _num(path, f"{where}.ceiling_height", pano["ceiling_height"])
    if ch <= 0 or ceil <= ch:
        raise invalid(path, f"{where}.ceiling_height", f"{ceil:g} with camera_height {ch:g}",
                      "0 < camera_height < ceiling_height")
    lay = _obj(path, f"{where}.layout_{layout}", pano[f"layout_{layout}"])
    verts = lay.get("vertices")
    try:
        v = np.asarray(verts, dtype=np.float64)
    except (TypeError, ValueError):
        v = None
    if v is None or v.ndim != 2 or v.shape[1] != 2:
        raise invalid(path, f"{where}.layout_{layout}.vertices", repr(verts)[:60], "a list of [x, y] pairs")
    if not np.isfinite(v).all():
        raise invalid(path, f"{where}.layout_{layout}.vertices", "non-finite values", "finite coordinates")
    units = None
    if scale == "metric" and floor_scale is not None:
        fpt = _obj(path, f"{where}.floor_plan_transformation", pano.get("floor_plan_transformation"))
        s = _num(path, f"{where}.floor_plan_transformation.scale", fpt.get("scale"))
        if s <= 0:
            raise invalid(path, f"{where}.floor_plan_transformation.scale", s, "a positive scale")
        units = s * floor_scale
    metric = units is not None
    if units is None:
        units = camera_height / ch
    poly = np.stack([-v[:, 0], v[:, 1]], -1) * units
    img = pano["image_path"]
    if not isinstance(img, str) or not img:
        raise invalid(path, f"{where}.image_path", repr(img), "a relative image path")
    check_relative_path(img, f"{path}: {where}.image_path")
    return poly, ch * units, (ceil - ch) * units, metric, img


class ZInD(torch.utils.data.Dataset):
    """ZInD panoramas with their room layouts as standard layout samples (module docstring).

    Args:
        root: dataset folder; split: ``train``/``val``/``test`` of ``zind_partition.json`` (``None``: every house
            folder); houses: explicit house ids (override ``split``).
        layout: ``visible`` (what the panorama sees; default), ``complete`` (the merged room) or ``raw``.
        scale: ``metric`` (dataset scale where known, else ``camera_height``) or ``camera_height``.
        camera_height: metres, for panoramas without metric scale (and for ``scale="camera_height"``).
        primary_only, ceiling_flat_only, simple_only: filters (``simple_only`` reads
            ``room_shape_simplicity_labels.json``).
        height, width, max_walls, max_samples: as the other layout adapters.
    """

    def __init__(self, root: str | Path, split: str | None = "train", houses: list[str] | None = None,
                 layout: str = "visible", scale: str = "metric", camera_height: float = 1.6,
                 primary_only: bool = False, ceiling_flat_only: bool = False, simple_only: bool = False,
                 height: int | None = 512, width: int | None = 1024, max_walls: int = MAX_WALLS,
                 max_samples: int | None = None) -> None:
        if layout not in LAYOUTS:
            raise ValueError(f"ZInD: layout={layout!r}; expected one of {', '.join(LAYOUTS)}")
        if scale not in ("metric", "camera_height"):
            raise ValueError(f"ZInD: scale={scale!r}; expected 'metric' or 'camera_height'")
        if not (math.isfinite(camera_height) and camera_height > 0):
            raise ValueError(f"ZInD: camera_height={camera_height}; expected a positive height in metres")
        self.root = Path(root).expanduser()
        if not self.root.is_dir():
            raise FileNotFoundError(f"ZInD: dataset root {self.root} does not exist (set data.root=<folder>)")
        if houses is None:
            if split is None:
                houses = sorted(p.name for p in self.root.iterdir() if (p / "zind_data.json").is_file())
            else:
                houses = read_zind_partition(self.root / "zind_partition.json", split)
        simple = None
        if simple_only:
            lab = self.root / "room_shape_simplicity_labels.json"
            labels = _obj(lab, "room shape simplicity labels", _load_json(lab, "room shape simplicity labels"))
            # keys "<house>_..._pano_<id>" (as LGT-Net reads them): keep (house, "pano_<id>") of the simple ones
            simple = {(k.split("_")[0], "_".join(k.split("_")[-2:])) for k, v in labels.items() if v is True}
        self.items: list[ZindPano] = []
        skipped: list[str] = []
        for house in houses:
            path = self.root / str(house) / "zind_data.json"
            if not path.is_file():
                raise FileNotFoundError(f"ZInD: house {house!r} has no {path}")
            data = _obj(path, "zind_data.json", _load_json(path, "zind_data.json"))
            scales = data.get("scale_meters_per_coordinate") or {}
            if not isinstance(scales, dict):
                raise invalid(path, "scale_meters_per_coordinate", f"a {type(scales).__name__}", "an object per floor")
            for fid, key, pano, where in iter_panos(data, path):
                name = f"{house}_{fid}_{key}"
                if f"layout_{layout}" not in pano:
                    skipped.append(f"{name} (no layout_{layout})")
                    continue
                if pano.get("is_inside") is False:
                    skipped.append(f"{name} (is_inside = false)")
                    continue
                if primary_only and not pano.get("is_primary", False):
                    continue
                if ceiling_flat_only and not pano.get("is_ceiling_flat", False):
                    continue
                if simple is not None and (str(house), key) not in simple:
                    continue
                fs = scales.get(fid)
                fs = None if fs is None else _num(path, f"scale_meters_per_coordinate.{fid}", fs)
                poly, ch, ceil, metric, img = parse_pano(path, str(house), fid, key, pano, where, layout, scale,
                                                         camera_height, fs)
                try:
                    check_room(poly, path, f"{where}.layout_{layout}")
                    check_room_units(poly, ch, ceil, path, where)
                except DataValidationError as e:
                    skipped.append(f"{name} ({e})")
                    continue
                self.items.append(ZindPano(name, self.root / str(house) / img, path, poly, ch, ceil, metric))
        if skipped:
            warnings.warn(f"ZInD: left out {len(skipped)} panorama(s): " + "; ".join(skipped[:10])
                          + (" ..." if len(skipped) > 10 else ""), stacklevel=2)
        if not self.items:
            raise FileNotFoundError(f"ZInD: no usable panoramas with layout_{layout} in houses {list(houses)[:5]} of "
                                    f"{self.root}")
        if max_samples:
            self.items = self.items[: int(max_samples)]
        self.layout, self.height, self.width, self.max_walls = layout, height, width, int(max_walls)
        self.camera = None
        if height is not None and width is not None:
            from ..cameras import Equirectangular
            self.camera = Equirectangular(width=width, height=height)

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> dict[str, Any]:
        p = self.items[i]
        image = read_panorama(p.image, self.width, self.height)
        return layout_sample(image, p.polygon, p.camera_height, p.ceiling_height, p.name, p.image, self.max_walls,
                             label_file=p.label_file, meta={"dataset": "zind", "layout": self.layout,
                                                            "metric": p.metric})
