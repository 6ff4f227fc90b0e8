"""Loader of the Non-Central Indoor Dataset (thesis §5.5; ``docs/design.md#non-central-indoor-dataset``).

Layout of ``root``: ``img/NAME.png`` (1024x512 RGB), ``depth_coded/NAME.png`` (24-bit fixed point,
``d = (R/255 + G/255^2 + B/255^3) * 10`` m, RGB on disk), ``EM_gt/NAME.png`` (edge map),
``DataPython/{3D_gt,cam_pose,label_ang}/NAME.npy`` and ``DataPython/label_cor/NAME.txt``.

Frame adapter (explicit). The dataset's azimuth *decreases* with the column: column ``x`` looks along
``theta = pi - 2 pi (x + 0.5) / W`` in its right-handed z-up frame (x = camera heading, y = left),
whereas omnidl's longitude ``lon = 2 pi (x + 0.5) / W - pi = -theta`` increases. Points map to omnidl's
layout frame as ``(x_l, y_l, z_l) = (-y_d, x_d, z_d)`` (:func:`dataset_to_layout`), and to the OpenCV
camera frame through ``UPRIGHT_TO_WORLD^T`` (:mod:`omnidl.geometry.rotations`). The image columns need no flip.

Sample keys (as the data engine, ``docs/synth.md``): ``image``, ``depth`` (range along the ray from the
column's optical centre, as decoded; 0 = invalid), ``boundary (2,W)`` rows + ``boundary_valid`` (from
``label_ang``, or ``EM_gt`` with ``boundary_source="edges"``, or the 3D corners through the camera with
``"corners"``), ``corner_heat (1,W)`` from ``label_cor``, ``corners_cam (max_walls,2,3)`` (``3D_gt - cam_pose``, zero-padded so batches collate),
``num_walls`` (the real corners), ``edges (1,H,W)``, ``meta`` (``name``, ``rig_radius``).

Splits (``split``): a sub-folder ``root/{train,valid|val,test}/`` holding the folders above (as
``python -m omnidl.apps.synth --format noncentral --split S --out root/S`` writes them), else a list of names
``root/split/{split}.txt`` (or ``root/{split}.txt``; one name per line; the release's ``ScaledLayoutsSplit.pkl``
is a pickle and is not read: write its names into such a list), else ``split_file``.
``Rc``: the ``rc`` argument, else parsed from names like ``..._R06585`` (0.6585 m), else an error.
"""
from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..cameras import Equirectangular
from ..geometry.rotations import UPRIGHT_TO_WORLD
from .horizonnet_format import SPLIT_DIRS, check_camera_height, read_label_cor
from .layout_sample import MAX_WALLS, check_room, check_room_units, pad_corners, polygon_from_corners_cam
from .layout_targets import boundary_targets, corner_heat
from .readers import array_to_tensor, read_rgb_array
from .splits import check_relative_path, check_split_name, find_split_file, read_split_list
from .validate import DataValidationError, UnreadableFileError, check_range, invalid, load_npy, read_image

DEPTH_MAX = 10.0
SPLIT_PATTERNS = ("split/{split}.txt", "{split}.txt")


def decode_depth(rgb: np.ndarray, d_max: float = DEPTH_MAX) -> np.ndarray:
    """24-bit fixed-point depth ``(H, W, 3)`` uint8 RGB -> metres ``(H, W)`` float32."""
    c = rgb.astype(np.float64)
    return ((c[..., 0] / 255 + c[..., 1] / 255 ** 2 + c[..., 2] / 255 ** 3) * d_max).astype(np.float32)


def dataset_to_layout(points: np.ndarray) -> np.ndarray:
    """Dataset frame ``(..., 3)`` (x heading, y left, z up; azimuth decreasing with the column) -> layout frame."""
    p = np.asarray(points, float)
    return np.stack([-p[..., 1], p[..., 0], p[..., 2]], -1)


def rc_from_name(name: str) -> float | None:
    """``'A23_R06585'`` -> 0.6585 (scaledLayout's naming); ``None`` if the name carries no radius."""
    m = re.search(r"_R(\d{5})(?:\D|$)", name)
    return int(m.group(1)) / 1e4 if m else None


