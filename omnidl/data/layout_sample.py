"""The standard layout sample of a *central* equirectangular panorama, shared by the real layout adapters
(:mod:`omnidl.data.pano_annotator`, :mod:`omnidl.data.zind`, ...).

Every adapter turns its file format into a room in omnidl's layout frame (gravity-aligned, z up, camera at
the origin; ``X_layout = UPRIGHT_TO_WORLD @ X_cam``, i.e. ``(x_l, y_l, z_l) = (x_cam, z_cam, -y_cam)``):
a top-view polygon ``(K, 2)`` (metres), the floor ``camera_height`` below the camera and the ceiling
``ceiling_height`` above it. :func:`layout_sample` makes the sample dict the layout models train on
(the keys of the data engine, ``docs/synth.md``):

* ``image (3, H, W)`` float32 RGB in ``[0, 1]``;
* ``boundary (2, W)`` ceiling/floor boundary rows (continuous pixel rows, through the camera) and
  ``boundary_valid (2, W)``;
* ``corner_heat (1, W)``: HorizonNet's ``0.96^d`` corner target at the corner columns;
* ``corners_cam (max_walls, 2, 3)`` ``[ceiling, floor]`` corners in the camera frame, zero-padded so that
  batches collate, with ``num_walls`` the number of real ones;
* ``camera_height ()`` metres (the central layout hooks read their scale from it);
* ``meta``: ``name``, ``file``, ``rig_radius = 0``, plus what the adapter adds.

:func:`check_room` is the one validation of a room polygon (finite, at least 3 corners, no corner twice, simple,
non-zero area, the camera inside), used by every layout adapter (label_cor ones through
:func:`polygon_from_corners_cam`); :func:`check_room_units` the one check of its units (metres).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..cameras import Equirectangular
from ..geometry.polygon import is_simple, points_in_polygon, polygon_area
from ..geometry.rotations import UPRIGHT_TO_WORLD
from .layout_targets import boundary_targets, corner_heat
from .readers import image_to_float
from .validate import DataValidationError, invalid

#: default padding of ``corners_cam`` (MatterportLayout rooms have up to 22 corners)
MAX_WALLS = 32
#: plausible camera height above the floor, metres (the unit checks of every layout adapter, docs/data.md)
CAMERA_HEIGHT_RANGE = (0.3, 5.0)
#: the largest room (top-view extent and floor-to-ceiling height), metres
MAX_ROOM_SIZE = 100.0
#: two corners closer than this (metres) are one corner listed twice
DUPLICATE_TOL = 1e-6
_R = np.asarray(UPRIGHT_TO_WORLD, dtype=np.float64)


def read_panorama(path: str | Path, width: int | None, height: int | None) -> torch.Tensor:
    """``(3, H, W)`` float32 RGB in ``[0, 1]`` of an equirectangular image (the reading policy of
    :func:`omnidl.data.readers.read_rgb`: EXIF orientation applied), resized to ``width x height`` when given.

    The stored (upright) image must be a full panorama (width = 2 x height); errors name the file."""
    from .readers import read_rgb_array, array_to_tensor
    arr = read_rgb_array(path, "panorama")
    h0, w0 = arr.shape[:2]
    if w0 != 2 * h0:
        raise invalid(path, "panorama", f"{w0}x{h0}", "an equirectangular image with width = 2 x height")
    return array_to_tensor(arr, (width or w0, height or h0))


def check_room(polygon: np.ndarray, path: str | Path, field: str) -> np.ndarray:
    """A top-view room polygon ``(K, 2)`` (layout frame) that layout targets can be made of, else a
    :class:`~omnidl.data.validate.DataValidationError` naming ``path`` and ``field``."""
    p = np.asarray(polygon, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2:
        raise invalid(path, field, f"of shape {tuple(p.shape)}", "a (K, 2) polygon")
    if not np.isfinite(p).all():
        k = int(np.argwhere(~np.isfinite(p))[0, 0])
        raise invalid(path, field, f"corner {k} = {p[k].tolist()}", "finite coordinates")
    if len(p) < 3:
        raise invalid(path, field, f"{len(p)} corner(s)", "at least 3 corners (a room polygon)")
    dist = np.linalg.norm(p[:, None] - p[None], axis=-1)
    dist[np.arange(len(p)), np.arange(len(p))] = np.inf
    if (dist <= DUPLICATE_TOL).any():
        j, k = sorted(int(i) for i in np.argwhere(dist <= DUPLICATE_TOL)[0])
        raise invalid(path, field, f"corner {k} = {p[k].tolist()} repeating corner {j} (a duplicated point)",
                      "each corner once")
    if not is_simple(p, 1e-9):
        raise invalid(path, field, f"a self-intersecting polygon ({len(p)} corners)",
                      "a simple polygon (walls in order, no crossings)")
    if abs(polygon_area(p)) < 1e-9:
        raise invalid(path, field, "a polygon of zero area", "a room of non-zero area")
    if not points_in_polygon(np.zeros((1, 2)), p)[0]:
        raise invalid(path, field, "a room that does not contain the camera",
                      "the camera (0, 0) inside the room polygon")
    return p


def check_room_units(polygon: np.ndarray, camera_height: float, ceiling_height: float, path: str | Path,
                     field: str = "room") -> None:
    """Plausible units of a room in metres, else a :class:`~omnidl.data.validate.DataValidationError` naming
    ``path``: the camera :data:`CAMERA_HEIGHT_RANGE` above the floor (a height in centimetres is 100x too
    large), the ceiling above the camera, and the room (its top view and its height) at most
    :data:`MAX_ROOM_SIZE` across (vertices in millimetres or x1e4 are not metres)."""
    for fld, v in (("camera height", camera_height), ("ceiling height above the camera", ceiling_height)):
        if not (np.isfinite(v) and v > 0):
            raise invalid(path, f"{field} {fld}", v, "a finite positive height in metres")
    lo, hi = CAMERA_HEIGHT_RANGE
    if not lo <= camera_height <= hi:
        raise invalid(path, f"{field} camera height", f"{camera_height:g} m", f"{lo:g}..{hi:g} m above the floor "
                      "(a height in centimetres or a wrong scale?)")
    if camera_height + ceiling_height > MAX_ROOM_SIZE:
        raise invalid(path, f"{field} height", f"{camera_height + ceiling_height:g} m (floor to ceiling)",
                      f"at most {MAX_ROOM_SIZE:g} m (heights in centimetres or a wrong scale?)")
    p = np.asarray(polygon, dtype=np.float64)
    size = float((p.max(0) - p.min(0)).max()) if p.size else 0.0
    if size > MAX_ROOM_SIZE:
        raise invalid(path, f"{field} polygon", f"{size:g} m across", f"a room at most {MAX_ROOM_SIZE:g} m across "
                      "in metres (vertices in another unit or a wrong scale?)")


def polygon_from_corners_cam(corners_cam: np.ndarray) -> np.ndarray:
    """``(K, 2, 3)`` ``[ceiling, floor]`` camera-frame corners -> the top-view floor polygon ``(K, 2)``
    (layout frame)."""
    c = np.asarray(corners_cam, dtype=np.float64)
    return (c[:, 1] @ _R.T)[:, :2]


def room_to_corners_cam(polygon: np.ndarray, camera_height: float, ceiling_height: float) -> np.ndarray:
    """Top-view polygon ``(K, 2)`` (layout frame), floor ``camera_height`` below and ceiling ``ceiling_height``
    above the camera -> ``(K, 2, 3)`` ``[ceiling, floor]`` corners in the camera frame."""
    p = np.asarray(polygon, dtype=np.float64)
    k = len(p)
    c = np.zeros((k, 2, 3))
    c[:, :, :2] = p[:, None]
    c[:, 0, 2], c[:, 1, 2] = ceiling_height, -camera_height
    return c @ _R                                                   # layout -> camera (R^T on the right)


def pad_corners(corners_cam: np.ndarray, max_walls: int, src: str | Path) -> torch.Tensor:
    """``(K, 2, 3)`` corners -> ``(max_walls, 2, 3)`` float32, zero rows after the ``K`` real ones (so batches
    collate; ``num_walls`` says ``K``). More than ``max_walls`` corners is an error naming ``src``."""
    cc = np.asarray(corners_cam)
    if len(cc) > max_walls:
        raise DataValidationError(f"{src}: room polygon has {len(cc)} corners, more than max_walls={max_walls} "
                                  "(raise data.max_walls)")
    padded = torch.zeros(max_walls, 2, 3)
    padded[: len(cc)] = torch.from_numpy(cc).float()
    return padded


def layout_sample(image: torch.Tensor, polygon: np.ndarray, camera_height: float, ceiling_height: float,
                  name: str, file: str | Path, max_walls: int = MAX_WALLS, label_file: str | Path | None = None,
                  meta: dict[str, Any] | None = None) -> dict[str, Any]:
    """The standard layout sample (module docstring) of a room seen from a central panorama.

    Args:
        image: ``(3, H, W)`` panorama (any size; the targets are made at this size).
        polygon: ``(K, 2)`` room polygon in the layout frame (metres), checked by :func:`check_room`.
        camera_height: camera above the floor (metres, > 0); ceiling_height: ceiling above the camera (> 0).
        name, file: sample name and image file (meta); label_file: the annotation file (for messages).
        max_walls: ``corners_cam`` padding; a room with more corners is an error naming the file.
    """
    src = label_file or file
    poly = check_room(polygon, src, "room polygon")
    check_room_units(poly, camera_height, ceiling_height, src)
    image = image_to_float(image, f"{file} image")
    H, W = image.shape[-2:]
    cam = Equirectangular(width=W, height=H)
    cc = room_to_corners_cam(poly, camera_height, ceiling_height)
    padded = pad_corners(cc, max_walls, src)                        # too many corners: an error naming src
    rows, valid = boundary_targets(cc, cam)
    if not bool(valid.any()):
        raise invalid(src, "room polygon", "a room whose boundary no column sees", "a room around the camera")
    uv, _ = cam.project(torch.from_numpy(cc[:, 1]))                 # floor corners -> corner columns
    m = {"name": name, "file": str(file), "rig_radius": 0.0, "camera": cam.to_config()}
    if label_file is not None:
        m["label_file"] = str(label_file)
    m.update(meta or {})
    return {"image": image, "boundary": rows, "boundary_valid": valid, "corner_heat": corner_heat(uv[:, 0].numpy(), W),
            "corners_cam": padded, "num_walls": torch.tensor(len(cc)),
            "camera_height": torch.tensor(float(camera_height)), "meta": m}
