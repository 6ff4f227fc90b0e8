"""``omnidl predict --camera``: run a model trained on one camera on images of another camera.

The input image ``(3, H, W)`` comes with its own camera ``C_in`` (``--camera FILE|PRESET``, or a sidecar file
next to the image, see :func:`sidecar_camera`); the model was trained on ``C_m`` (the checkpoint's camera at
the network's input size, :meth:`Predictor.camera_for`). :class:`CameraBridge` takes the image into ``C_m``,
the network runs there, and its maps come back to every input pixel:

* **to the model** (:meth:`CameraBridge.to_model`): each model pixel's ray (model frame) is turned into the
  input frame (``R_in_m = R_up_cam^T`` when the input was levelled, else the identity), projected by
  ``C_in`` and the input image is sampled there (bilinear). A large input is first shrunk (antialiased) to
  about the model's angular pixel pitch, with ``C_in`` resized by the same factor, so nothing aliases.
  Model pixels the input camera does not see are black and marked unseen.
* **back to the input** (:meth:`CameraBridge.to_input`): every input pixel's ray is projected by ``C_m`` and
  the model's map is sampled there with masked bilinear interpolation (:func:`omnidl.geometry.sample_grid`,
  ``mode="masked"``): model pixels the input does not see, or that ``C_m`` marks invalid, never blend in.
  Input pixels that ``C_m`` does not see (or whose every tap is masked) are **masked, never filled in**:
  depth ``NaN`` (``0`` in the 16-bit PNG), semantic class ``0`` and ``0`` in ``<name>_valid.png``.
* **depth** is the range along each input pixel's own ray, from the ray's origin. Both cameras share the
  optical centre when central, so the range carries over unchanged. For a **non-central** input camera
  (rays ``o + t d``), ``t`` solves ``|o + t d| = D(dir(o + t d))`` with ``D`` the model's range along its own
  (central) ray, by a few fixed-point steps; the point cloud is ``o + t d`` in metres. The image is taken
  into ``C_m`` through points at the model's first estimate of the range (one extra network pass; the first
  pass puts the scene far away).
* **coverage** (:class:`Coverage`): the share of the input's valid pixels that got a value and the share of
  the model's valid pixels the input fills, printed on the console and written in the outputs' JSON.

A non-central **model** camera cannot be fed from another camera without the scene's depth; ``--camera`` with
such a checkpoint is refused.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from omnidl.cameras import Camera, load
from omnidl.geometry.warp import WarpGrid, sample_grid

#: sidecar names looked for next to an input ``<dir>/<stem>.<ext>`` (first match wins)
SIDECAR_SUFFIXES = (".camera.yaml", ".camera.yml", ".camera.json", ".camera.xml", ".camera.txt")
#: fixed-point steps for the range along a non-central input ray
NONCENTRAL_STEPS = 4
#: distance (metres) at which the first pass of a non-central input puts the scene
FAR = 1.0e4


def sidecar_camera(source: str | Path | None) -> Path | None:
    """The camera file stored next to an input file: ``<stem>.camera.yaml`` (or ``.yml``, ``.json``, ``.xml``,
    ``.txt``) in the same folder, e.g. ``img.jpg`` -> ``img.camera.yaml``; for a video, one file for every
    frame. ``None`` when there is none."""
    if source is None:
        return None
    p = Path(source)
    for suf in SIDECAR_SUFFIXES:
        c = p.with_name(p.stem + suf)
        if c.is_file():
            return c
    return None


def input_camera(spec: Any, width: int, height: int, what: str = "--camera") -> Camera:
    """The camera of a ``width x height`` input from ``spec``: any file :func:`omnidl.cameras.load` reads
    (omnidl YAML, COLMAP, Kalibr, OpenCV, ORB-SLAM3, OCamCalib, KB text, WoodScape JSON), a preset name
    (``configs/camera``, e.g. ``kb_f195``, resolved by :func:`omnidl.cameras.resolve_camera`) or a ``Camera``.
    A calibration of another size is used on the image uniformly resized; any other size is a ``ValueError``
    naming ``what``, the spec and both sizes (as every other error here)."""
    try:
        from omnidl.cameras import list_cameras, resolve_camera
        if isinstance(spec, str) and spec in list_cameras() and not Path(spec).is_file():
            return resolve_camera(spec, int(width), int(height))     # a family at the image size (equirect)
        return load(spec if isinstance(spec, Camera) else str(spec), image_size=(int(width), int(height)))
    except (ValueError, KeyError, TypeError, OSError) as e:
        raise ValueError(f"{what} {str(spec)!r}: {e}") from e


@dataclass(frozen=True)
class Coverage:
    """Which pixels the two cameras share.

    Attributes:
        input_pixels: valid pixels of the input camera (its rays see the scene).
        input_covered: of those, pixels that got a model value (the model camera sees them).
        model_pixels: valid pixels of the model camera.
        model_seen: of those, pixels the input camera sees.
    """

    input_pixels: int
    input_covered: int
    model_pixels: int
    model_seen: int

    @property
    def input_fraction(self) -> float:
        return self.input_covered / self.input_pixels if self.input_pixels else 0.0

    @property
    def model_fraction(self) -> float:
        return self.model_seen / self.model_pixels if self.model_pixels else 0.0

    def to_dict(self) -> dict:
        return {"input_valid_pixels": self.input_pixels, "input_covered_pixels": self.input_covered,
                "input_covered_fraction": self.input_fraction, "input_masked_fraction": 1.0 - self.input_fraction,
                "model_valid_pixels": self.model_pixels, "model_seen_pixels": self.model_seen,
                "model_seen_fraction": self.model_fraction,
                "masked": "input pixels the model camera does not see: depth NaN in <name>_depth.npy and 0 in "
                          "<name>_depth.png, semantic class 0, 0 in <name>_valid.png; never filled in"}

    def line(self) -> str:
        return (f"the model camera sees {100 * self.input_fraction:.1f} % of the input's valid pixels "
                f"({100 * (1 - self.input_fraction):.1f} % masked: NaN depth, class 0); the input fills "
                f"{100 * self.model_fraction:.1f} % of the model camera's view")


def angular_pitch(camera: Camera, samples: int = 33) -> float:
    """Median angle (radians) between the rays of horizontally neighbouring pixels over a coarse grid of
    valid pixels: the camera's angular resolution."""
    u = (torch.arange(samples, dtype=torch.float64) + 0.5) / samples * max(camera.width - 1, 1)
    v = (torch.arange(samples, dtype=torch.float64) + 0.5) / samples * camera.height
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    uv = torch.stack([uu, vv], -1).reshape(-1, 2)
    a, b = camera.unproject(uv), camera.unproject(uv + torch.tensor([1.0, 0.0], dtype=torch.float64))
    ok = a.valid & b.valid
    if not bool(ok.any()):
        return float("nan")
    c = (a.direction[ok] * b.direction[ok]).sum(-1).clamp(-1, 1)
    return float(torch.acos(c).median())