def corners_from_label_cor_camera(cor: np.ndarray, camera: Any, camera_height: float = 1.6) -> np.ndarray:
    """Camera-frame 3D corners ``(K, 2, 3)`` of ``label_cor`` pixels ``(2K, 2)`` through any panorama camera
    (central or non-central): each floor pixel's ray meets the floor plane ``camera_height`` below the rig,
    each ceiling pixel's ray the vertical line of its floor corner; the ceiling height is their mean.
    Raises ``ValueError`` when a floor ray does not go down or a ceiling ray does not go up."""
    c = np.asarray(cor, float).reshape(-1, 2, 2)
    rays = camera.unproject(torch.from_numpy(c.reshape(-1, 2) + 0.5))
    R = np.asarray(UPRIGHT_TO_WORLD, dtype=np.float64)
    o = (rays.origin.double().numpy() @ R.T).reshape(-1, 2, 3)          # camera -> layout frame (z up)
    d = (rays.direction.double().numpy() @ R.T).reshape(-1, 2, 3)
    if np.any(d[:, 1, 2] >= 0) or np.any(d[:, 0, 2] <= 0):
        raise ValueError("label_cor: every ceiling point must be above and every floor point below the horizon")
    t = (-camera_height - o[:, 1, 2]) / d[:, 1, 2]
    floor_xy = o[:, 1, :2] + t[:, None] * d[:, 1, :2]
    b = d[:, 0, :2]
    s_c = np.sum((floor_xy - o[:, 0, :2]) * b, 1) / np.maximum(np.sum(b * b, 1), 1e-12)
    h_c = float(np.mean(o[:, 0, 2] + s_c * d[:, 0, 2]))
    out = np.zeros((len(c), 2, 3))
    out[:, :, :2] = floor_xy[:, None]
    out[:, 0, 2], out[:, 1, 2] = h_c, -camera_height
    return out @ R                                                      # layout -> camera frame


