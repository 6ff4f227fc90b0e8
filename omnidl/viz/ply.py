"""Coloured point clouds as PLY files (binary little-endian, written atomically)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from omnidl.utils.io import atomic_write_bytes


def depth_to_points(depth: torch.Tensor, camera, image: torch.Tensor | None = None
                    ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Back-project a range map through ``camera.unproject``.

    Args:
        depth: ``(H, W)`` or ``(1, H, W)`` range along each pixel's ray (m); 0/non-finite = invalid.
        camera: an :class:`omnidl.cameras.Camera` of the same ``H x W`` (resize it with ``camera.resized``).
        image: optional ``(3, H, W)`` colours in [0, 1].
    Returns:
        ``points (N, 3)`` camera-frame metres and ``colors (N, 3)`` (or None) of the valid pixels.
    """
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
    return pts[valid].float(), (cols.float() if cols is not None else None)


def write_ply(path: str | Path, points: torch.Tensor | np.ndarray, colors: torch.Tensor | np.ndarray | None = None
              ) -> Path:
    """Write ``points (N, 3)`` (float) and optional ``colors (N, 3)`` ([0, 1] floats or uint8) as binary PLY."""
    pts = np.asarray(points.detach().cpu() if isinstance(points, torch.Tensor) else points, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {pts.shape}")
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(pts)}",
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


def read_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Read a PLY written by :func:`write_ply` (for tests and tools): ``(points (N,3), colors (N,3) uint8 | None)``."""
    raw = Path(path).read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    lines = raw[:end].decode("ascii").splitlines()
    n = int(next(line for line in lines if line.startswith("element vertex")).split()[-1])
    has_color = any("red" in line for line in lines)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")] + ([("red", "u1"), ("green", "u1"), ("blue", "u1")]
                                                            if has_color else [])
    rec = np.frombuffer(raw[end:], dtype=fields, count=n)
    pts = np.stack([rec["x"], rec["y"], rec["z"]], 1)
    cols = np.stack([rec["red"], rec["green"], rec["blue"]], 1) if has_color else None
    return pts, cols
