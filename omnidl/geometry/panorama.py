"""Resampling 360° panoramas: reading one at arbitrary directions, rotating it (the rotated-panorama
augmentation of ch. 4, HoLiNet's training data and the stabilisation of ch. 6).

This is the one home of panorama resampling. Both functions take their geometry from the camera
(:class:`~omnidl.cameras.Equirectangular`: :func:`~omnidl.cameras.equirectangular.direction_to_lonlat`
and ``lonlat_to_uv``, or ``project``/``unproject_grid`` through :func:`~omnidl.geometry.warp.reproject`)
and sample with :func:`~omnidl.geometry.warp.sample_grid`, so the pixel convention (centres at
``j + 0.5``), the wrap across the seam (column ``W`` is column 0) and the clamped pole rows are the same
everywhere.
"""
from __future__ import annotations

import torch
from torch import Tensor

from omnidl.cameras.base import Camera
from omnidl.cameras.equirectangular import Equirectangular, direction_to_lonlat

from .warp import WarpGrid, reproject, sample_grid


def sample_panorama(image: Tensor, directions: Tensor, mode: str = "bilinear") -> Tensor:
    """Read a full 360° x 180° equirectangular ``image (B, C, H, W)`` at viewing directions.

    The hot path of the photometric gyroscopes (thousands of points per iteration): it skips the
    validity bookkeeping of ``project``, which is moot on the full sphere, and converts with the
    camera's own longitude/latitude functions.

    Args:
        image: panorama batch (floating for ``bilinear``; any dtype for ``nearest``).
        directions: ``(N, 3)`` (shared by the batch) or ``(B, N, 3)`` directions in the camera frame
            (OpenCV, any length).
        mode: ``"bilinear"`` or ``"nearest"``.

    Returns:
        ``(B, C, N)`` in the dtype of ``image``. Longitude wraps around, latitude is clamped at the poles
        (border rows). Differentiable w.r.t. the image (and the directions for ``bilinear``).
    """
    if image.dim() != 4:
        raise ValueError(f"image must have shape (B, C, H, W), got {tuple(image.shape)}")
    if directions.shape[-1] != 3 or directions.dim() not in (2, 3):
        raise ValueError(f"directions must have shape (N, 3) or (B, N, 3), got {tuple(directions.shape)}")
    H, W = int(image.shape[-2]), int(image.shape[-1])
    d = directions if directions.dim() == 3 else directions.unsqueeze(0)
    if image.is_floating_point():
        d = d.to(image.dtype)
    uv = Equirectangular(width=W, height=H).lonlat_to_uv(*direction_to_lonlat(d))  # (B|1, N, 2)
    valid = torch.ones(uv.shape[:-1], dtype=torch.bool, device=uv.device)
    out, _ = sample_grid(image, WarpGrid(uv.unsqueeze(1), valid.unsqueeze(1), W, H, True), mode)
    return out[:, :, 0, :]


def rotate_panorama(image: Tensor, R: Tensor, mode: str = "bilinear", camera: Camera | None = None,
                    cache: bool = True, invalid: float | None = None) -> tuple[Tensor, Tensor]:
    """Re-render a panorama for a rotated camera: :func:`~omnidl.geometry.warp.reproject` with
    the same camera as source and destination.

    The output pixel whose direction is ``d`` (new camera frame) shows the input at ``R @ d``:
    ``R`` is ``R_old_new``, the orientation of the new camera expressed in the old one. So
    rotating by ``R`` and then by ``R.T`` gives the original back (up to interpolation blur),
    and a scene point ``X`` of the old frame appears in the new panorama at ``R.T @ X``.
    With a gyroscope orientation ``R = R_ref_cur``, ``rotate_panorama(reference, R)`` is the
    current view and ``rotate_panorama(current, R.transpose(-1, -2))`` the stabilised one.

    Args:
        image: ``(B, C, H, W)`` (or ``(C, H, W)`` / ``(H, W)``) panorama; labels with ``mode="nearest"``.
            Depth (range) maps stay valid under rotation (ranges do not change): rotate them with
            ``mode="masked"`` so the 0 of holes is not blended into valid ranges.
        R: ``(3, 3)`` or ``(B, 3, 3)`` rotation ``R_old_new`` (OpenCV camera frame).
        mode: ``"bilinear"``, ``"masked"`` (bilinear over the valid taps; depth) or ``"nearest"``.
        camera: the equirectangular camera of ``image`` (default: full sphere of the image size).
        cache: keep the sampling grid for the next call with the same ``R`` (see :func:`reproject`);
            ``False`` when every call brings a new rotation (random augmentation, video frames).
        invalid: value of "no measurement" for ``masked`` (default 0); with ``bilinear`` it means ``masked``.

    Returns:
        ``(rotated image, valid)`` as :func:`reproject` (valid is all True for a full panorama).
    """
    if camera is None:
        if image.dim() < 2:
            raise ValueError(f"image must have shape (B, C, H, W), (C, H, W) or (H, W), got {tuple(image.shape)}")
        camera = Equirectangular(width=int(image.shape[-1]), height=int(image.shape[-2]))
    return reproject(image, camera, camera, rotation=R, mode=mode, cache=cache, invalid=invalid)