class NonCentralIndoorDataset(torch.utils.data.Dataset):
    """Map-style dataset over ``root`` (see module docstring).

    Args:
        root: dataset folder.
        names: sample names to use (default: every ``img/*.png``), e.g. a split list.
        rc: rig radius in metres (default: from the file name, else error).
        boundary_source: ``"label_ang"`` | ``"edges"`` (EM_gt, as scaledLayout) | ``"corners"`` (3D_gt through
            the camera) | ``"label_cor"`` (the corner pixels through the camera, up to ``camera_height``).
        depth: also decode ``depth_coded``.
        label_cor_only: read only ``img/`` and ``label_cor`` (``DataPython/label_cor/`` or ``label_cor/``):
            the other folders are optional and not read; boundaries and ``corners_cam`` come from ``label_cor``
            (``boundary_source="label_cor"``, metric up to the assumed ``camera_height``); no ``depth``/``edges``.
        camera_height: assumed camera height (m) of the ``label_cor`` reconstruction.
        split: ``train`` / ``val`` / ``test`` (module docstring) or ``None`` (every image of ``root``).
        split_file: explicit list of names (overrides ``split``'s search; ``names`` overrides both).
        width, height: the expected image size (the network's input; the images are not resized): another
            size is an error naming the file. ``None`` accepts any size.
        max_walls: padding of ``corners_cam``; max_samples: keep the first N samples (quick runs).

    Every file is validated (:mod:`omnidl.data.validate`): sizes against the image, ``depth_coded`` 24-bit
    RGB (a grayscale one is refused), finite ``3D_gt``/``cam_pose``/``label_ang`` of the documented shapes,
    ``label_cor`` inside the image with each corner's ceiling and floor in one column and no corner twice, the same
    number of corners in ``label_cor`` and ``3D_gt``, the room's floor polygon simple and around the rig
    (:func:`~omnidl.data.layout_sample.check_room`) and in metres (camera 0.3..5 m above the floor, room at most
    100 m across; :func:`~omnidl.data.layout_sample.check_room_units`). A bad file raises a :class:`~omnidl.data.robust.CorruptSampleError` naming
    it (skipped with a warning in training).
    """

    def __init__(self, root: str | Path, names: list[str] | None = None, rc: float | None = None,
                 boundary_source: str = "label_ang", depth: bool = True, label_cor_only: bool = False,
                 camera_height: float = 1.6, split: str | None = None, split_file: str | Path | None = None,
                 width: int | None = None, height: int | None = None, max_walls: int = MAX_WALLS,
                 max_samples: int | None = None) -> None:
        self.root = Path(root).expanduser()
        if names is not None:
            pass                                                        # an explicit list wins
        elif split_file is not None:
            names = read_split_list(split_file)
        elif split is not None:
            check_split_name(split, "NonCentralIndoorDataset")
            sub = next((self.root / d for d in SPLIT_DIRS[split] if (self.root / d / "img").is_dir()), None)
            if sub is not None:
                self.root = sub
            else:
                names = read_split_list(find_split_file(self.root, split, SPLIT_PATTERNS, "NonCentralIndoorDataset"))
        if boundary_source not in ("label_ang", "edges", "corners", "label_cor"):
            raise ValueError(f"boundary_source must be label_ang, edges, corners or label_cor, got {boundary_source!r}")
        check_camera_height(camera_height, "NonCentralIndoorDataset")
        img_dir = self.root / "img"
        if not img_dir.is_dir():
            raise FileNotFoundError(f"NonCentralIndoorDataset: {img_dir} not found")
        self.names = list(names) if names is not None else sorted(p.stem for p in img_dir.glob("*.png"))
        for m in self.names:
            check_relative_path(m, f"NonCentralIndoorDataset names of {self.root}")
        if not self.names:
            raise FileNotFoundError(f"NonCentralIndoorDataset: no images in {img_dir}")
        lost = [m for m in self.names if not (img_dir / f"{m}.png").is_file()]
        if lost:
            raise FileNotFoundError(f"NonCentralIndoorDataset: {len(lost)} listed name(s) have no image in {img_dir}: "
                                    f"{lost[:10]} (expected {img_dir}/<name>.png)")
        if max_samples:
            self.names = self.names[: int(max_samples)]
        self.size = (int(width), int(height)) if width and height else None
        self.max_walls = int(max_walls)
        self.label_cor_only = bool(label_cor_only)
        if self.label_cor_only:
            boundary_source, depth = "label_cor", False
            if not any((self.root / d).is_dir() for d in ("DataPython/label_cor", "label_cor")):
                raise FileNotFoundError(f"NonCentralIndoorDataset: {self.root} has no DataPython/label_cor/ or "
                                        "label_cor/ folder (label_cor_only=True needs one)")
        self.rc, self.boundary_source, self.depth = rc, boundary_source, depth
        self.camera_height = float(camera_height)

    def __len__(self) -> int:
        return len(self.names)

    def _rc(self, name: str) -> float:
        rc = self.rc if self.rc is not None else rc_from_name(name)
        if rc is None:
            raise ValueError(f"NonCentralIndoorDataset: no rig radius for {name!r}: set rc= (data.rc) or use names "
                             "with '_R<5 digits>' (e.g. _R10000 for 1 m)")
        return float(rc)

    def _file(self, *parts: str) -> Path:
        p = self.root.joinpath(*parts)
        if not p.exists():
            raise UnreadableFileError(f"NonCentralIndoorDataset: missing file {p}")
        return p

    def _label_cor_file(self, name: str) -> Path:
        for d in (("DataPython", "label_cor"), ("label_cor",)):
            p = self.root.joinpath(*d, f"{name}.txt")
            if p.exists():
                return p
        return self._file("DataPython", "label_cor", f"{name}.txt")

    def __getitem__(self, i: int) -> dict:
        from ..cameras import build
        name = self.names[i]
        img_path = self._file("img", f"{name}.png")
        rgb = read_rgb_array(img_path, "image")                 # the reading policy; unreadable -> named error
        H, W = rgb.shape[:2]
        if self.size is not None and (W, H) != self.size:
            raise invalid(img_path, "image", f"{W}x{H}", f"{self.size[0]}x{self.size[1]} (data.width x data.height; "
                          "non-central panoramas are not resized: set them to the images' size)")
        rc = self._rc(name)
        cam = build({"type": "noncentral_pano", "width": W, "height": H, "rc": rc})
        out: dict[str, Any] = {"image": array_to_tensor(rgb)}
        if self.depth:
            path = self._file("depth_coded", f"{name}.png")
            coded = read_image(path, "depth_coded", channels=3, dtypes=(np.uint8,), size=(W, H), convert=False)
            out["depth"] = torch.from_numpy(decode_depth(coded))[None]
        cor_path = self._label_cor_file(name)
        cor = read_label_cor(cor_path, W, H)
        if self.label_cor_only or self.boundary_source == "label_cor":
            try:
                corners_cam = corners_from_label_cor_camera(cor, cam, self.camera_height)
            except ValueError as e:
                raise DataValidationError(f"{cor_path}: {e}") from e
            n, n_src = len(corners_cam), None
        else:
            gt_path = self._file("DataPython", "3D_gt", f"{name}.npy")
            gt = load_npy(gt_path, "3D_gt", shape=(None, 3))
            if len(gt) % 2 or len(gt) == 0:
                raise invalid(gt_path, "3D_gt", f"of shape {gt.shape}", "shape (2N, 3): N ceiling then N floor corners")
            pose = load_npy(self._file("DataPython", "cam_pose", f"{name}.npy"), "cam_pose").reshape(-1)
            if pose.size != 3:
                raise invalid(self.root / "DataPython" / "cam_pose" / f"{name}.npy", "cam_pose",
                              f"{pose.size} values", "3 values (x, y, z of the camera)")
            n, n_src = len(gt) // 2, gt_path
            if len(cor) // 2 > n:
                raise invalid(cor_path, "label_cor", f"{len(cor) // 2} corners", f"at most the {n} corners of "
                              f"{gt_path.name} (3D_gt; label_cor lists the visible ones): the files of one sample "
                              "must describe the same room")
            lay = dataset_to_layout(gt - pose.reshape(1, 3))
            corners = np.stack([lay[:n], lay[n:]], 1)                  # (N, 2, 3) layout frame
            corners_cam = corners @ np.asarray(UPRIGHT_TO_WORLD)         # -> OpenCV camera frame (R^T)
        src = cor_path if n_src is None else n_src
        poly = check_room(polygon_from_corners_cam(corners_cam), src, "room (top view of the floor corners)")
        check_room_units(poly, float(corners_cam[:, 1, 1].mean()), float(-corners_cam[:, 0, 1].mean()), src,
                         "room")                                        # camera frame: y is down
        out["corners_cam"] = pad_corners(corners_cam, self.max_walls, cor_path if n_src is None else n_src)
        out["num_walls"] = torch.tensor(n)
        out["corner_heat"] = corner_heat(cor[0::2, 0] + 0.5, W)
        em = None
        if not self.label_cor_only:
            em_path = self._file("EM_gt", f"{name}.png")
            em = read_image(em_path, "EM_gt", channels=1, dtypes=(np.uint8,), size=(W, H)) >= 250
            out["edges"] = torch.from_numpy(em.astype(np.float32))[None]
        if self.boundary_source == "label_ang":
            ang_path = self._file("DataPython", "label_ang", f"{name}.npy")
            ang = load_npy(ang_path, "label_ang", shape=(3, None))
            check_range(ang[1:], ang_path, "label_ang elevation", -math.pi / 2, math.pi / 2)
            out["boundary"], out["boundary_valid"] = self._from_label_ang(ang, W, H, name)
        elif self.boundary_source == "edges":
            out["boundary"], out["boundary_valid"] = self._from_edges(em)
        else:
            out["boundary"], out["boundary_valid"] = boundary_targets(corners_cam, cam)
        out["meta"] = {"name": name, "file": str(img_path), "rig_radius": rc, "camera": cam.to_config()}
        return out
    @staticmethod
    def _from_label_ang(ang: np.ndarray, W: int, H: int, name: str):
        if ang.ndim != 2 or ang.shape[0] != 3:
            raise ValueError(f"{name}: label_ang must be (3, K) (azimuth, ceiling, floor elevations), got {ang.shape}")
        lon = -ang[0]                                                    # the dataset's azimuth runs opposite
        order = np.argsort(lon)
        pano = Equirectangular(width=W, height=H)                        # the dataset's pixel <-> angle map
        u = torch.arange(W, dtype=torch.float64) + 0.5
        lon_u = pano.uv_to_lonlat(torch.stack([u, torch.zeros_like(u)], -1))[0].numpy()
        rows, valid = [], []
        for k in (1, 2):
            el = ang[k][order]
            seen = el != 0                                               # 0 = boundary not seen
            e = np.interp(lon_u, lon[order], el, period=2 * math.pi)
            ok = np.interp(lon_u, lon[order], seen.astype(float), period=2 * math.pi) > 0.999
            rows.append(pano.lonlat_to_uv(torch.from_numpy(lon_u), torch.from_numpy(e))[:, 1].numpy())
            valid.append(ok)
        rows, valid = np.stack(rows), np.stack(valid)
        return torch.from_numpy(np.where(valid, rows, -1.0)).float(), torch.from_numpy(valid)

    @staticmethod
    def _from_edges(edge: np.ndarray):
        """scaledLayout's rule: first white pixel from the top (upper half) / last from the bottom (lower half)."""
        H, W = edge.shape
        up, lo = edge[: H // 2], edge[H // 2:]
        has_c, has_f = up.any(0), lo.any(0)
        c = up.argmax(0) + 0.5
        f = H // 2 + (lo.shape[0] - 1 - lo[::-1].argmax(0)) + 0.5
        valid = np.stack([has_c, has_f])
        rows = np.where(valid, np.stack([c, f]), -1.0)
        return torch.from_numpy(rows).float(), torch.from_numpy(valid)
