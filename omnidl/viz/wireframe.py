"""3-D line segments drawn over an image through its camera (e.g. a room layout's wireframe on a panorama).

Each segment is sampled densely along its 3-D extent and projected with ``camera.project``, so straight
room edges appear as the curves the camera really sees; pieces are broken where a projection is invalid
or, for a 360° panorama, where they cross the seam.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor


def draw_segments_3d(image: Tensor, segments: Tensor | np.ndarray, camera, color: Sequence[float] = (0.0, 1.0, 0.0),
                     thickness: int | None = None, samples: int = 256) -> Tensor:
    """Draw 3-D segments over ``image``.

    Args:
        image: ``(3, H, W)`` RGB in [0, 1], the camera's image size.
        segments: ``(E, 2, 3)`` end points in the camera frame (OpenCV, metres or any unit).
        camera: an :class:`omnidl.cameras.Camera` of size ``W x H``.
        color: RGB in [0, 1]; thickness: pixels (default ``max(1, H // 256)``).
    Returns:
        ``(3, H, W)`` new image in [0, 1].
    """
    import cv2
    img = image.detach().float().cpu().clamp(0, 1)
    H, W = img.shape[-2:]
    if (camera.width, camera.height) != (W, H):
        raise ValueError(f"draw_segments_3d: camera is {camera.width}x{camera.height} but the image is {W}x{H}")
    seg = torch.as_tensor(np.asarray(segments, dtype=np.float64) if not isinstance(segments, Tensor) else segments,
                          dtype=torch.float64)
    if seg.dim() != 3 or seg.shape[1:] != (2, 3):
        raise ValueError(f"draw_segments_3d: segments must be (E, 2, 3), got {tuple(seg.shape)}")
    canvas = np.ascontiguousarray((img.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8))
    if len(seg) == 0:
        return img
    t = torch.linspace(0, 1, samples, dtype=torch.float64)[None, :, None]
    pts = seg[:, :1] * (1 - t) + seg[:, 1:] * t                            # (E, S, 3)
    uv, valid = camera.project(pts)
    uv, valid = uv.numpy(), valid.numpy() & np.isfinite(uv.numpy()).all(-1)
    wraps = bool(getattr(camera, "wraps_horizontally", False))
    th = int(thickness or max(1, H // 256))
    col = tuple(int(round(c * 255)) for c in color)
    shift = 4
    for e in range(len(seg)):
        run: list[np.ndarray] = []
        for s in range(samples):
            if not valid[e, s] or (run and wraps and abs(uv[e, s, 0] - run[-1][0]) > W / 2):
                if len(run) > 1:
                    cv2.polylines(canvas, [(np.array(run) * (1 << shift)).round().astype(np.int32)], False, col, th,
                                  cv2.LINE_AA, shift)
                run = []
            if valid[e, s]:
                run.append(uv[e, s] - 0.5)   # pixel centres are at j + 0.5
        if len(run) > 1:
            cv2.polylines(canvas, [(np.array(run) * (1 << shift)).round().astype(np.int32)], False, col, th,
                          cv2.LINE_AA, shift)
    return torch.from_numpy(canvas).permute(2, 0, 1).float() / 255


def box_edges(floor: np.ndarray, ceiling: np.ndarray) -> np.ndarray:
    """Wireframe of a prism room: ``floor, ceiling (N, 3)`` corners in order -> ``(3N, 2, 3)`` segments
    (floor edges, ceiling edges, vertical wall edges)."""
    floor, ceiling = np.asarray(floor, float), np.asarray(ceiling, float)
    nf, nc = np.roll(floor, -1, 0), np.roll(ceiling, -1, 0)
    return np.concatenate([np.stack([floor, nf], 1), np.stack([ceiling, nc], 1), np.stack([floor, ceiling], 1)], 0)