class CameraBridge:
    """Input camera <-> model camera for one input size (see the module docstring).

    Args:
        input_camera: ``C_in`` at the input image's size ``W x H``.
        model_camera: ``C_m`` at the network's input size (central).
        R_up_cam: ``(3, 3)`` rotation input camera frame -> model frame (the levelling of a tilted input),
            ``None`` for the identity.
    """

    def __init__(self, input_camera: Camera, model_camera: Camera, R_up_cam: Tensor | None = None) -> None:
        if not model_camera.central:
            raise ValueError(f"--camera: the checkpoint's camera ({type(model_camera).__name__}) is non-central; an "
                             "image of another camera cannot be re-projected into it without the scene's depth. "
                             "Run without --camera on images of the model's own camera")
        self.cin, self.cm = input_camera, model_camera
        self.R = torch.eye(3, dtype=torch.float64) if R_up_cam is None else \
            torch.as_tensor(R_up_cam, dtype=torch.float64).reshape(3, 3)
        rays = model_camera.unproject_grid(torch.float64)
        self.model_dir, self.model_valid = rays.direction, rays.valid          # (h, w, 3), (h, w) model frame
        rin = input_camera.unproject_grid(torch.float64)
        self.in_origin, self.in_dir, self.in_valid = rin.origin, rin.direction, rin.valid   # input frame

    # -- input image -> model camera ------------------------------------------------------------------------
    def _prefiltered(self, image: Tensor) -> tuple[Tensor, Camera]:
        """The input shrunk (antialiased) to about the model's angular pitch, and its camera."""
        p_in, p_m = angular_pitch(self.cin), angular_pitch(self.cm)
        if not (math.isfinite(p_in) and math.isfinite(p_m)) or p_in >= p_m:
            return image, self.cin
        s = p_in / p_m
        w, h = max(1, round(self.cin.width * s)), max(1, round(self.cin.height * s))
        if (w, h) == (self.cin.width, self.cin.height):
            return image, self.cin
        small = F.interpolate(image[None].float(), size=(h, w), mode="bilinear", align_corners=False,
                              antialias=True)[0]
        return small, self.cin.resized(w, h)

    def to_model(self, image: Tensor, model_range: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """``image (3, H, W)`` -> ``(model image (3, h, w), seen (h, w) bool)``: the input seen through the
        model camera; unseen model pixels are 0. ``model_range (h, w)``: the scene's range along each model
        ray (non-central inputs; default far away)."""
        img, cam = self._prefiltered(image)
        d_in = self.model_dir @ self.R                                   # R^T d: model frame -> input frame
        if cam.central:
            pts = d_in
        else:
            r = torch.full(d_in.shape[:-1], FAR, dtype=torch.float64) if model_range is None else \
                torch.nan_to_num(model_range.double().reshape(d_in.shape[:-1]), nan=FAR, posinf=FAR)
            pts = d_in * r.clamp_min(1e-3)[..., None]
        uv, ok = cam.project(pts)
        ok = ok & self.model_valid
        grid = WarpGrid(uv[None], ok[None], int(cam.width), int(cam.height), bool(cam.wraps_horizontally))
        out, valid = sample_grid(img[None].float(), grid, "bilinear")
        return out[0], valid[0, 0]

    # -- model maps -> input pixels -----------------------------------------------------------------------
    def _sample_model(self, maps: Tensor, points_in: Tensor) -> tuple[Tensor, Tensor]:
        """``maps (C, h, w)`` (NaN = masked) at the model pixels of input-frame points ``(H, W, 3)``."""
        uv, ok = self.cm.project(points_in @ self.R.T)
        ok = ok & self.in_valid
        grid = WarpGrid(uv[None], ok[None], int(self.cm.width), int(self.cm.height), bool(self.cm.wraps_horizontally))
        out, valid = sample_grid(maps[None], grid, "masked", invalid=float("nan"))
        return out[0], valid[0, 0]

    def mask_model_map(self, maps: Tensor, seen: Tensor) -> Tensor:
        """``maps (C, h, w)`` with NaN where the model camera is invalid or the input did not fill it."""
        keep = (self.model_valid & seen.to(self.model_valid.device))[None]
        return torch.where(keep, maps.double(), torch.full((), float("nan"), dtype=torch.float64))

    def depth_to_input(self, model_depth: Tensor, seen: Tensor) -> tuple[Tensor, Tensor]:
        """Model range ``(1, h, w)`` -> ``(range along each input ray (H, W) float64, NaN = masked; valid)``."""
        maps = self.mask_model_map(model_depth.reshape(1, *model_depth.shape[-2:]), seen)
        o, d = self.in_origin, self.in_dir
        D, valid = self._sample_model(maps, d)                           # range of the direction from the centre
        t = D[0]
        if not self.cin.central:
            od, oo = (o * d).sum(-1), (o * o).sum(-1)
            for _ in range(NONCENTRAL_STEPS):
                p = o + torch.nan_to_num(t, nan=FAR)[..., None] * d
                D, valid = self._sample_model(maps, p)
                disc = od * od - oo + D[0] * D[0]
                t = torch.where(disc >= 0, -od + torch.sqrt(disc.clamp_min(0)), torch.full_like(od, float("nan")))
        valid = valid & self.in_valid & torch.isfinite(t) & (t > 0)
        return torch.where(valid, t, torch.full_like(t, float("nan"))), valid

    def map_to_input(self, model_map: Tensor, seen: Tensor, depth_in: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Any model map ``(C, h, w)`` (e.g. semantic logits) -> ``((C, H, W), valid (H, W))`` at the input
        pixels (NaN where masked); ``depth_in``: the input ranges for non-central inputs."""
        maps = self.mask_model_map(model_map, seen)
        pts = self.in_dir if self.cin.central or depth_in is None else \
            self.in_origin + torch.nan_to_num(depth_in.double(), nan=FAR)[..., None] * self.in_dir
        return self._sample_model(maps, pts)

    def points(self, depth_in: Tensor) -> tuple[Tensor, Tensor]:
        """``(points (H, W, 3) input frame metres = o + t d, valid (H, W))``."""
        ok = self.in_valid & torch.isfinite(depth_in) & (depth_in > 0)
        t = torch.where(ok, depth_in.double(), torch.zeros((), dtype=torch.float64))
        return self.in_origin + t[..., None] * self.in_dir, ok

    def coverage(self, seen: Tensor, valid_in: Tensor) -> Coverage:
        return Coverage(int(self.in_valid.sum()), int((valid_in & self.in_valid).sum()),
                        int(self.model_valid.sum()), int((seen & self.model_valid).sum()))

    def to_dict(self) -> dict:
        return {"input_camera": _camera_dict(self.cin), "model_camera": _camera_dict(self.cm),
                "R_model_input": self.R.tolist()}


def _camera_dict(cam: Camera) -> dict:
    try:
        return cam.to_config()
    except Exception:  # noqa: BLE001 (a camera without a plain config: name it at least)
        return {"type": type(cam).__name__, "width": cam.width, "height": cam.height}
