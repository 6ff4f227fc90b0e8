"""HorizonNet's ``label_cor`` format and a folder dataset (``root/img/*.png|jpg`` + ``root/label_cor/*.txt``).

``label_cor``: one ``x y`` per line (0-based pixels, top-left origin: the centre of pixel column ``j`` is
``x = j``, i.e. our continuous ``u = x + 0.5``), ceiling then floor of each wall-wall corner, corners
in layout order (HorizonNet) or sorted by ``x`` (NonCentralIndoorDataset).

The folder dataset is for *central* equirectangular panoramas: the 3D room is recovered from the
corner pixels with an assumed camera height (HorizonNet's convention, 1.6 m; only the shape
matters for the targets), and the boundary targets are computed through the camera from it.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..cameras import Equirectangular
from ..geometry.rotations import UPRIGHT_TO_WORLD
from .layout_sample import (CAMERA_HEIGHT_RANGE, MAX_WALLS, check_room, check_room_units, pad_corners,
                            polygon_from_corners_cam)
from .layout_targets import boundary_targets, corner_heat
from .readers import array_to_tensor, read_rgb_array
from .validate import DataValidationError, check_label_cor, read_text


def read_label_cor(path: str | Path, width: int | None = None, height: int | None = None,
                   min_corners: int = 3) -> np.ndarray:
    """``(2K, 2)`` float array of ``x y`` rows; a clear error names the file and the bad line.

    With ``width``/``height`` (the image's stored size) the corners are also checked by
    :func:`omnidl.data.validate.check_label_cor`: finite, on the image (``-0.5 <= x < width``,
    ``-0.5 <= y < height``; never wrapped), ceiling above floor, at least ``min_corners`` corners."""
    path = Path(path)
    rows = []
    for i, line in enumerate(read_text(path, "label_cor").splitlines(), 1):
        if not line.strip():
            continue
        parts = line.split()
        if len(parts) != 2:
            raise DataValidationError(f"{path}:{i}: expected 'x y', got {line!r}")
        try:
            rows.append((float(parts[0]), float(parts[1])))
        except ValueError as e:
            raise DataValidationError(f"{path}:{i}: not numbers: {line!r}") from e
    arr = np.asarray(rows, float).reshape(-1, 2)
    if len(arr) % 2:
        raise DataValidationError(f"{path}: {len(arr)} points; label_cor needs ceiling/floor pairs (an even count)")
    if width is not None and height is not None:
        check_label_cor(arr, path, width, height, min_corners)
    return arr


def check_camera_height(camera_height: float, what: str) -> float:
    """An assumed camera height (a setting, metres) in :data:`~omnidl.data.layout_sample.CAMERA_HEIGHT_RANGE`."""
    lo, hi = CAMERA_HEIGHT_RANGE
    if not (np.isfinite(camera_height) and lo <= camera_height <= hi):
        raise ValueError(f"{what}: camera_height={camera_height}; expected {lo:g}..{hi:g} metres above the floor "
                         "(a height in centimetres?)")
    return float(camera_height)


def room_from_label_cor(cor: np.ndarray, path: str | Path, width: int, height: int, camera_height: float = 1.6
                        ) -> np.ndarray:
    """Camera-frame corners ``(K, 2, 3)`` of a central panorama's checked ``label_cor``, with the room checked as
    every layout adapter checks it (:func:`~omnidl.data.layout_sample.check_room`: corners in wall order, none
    twice, the camera inside; :func:`~omnidl.data.layout_sample.check_room_units`); errors name ``path``."""
    try:
        cc = corners_from_label_cor(cor, width, height, camera_height)
    except ValueError as e:
        raise DataValidationError(f"{path}: {e}") from e
    poly = check_room(polygon_from_corners_cam(cc), path, "label_cor (top view of the floor corners)")
    check_room_units(poly, camera_height, float(-cc[0, 0, 1]), path, "label_cor room")   # camera y is down
    return cc


def write_label_cor(path: str | Path, cor: np.ndarray) -> None:
    """Write ``(2K, 2)`` corners atomically (2 decimals)."""
    from ..utils.io import atomic_write_text
    atomic_write_text(path, "".join(f"{x:.2f} {y:.2f}\n" for x, y in np.asarray(cor, float)))


def corners_from_label_cor(cor: np.ndarray, width: int, height: int, camera_height: float = 1.6) -> np.ndarray:
    """Camera-frame 3D corners ``(K, 2, 3)`` of a *central* panorama's ``label_cor`` (ceiling/floor pairs).

    Floor corners are put on the plane ``camera_height`` below the camera; the ceiling height is the
    mean over corners of the height at which each ceiling pixel meets its floor corner's vertical.
    """
    c = np.asarray(cor, float).reshape(-1, 2, 2)
    lon, lat = (a.numpy() for a in Equirectangular(width=width, height=height).uv_to_lonlat(torch.from_numpy(c + 0.5)))
    if np.any(lat[:, 1] >= 0) or np.any(lat[:, 0] <= 0):
        raise ValueError("label_cor: every ceiling point must be above and every floor point below the horizon")
    r = camera_height / np.tan(-lat[:, 1])                        # horizontal distance of the floor corner
    h_c = float(np.mean(r * np.tan(lat[:, 0])))
    lon_k = lon[:, 1]
    xy = np.stack([r * np.sin(lon_k), r * np.cos(lon_k)], -1)
    out = np.zeros((len(c), 2, 3))
    out[:, :, :2] = xy[:, None]
    out[:, 0, 2], out[:, 1, 2] = h_c, -camera_height
    return out @ np.asarray(UPRIGHT_TO_WORLD)                      # layout -> camera frame (R^T on the right)


#: sub-folder names of each split (HorizonNet's ``{train,valid,test}/``; ``val/`` accepted too)
SPLIT_DIRS = {"train": ("train",), "val": ("valid", "val"), "test": ("test",)}


def split_root(root: Path, split: str | None, what: str) -> Path:
    """``root`` itself for ``split=None``, else its split sub-folder (:data:`SPLIT_DIRS`); a clear error lists
    the folders looked for."""
    if split is None:
        return root
    from .splits import check_split_name
    check_split_name(split, what)
    cands = [root / d for d in SPLIT_DIRS[split]]
    for c in cands:
        if c.is_dir():
            return c
    raise FileNotFoundError(f"{what}: no folder for split {split!r} in {root} (looked for "
                            f"{[str(c) for c in cands]}); use data.split=null for a folder without splits")


class HorizonNetFolderDataset(torch.utils.data.Dataset):
    """``root/img/NAME.{png,jpg}`` + ``root/label_cor/NAME.txt`` -> layout samples (central panoramas).

    With ``split`` the folder is HorizonNet's ``root/{train,valid,test}/{img,label_cor}`` (MatterportLayout,
    PanoContext / Stanford2D-3D as HorizonNet ships them; ``val/`` is accepted for ``valid/``).

    Every sample is validated (:mod:`omnidl.data.validate`): an unreadable image or an invalid ``label_cor``
    (a point outside the image, NaN, ceiling below floor, ceiling and floor in different columns, a corner listed
    twice, fewer than 3 corners, corners out of wall order, a room not around the camera or over 100 m) raises a
    :class:`~omnidl.data.robust.CorruptSampleError` naming the file (skipped with a warning in training).

    Keys (the standard layout sample, :mod:`omnidl.data.layout_sample`): ``image (3,H,W)``, ``boundary (2,W)``
    rows, ``boundary_valid``, ``corner_heat (1,W)``, ``corners_cam (max_walls,2,3)`` zero-padded (up to the
    assumed ``camera_height``) with ``num_walls`` real ones, ``camera_height ()``, ``meta``.
    """

    def __init__(self, root: str | Path, width: int | None = None, height: int | None = None,
                 camera_height: float = 1.6, split: str | None = None, max_walls: int = MAX_WALLS,
                 max_samples: int | None = None) -> None:
        check_camera_height(camera_height, "HorizonNetFolderDataset")                # settings first
        self.root = split_root(Path(root).expanduser(), split, "HorizonNetFolderDataset")
        img_dir, lab_dir = self.root / "img", self.root / "label_cor"
        if not img_dir.is_dir() or not lab_dir.is_dir():
            raise FileNotFoundError(f"HorizonNet folder {self.root}: needs img/ and label_cor/ sub-folders")
        self.items = []
        for p in sorted(img_dir.iterdir()):
            if p.suffix.lower() in (".png", ".jpg", ".jpeg"):
                lab = lab_dir / f"{p.stem}.txt"
                if not lab.exists():
                    raise FileNotFoundError(f"{p}: no label file {lab}")
                self.items.append((p, lab))
        if not self.items:
            raise FileNotFoundError(f"HorizonNet folder {self.root}: no images in {img_dir}")
        if max_samples:
            self.items = self.items[: int(max_samples)]
        self.width, self.height, self.camera_height = width, height, float(camera_height)
        self.max_walls = int(max_walls)
        self.camera = Equirectangular(width=width, height=height) if width and height else None

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> dict:
        p, lab = self.items[i]
        rgb = read_rgb_array(p, "image")                                 # the reading policy; unreadable -> named error
        H0, W0 = rgb.shape[:2]
        W, H = self.width or W0, self.height or H0
        img = array_to_tensor(rgb, (W, H))
        cor = read_label_cor(lab, W0, H0) * np.array([W / W0, H / H0])
        cc = room_from_label_cor(cor, lab, W, H, self.camera_height)
        padded = pad_corners(cc, self.max_walls, lab)
        cam = Equirectangular(width=W, height=H)
        rows, valid = boundary_targets(cc, cam)
        return {"image": img, "boundary": rows, "boundary_valid": valid,
                "corner_heat": corner_heat(cor[0::2, 0] + 0.5, W), "corners_cam": padded,
                "num_walls": torch.tensor(len(cc)), "camera_height": torch.tensor(self.camera_height),
                "meta": {"name": p.stem, "file": str(p), "label_file": str(lab), "rig_radius": 0.0,
                         "camera": cam.to_config()}}
