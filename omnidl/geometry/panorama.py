"""Rotating equirectangular panoramas (rotated-panorama augmentation of ch. 4, stabilisation of ch. 6)."""
from __future__ import annotations

from torch import Tensor

from omnidl.cameras.base import Camera
from omnidl.cameras.equirectangular import Equirectangular

from .warp import reproject


def rotate_panorama(image: Tensor, R: Tensor, mode: str = "bilinear",
                    camera: Camera | None = None) -> tuple[Tensor, Tensor]:
    """Re-render a panorama for a rotated camera: :func:`~omnidl.geometry.warp.reproject` with
    the same equirectangular camera as source and destination.

    The output pixel whose direction is ``d`` (new camera frame) shows the input at ``R @ d``:
    ``R`` is ``R_old_new``, the orientation of the new camera expressed in the old one. So
    rotating by ``R`` and then by ``R.T`` gives the original back (up to interpolation blur),
    and a scene point ``X`` of the old frame appears in the new panorama at ``R.T @ X``.

    Args:
        image: ``(B, C, H, W)`` (or ``(C, H, W)`` / ``(H, W)``) panorama; labels with ``mode="nearest"``.
            Depth (range) maps stay valid under rotation: ranges do not change.
        R: ``(3, 3)`` or ``(B, 3, 3)`` rotation ``R_old_new`` (OpenCV camera frame).
        mode: ``"bilinear"`` or ``"nearest"``.
        camera: the equirectangular camera of ``image`` (default: full sphere of the image size).

    Returns:
        ``(rotated image, valid)`` as :func:`reproject` (valid is all True for a full panorama).
    """
    if camera is None:
        if image.dim() < 2:
            raise ValueError(f"image must have shape (B, C, H, W), (C, H, W) or (H, W), got {tuple(image.shape)}")
        camera = Equirectangular(width=int(image.shape[-1]), height=int(image.shape[-2]))
    return reproject(image, camera, camera, rotation=R, mode=mode)
