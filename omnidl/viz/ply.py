"""Coloured point clouds as PLY files (binary little-endian, written atomically).

Frames. :func:`depth_to_points` returns points in the **camera frame** (OpenCV: x right, y down,
z forward) unless ``frame="gravity_y_up"``. :func:`write_ply` files written by omnidl's commands
(``omnidl predict``, ``evaluate.py``) use the **gravity-aligned y-up frame** so that viewers (MeshLab,
CloudCompare, Blender's PLY import with "Y up", three.js) show rooms upright:

* origin at the camera centre, metres;
* ``+y`` points up, against gravity (the upright camera's ``-y``);
* ``+x`` is the upright camera's right, ``-z`` its forward viewing direction (the centre column of an
  upright panorama), i.e. the OpenGL convention: ``p_yup = diag(1, -1, -1) @ R_up_cam @ p_cam``;
* ``R_up_cam`` is the camera's tilt (camera frame -> the upright camera frame with the same heading,
  :mod:`omnidl.geometry.rotations`); identity for an upright panorama. The frame is written in the
  file's header as a ``comment frame ...`` line.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from omnidl.utils.io import atomic_write_bytes


#: OpenCV camera axes (x right, y down, z forward) -> the y-up, -z-forward viewer frame
CAM_TO_Y_UP = ((1.0, 0.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, -1.0))
FRAME_COMMENT = {
    "camera": "frame camera (OpenCV: x right, y down, z forward), metres",
    "gravity_y_up": "frame gravity_y_up (y up against gravity, x right, -z forward = panorama centre column), metres",
}


def to_gravity_y_up(points: torch.Tensor, R_up_cam: torch.Tensor | None = None) -> torch.Tensor:
    """Camera-frame ``points (N, 3)`` -> the gravity-aligned y-up frame (module docstring):
    ``diag(1, -1, -1) @ R_up_cam @ p``. ``R_up_cam (3, 3)`` is the camera tilt (None: upright)."""
    M = torch.tensor(CAM_TO_Y_UP, dtype=points.dtype, device=points.device)
    if R_up_cam is not None:
        R = torch.as_tensor(R_up_cam, dtype=points.dtype, device=points.device)
        if R.shape != (3, 3):
            raise ValueError(f"R_up_cam must be (3, 3), got {tuple(R.shape)}")
        M = M @ R
    return points @ M.T


def depth_to_points(depth: torch.Tensor, camera, image: torch.Tensor | None = None, frame: str = "camera",
                    R_up_cam: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Back-project a range map through ``camera.unproject``.

    Args:
        depth: ``(H, W)`` or ``(1, H, W)`` range along each pixel's ray (m); 0/non-finite = invalid.
        camera: an :class:`omnidl.cameras.Camera` of the same ``H x W`` (resize it with ``camera.resized``).
        image: optional ``(3, H, W)`` colours in [0, 1].
        frame: ``"camera"`` (OpenCV, y down) or ``"gravity_y_up"`` (see the module docstring).
        R_up_cam: ``(3, 3)`` camera tilt for ``gravity_y_up`` (None: the camera is upright).
    Returns:
        ``points (N, 3)`` metres in ``frame`` and ``colors (N, 3)`` (or None) of the valid pixels.
    """
    if frame not in FRAME_COMMENT:
        raise ValueError(f"depth_to_points: frame must be one of {sorted(FRAME_COMMENT)}, got {frame!r}")
    d = depth.detach().reshape(depth.shape[-2:]).double().cpu()
    h, w = d.shape
    if (camera.width, camera.height) != (w, h):
        raise ValueError(f"camera is {camera.width}x{camera.height} but the depth map is {w}x{h}")
    rays = camera.unproject_grid(dtype=torch.float64)
    pts = rays.at(d)
    valid = rays.valid & torch.isfinite(d) & (d > 0)
    cols = None
    if image is not None:
        cols = image.detach().double().cpu().permute(1, 2, 0)[valid]
    pts = pts[valid]
    if frame == "gravity_y_up":
        pts = to_gravity_y_up(pts, None if R_up_cam is None else torch.as_tensor(R_up_cam, dtype=pts.dtype))
    return pts.float(), (cols.float() if cols is not None else None)


def write_ply(path: str | Path, points: torch.Tensor | np.ndarray, colors: torch.Tensor | np.ndarray | None = None,
              frame: str | None = None) -> Path:
    """Write ``points (N, 3)`` (float) and optional ``colors (N, 3)`` ([0, 1] floats or uint8) as binary PLY.

    ``frame`` (``"camera"`` or ``"gravity_y_up"``, see the module docstring) is recorded as a header comment."""
    pts = np.asarray(points.detach().cpu() if isinstance(points, torch.Tensor) else points, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {pts.shape}")
    if frame is not None and frame not in FRAME_COMMENT:
        raise ValueError(f"write_ply: frame must be one of {sorted(FRAME_COMMENT)}, got {frame!r}")
    header = ["ply", "format binary_little_endian 1.0"] + ([f"comment {FRAME_COMMENT[frame]}"] if frame else []) + [
              f"element vertex {len(pts)}",
              "property float x", "property float y", "property float z"]
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colors is not None:
        c = np.asarray(colors.detach().cpu() if isinstance(colors, torch.Tensor) else colors)
        if c.shape != pts.shape:
            raise ValueError(f"colors must have the shape of points {pts.shape}, got {c.shape}")
        if c.dtype != np.uint8:
            c = (np.clip(c, 0, 1) * 255).round().astype(np.uint8)
        header += ["property uchar red", "property uchar green", "property uchar blue"]
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    header.append("end_header")
    rec = np.empty(len(pts), dtype=fields)
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    if colors is not None:
        rec["red"], rec["green"], rec["blue"] = c[:, 0], c[:, 1], c[:, 2]
    data = ("\n".join(header) + "\n").encode("ascii") + rec.tobytes()
    return atomic_write_bytes(path, data)


def ply_frame(path: str | Path) -> str | None:
    """The frame name recorded in a PLY header by :func:`write_ply` (None when absent)."""
    raw = Path(path).read_bytes()[:4096]
    for line in raw.split(b"end_header")[0].decode("ascii", "replace").splitlines():
        if line.startswith("comment frame "):
            return line.split()[2]
    return None


def read_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Read a PLY written by :func:`write_ply` (for tests and tools): ``(points (N,3), colors (N,3) uint8 | None)``."""
    raw = Path(path).read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    lines = raw[:end].decode("ascii").splitlines()
    n = int(next(line for line in lines if line.startswith("element vertex")).split()[-1])
    has_color = any(line.startswith("property") and line.split()[-1] == "red" for line in lines)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")] + ([("red", "u1"), ("green", "u1"), ("blue", "u1")]
                                                            if has_color else [])
    rec = np.frombuffer(raw[end:], dtype=fields, count=n)
    pts = np.stack([rec["x"], rec["y"], rec["z"]], 1)
    cols = np.stack([rec["red"], rec["green"], rec["blue"]], 1) if has_color else None
    return pts, cols
