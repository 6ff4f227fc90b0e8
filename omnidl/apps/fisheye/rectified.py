"""The rectification baseline of thesis §7.4.3: rectify the fisheye image to a perspective image,
run a perspective network, un-rectify its outputs and evaluate them in the fisheye domain.

A perspective image holds only rays in front of the camera (``z > 0``) and only up to its own field
of view, so part of a wide fisheye image cannot be rectified (every pixel 90° or more off-axis of a
195° lens). There the un-rectified prediction is empty — depth 0 and all-zero logits (predicted class
0 = unknown) — and is counted as an error by the metrics; :func:`rectification_report` gives the
fractions of the fisheye image that can be rectified at all and that the chosen perspective camera
covers.
"""
from __future__ import annotations

from dataclasses import asdict
from typing import Any

import torch
from torch import Tensor, nn

from omnidl.cameras import Camera, resolve_camera
from omnidl.geometry import perspective_camera, rectification_coverage, reproject


def rectifying_camera(fisheye: Camera, fov_deg: float | None = 150.0, width: int | None = None,
                      height: int | None = None) -> Camera:
    """The pinhole of the rectified image: the fisheye's size, horizontal FOV ``fov_deg`` (``None``: the
    fisheye's resolution at the principal point, :func:`omnidl.geometry.perspective_camera`)."""
    return perspective_camera(fisheye, width, height, fov_deg)


class RectifiedModel(nn.Module):
    """``model`` applied to rectified fisheye images; outputs returned in the fisheye domain.

    Args:
        model: a perspective network (``forward(image) -> {"depth", "semantic", ...}``).
        fisheye: camera of the input images (its size must equal the input's).
        pinhole: perspective camera of the rectified image (default :func:`rectifying_camera`).
        fov_deg: horizontal field of view of the default pinhole.

    ``forward(image (B,3,H,W)) -> dict``: ``depth (B,1,H,W)`` (0 where not rectified), ``semantic``
    logits (0 where not rectified), and ``rectified (B,1,H,W)`` bool: the fisheye pixels the pinhole
    covers. Differentiable (fine-tuning through the warps works).
    """

    def __init__(self, model: nn.Module, fisheye: Camera, pinhole: Camera | None = None,
                 fov_deg: float | None = 150.0) -> None:
        super().__init__()
        self.model = model
        self.fisheye = fisheye
        self.pinhole = pinhole or rectifying_camera(fisheye, fov_deg)

    def forward(self, image: Tensor) -> dict[str, Tensor]:
        if tuple(image.shape[-2:]) != (self.fisheye.height, self.fisheye.width):
            raise ValueError(f"RectifiedModel: input {tuple(image.shape[-2:])} (H, W) disagrees with the fisheye "
                             f"calibration ({self.fisheye.height}, {self.fisheye.width})")
        rect, _ = reproject(image, self.fisheye, self.pinhole, mode="bilinear")
        out = self.model(rect)
        result: dict[str, Tensor] = {}
        covered = None
        for key, val in out.items():
            if not isinstance(val, Tensor) or val.dim() != 4 or not val.is_floating_point():
                continue
            back, valid = reproject(val, self.pinhole, self.fisheye, mode="bilinear")
            result[key] = back
            covered = valid
        if covered is not None:
            result["rectified"] = covered
        return result


def rectified_model(model: nn.Module, camera: Any, width: int, height: int, fov_deg: float | None = 150.0
                    ) -> RectifiedModel:
    """:class:`RectifiedModel` for config files: ``camera`` is any :func:`omnidl.cameras.resolve_camera` spec,
    resized to the ``width x height`` input images (e.g. ``{_target_: ...rectified_model, model: <model node>,
    camera: ${camera}, width: ${data.width}, height: ${data.height}}``)."""
    return RectifiedModel(model, resolve_camera(camera, width, height, check_aspect=True), fov_deg=fov_deg)


def rectification_report(fisheye: Camera, pinhole: Camera | None = None, fov_deg: float | None = 150.0
                         ) -> dict[str, Any]:
    """Fractions of the fisheye's valid pixels: ``rectifiable`` (rays with ``z > 0``), ``unrectifiable``
    (``1 - rectifiable``: lost by any rectification) and ``covered`` (held by this pinhole)."""
    pinhole = pinhole or rectifying_camera(fisheye, fov_deg)
    rep = asdict(rectification_coverage(fisheye, pinhole))
    rep["pinhole_fov_deg"] = float(torch.rad2deg(2 * torch.atan(torch.tensor(pinhole.width / 2 / pinhole.fx))))
    return rep
