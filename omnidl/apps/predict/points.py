"""Point-cloud size control of ``omnidl predict depth`` (``--voxel SIZE``, ``--max-points N``).

Both are deterministic (the same input gives the same file, byte for byte):

* ``--voxel SIZE`` (metres, > 0): one point per occupied cube of side ``SIZE`` on the grid anchored at the
  origin of the written frame: the mean of its points and of their colours (as Open3D's
  ``voxel_down_sample``); voxels are listed in lexicographic order of their integer coordinates.
* ``--max-points N`` (> 0): at most ``N`` points, applied after ``--voxel``: the points at indices
  ``floor(k * n / N)``, ``k = 0..N-1`` of the (pixel-ordered or voxel-ordered) list, an even stride through it.

Default (neither): every valid pixel is a point, as before these options existed (a 4096x2048 panorama writes
about 8.4 million points, ~126 MB).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass(frozen=True)
class CloudOptions:
    """``max_points``: 0 = no limit; ``voxel``: 0 = no voxel grid (metres otherwise)."""

    max_points: int = 0
    voxel: float = 0.0

    def __post_init__(self) -> None:
        if isinstance(self.max_points, bool) or not isinstance(self.max_points, int) or self.max_points < 0:
            raise ValueError(f"--max-points must be a whole number >= 0 (0: every point), got {self.max_points!r}")
        if not (isinstance(self.voxel, (int, float)) and math.isfinite(self.voxel) and self.voxel >= 0):
            raise ValueError(f"--voxel must be a finite size in metres >= 0 (0: off), got {self.voxel!r}")

    def to_dict(self) -> dict:
        return {"max_points": self.max_points or None, "voxel_m": self.voxel or None}


def voxel_downsample(points: Tensor, colors: Tensor | None, size: float) -> tuple[Tensor, Tensor | None]:
    """``points (N, 3)`` (+ ``colors (N, 3)``) -> one mean point (and colour) per occupied ``size`` voxel."""
    if len(points) == 0:
        return points, colors
    keys = torch.floor(points.double() / size).long()
    uniq, inv = torch.unique(keys, dim=0, return_inverse=True)          # sorted lexicographically
    n = len(uniq)
    count = torch.zeros(n, dtype=torch.float64).index_add_(0, inv, torch.ones(len(points), dtype=torch.float64))
    mean = torch.zeros(n, 3, dtype=torch.float64).index_add_(0, inv, points.double()) / count[:, None]
    cols = None
    if colors is not None:
        cols = (torch.zeros(n, 3, dtype=torch.float64).index_add_(0, inv, colors.double()) / count[:, None])
        cols = cols.to(colors.dtype)
    return mean.to(points.dtype), cols


def stride_subsample(points: Tensor, colors: Tensor | None, max_points: int) -> tuple[Tensor, Tensor | None]:
    """At most ``max_points`` of ``points (N, 3)``: indices ``floor(k N / max_points)`` (an even stride)."""
    n = len(points)
    if max_points <= 0 or n <= max_points:
        return points, colors
    idx = torch.div(torch.arange(max_points, dtype=torch.int64) * n, max_points, rounding_mode="floor")
    return points[idx], (colors[idx] if colors is not None else None)


def subsample(points: Tensor, colors: Tensor | None, options: CloudOptions) -> tuple[Tensor, Tensor | None]:
    """``--voxel`` then ``--max-points`` (see the module docstring)."""
    if options.voxel > 0:
        points, colors = voxel_downsample(points, colors, options.voxel)
    return stride_subsample(points, colors, options.max_points)
