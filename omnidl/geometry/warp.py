"""Re-projection of an image between two cameras (and a rotation), with cached sampling grids.

Contract (``docs/extending.md``): :func:`reproject` renders ``dst_camera``'s image from an
image taken by a *central* ``src_camera``. Every destination pixel centre is unprojected
to a ray of ``dst_camera``; its direction ``d`` (dst camera frame) becomes ``R_src_dst @ d``
in the source frame, is projected by ``src_camera`` and the source image is sampled there.

Conventions:

* Pixels follow the project convention: the centre of pixel (row ``i``, column ``j``) is
  ``(u, v) = (j + 0.5, i + 0.5)``; bilinear sampling interpolates between pixel centres
  (``grid_sample(align_corners=False)``), the half pixel between the last centre and the
  image border repeats the border pixel.
* Sources that wrap horizontally (360° panoramas) sample across the seam ``u = 0 = W``
  seamlessly (the image is padded with one wrapped column on each side).
* ``mode="nearest"`` picks the source pixel containing the sample point (for labels; any
  dtype, values copied exactly). ``mode="bilinear"`` needs a floating image.
* ``mode="masked"`` (the mode for depth and any map with an invalid value) is bilinear with the
  weights renormalised over the *valid* taps: a tap equal to ``invalid`` (default ``0``, the
  invalid depth) or non-finite gets weight 0, so holes never blend into valid values (an output
  lies between its valid neighbours and a constant region stays exactly constant). A pixel
  with no valid tap is ``invalid`` and ``valid=False``. ``mode="bilinear"`` with ``invalid=``
  given means ``"masked"``.
* Destination pixels whose ray is invalid or falls outside the source image are ``0`` and
  ``valid=False``.
* Depth maps that store the range from the camera centre re-project unchanged between
  central cameras sharing the centre (a rotation keeps ranges); warp them with
  ``mode="masked"`` (plain ``bilinear`` blends the 0 of holes into valid ranges; ``nearest``
  keeps depth edges sharp). For a non-central ``dst_camera`` only the ray directions are used
  (the scene is assumed far away compared with the baseline).
"""
from __future__ import annotations

import threading
from collections import OrderedDict
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from omnidl.cameras.base import Camera

_MODES = ("bilinear", "nearest", "masked")
#: the invalid value of depth maps (no measurement), the default ``invalid`` of ``mode="masked"``
DEPTH_INVALID = 0.0
_CACHE_SIZE = 32
_cache: "OrderedDict[tuple, WarpGrid]" = OrderedDict()
_cache_lock = threading.Lock()


class WarpGrid(NamedTuple):
    """Where every destination pixel samples the source image.

    Attributes:
        uv: ``(B, Hd, Wd, 2)`` source pixel coordinates (pixel-centre convention), finite.
        valid: ``(B, Hd, Wd)`` bool, the destination pixel sees a valid source pixel.
        src_width: source image width in pixels.
        src_height: source image height in pixels.
        wrap: the source wraps horizontally (column ``W`` is column ``0``).
    """

    uv: Tensor
    valid: Tensor
    src_width: int
    src_height: int
    wrap: bool


def _check_rotation(rotation: Tensor | None, dtype: torch.dtype, device) -> Tensor | None:
    if rotation is None:
        return None
    rotation = torch.as_tensor(rotation)
    if rotation.shape[-2:] != (3, 3) or rotation.dim() not in (2, 3):
        raise ValueError(f"rotation must have shape (3, 3) or (B, 3, 3), got {tuple(rotation.shape)}")
    if not torch.isfinite(rotation).all():
        raise ValueError("rotation contains NaN or inf")
    return rotation.to(dtype=dtype, device=device)


def _grid_key(src: Camera, dst: Camera, rotation: Tensor | None, dtype: torch.dtype, device) -> tuple | None:
    if rotation is not None and rotation.requires_grad:
        return None
    rot = None if rotation is None else (tuple(rotation.shape), rotation.detach().cpu().double().numpy().tobytes())
    return (src, dst, rot, dtype, str(torch.device(device) if device is not None else torch.device("cpu")))


def _compute_grid(src: Camera, dst: Camera, rotation: Tensor | None, dtype: torch.dtype, device) -> WarpGrid:
    if not src.central:
        raise ValueError(f"reproject needs a central source camera; {type(src).__name__} is non-central")
    rays = dst.unproject_grid(dtype=dtype, device=device)  # (Hd, Wd)
    d = rays.direction.unsqueeze(0)  # (1, Hd, Wd, 3)
    if rotation is not None:
        rot = rotation if rotation.dim() == 3 else rotation.unsqueeze(0)
        d = torch.einsum("bij,bhwj->bhwi", rot, d)
    uv, valid = src.project(d)
    valid = valid & rays.valid.unsqueeze(0)
    uv = torch.where(valid.unsqueeze(-1), uv, torch.zeros_like(uv))  # finite everywhere
    return WarpGrid(uv, valid, int(src.width), int(src.height), bool(src.wraps_horizontally))


def warp_grid(src_camera: Camera, dst_camera: Camera, rotation: Tensor | None = None,
              dtype: torch.dtype = torch.float32, device: torch.device | str | None = None,
              cache: bool = True) -> WarpGrid:
    """The sampling grid of :func:`reproject` (``dst`` pixel -> ``src`` pixel).

    Args:
        src_camera: central camera of the source image.
        dst_camera: camera whose image is rendered.
        rotation: ``R_src_dst``, ``(3, 3)`` or ``(B, 3, 3)``; a dst-frame direction ``d`` is
            ``R_src_dst @ d`` in the src frame. ``None`` is the identity.
        dtype, device: of the grid.
        cache: keep the grid (keyed by both cameras, the rotation values, dtype and device)
            so repeated warps with the same geometry are cheap. Rotations that require
            gradients are never cached. Cached tensors are shared: do not modify them in place.

    Returns:
        :class:`WarpGrid` with ``B = 1`` for a ``(3, 3)`` rotation (or none).
    """
    rotation = _check_rotation(rotation, dtype, device)
    key = _grid_key(src_camera, dst_camera, rotation, dtype, device) if cache else None
    if key is not None:
        with _cache_lock:
            hit = _cache.get(key)
            if hit is not None:
                _cache.move_to_end(key)
                return hit
    grid = _compute_grid(src_camera, dst_camera, rotation, dtype, device)
    if key is not None:
        with _cache_lock:
            _cache[key] = grid
            while len(_cache) > _CACHE_SIZE:
                _cache.popitem(last=False)
    return grid


def clear_warp_cache() -> None:
    """Forget every cached :func:`warp_grid`."""
    with _cache_lock:
        _cache.clear()


def _as_bchw(image: Tensor) -> tuple[Tensor, int]:
    if not isinstance(image, Tensor):
        raise TypeError(f"image must be a torch.Tensor, got {type(image).__name__}")
    if image.dim() == 4:
        return image, 4
    if image.dim() == 3:
        return image.unsqueeze(0), 3
    if image.dim() == 2:
        return image.unsqueeze(0).unsqueeze(0), 2
    raise ValueError(f"image must have shape (B, C, H, W), (C, H, W) or (H, W), got {tuple(image.shape)}")


def _restore(x: Tensor, ndim: int) -> Tensor:
    if ndim == 4:
        return x
    if ndim == 3:
        return x[0]
    return x[0, 0]


def _resolve_mode(mode: str, invalid: float | None) -> tuple[str, float | None]:
    """``(mode, invalid)`` with ``bilinear`` + ``invalid`` -> ``masked`` and ``masked`` defaulting to 0."""
    if mode not in _MODES:
        raise ValueError(f"mode must be one of {_MODES}, got {mode!r}")
    if invalid is not None:
        invalid = float(invalid)
    if mode == "masked" and invalid is None:
        invalid = DEPTH_INVALID
    if mode == "bilinear" and invalid is not None:
        mode = "masked"
    return mode, invalid


def _bilinear(image: Tensor, grid: WarpGrid, uv: Tensor, bo: int) -> Tensor:
    """``grid_sample`` of ``image (b, C, H, W)`` at ``uv (bg, Hd, Wd, 2)`` with the seam wrap -> ``(bo, C, Hd, Wd)``."""
    b, _, h, w = image.shape
    bg = uv.shape[0]
    uv = uv.to(image.dtype)
    u, v = uv[..., 0], uv[..., 1]
    src = image
    if grid.wrap:  # one wrapped column on each side: interpolation across the seam
        src = torch.cat([image[..., -1:], image, image[..., :1]], dim=-1)
        lo, hi = torch.aminmax(u.detach())
        if float(lo) < 0 or float(hi) > w:  # camera projections already lie in [0, W]
            u = torch.remainder(u, w)
        u = u + 1.0
        wp = w + 2
    else:
        wp = w
    g = torch.stack([2.0 * u / wp - 1.0, 2.0 * v / h - 1.0], -1)
    if b != bo:
        src = src.expand(bo, -1, -1, -1)
    if bg != bo:
        g = g.expand(bo, -1, -1, -1)
    return F.grid_sample(src, g, mode="bilinear", padding_mode="border", align_corners=False)


def _masked_bilinear(image: Tensor, grid: WarpGrid, uv: Tensor, bo: int, invalid: float) -> tuple[Tensor, Tensor]:
    """Bilinear over the valid taps only -> ``(out (bo, C, Hd, Wd), has_tap (bo, 1, Hd, Wd))``.

    The four taps of ``grid_sample(align_corners=False, padding_mode="border")`` (columns wrapped when the
    source wraps). A tap is valid when finite and not ``invalid``; the output is ``ref + sum_k w_k (x_k - ref)
    / sum_k w_k`` over the valid taps, ``ref`` the first valid tap, so it lies between the valid taps and a
    constant region stays exactly constant. Taps of total weight < 1e-6 count as none."""
    b, c, h, w = image.shape
    bg, hd, wd = uv.shape[:3]
    uv = uv.to(image.dtype)
    x, y = uv[..., 0] - 0.5, uv[..., 1] - 0.5
    x0, y0 = torch.floor(x.detach()), torch.floor(y.detach())
    tx, ty = x - x0, y - y0
    x0, y0 = x0.long(), y0.long()
    if grid.wrap:
        cols = (torch.remainder(x0, w), torch.remainder(x0 + 1, w))
    else:
        cols = (x0.clamp(0, w - 1), (x0 + 1).clamp(0, w - 1))
    rows = (y0.clamp(0, h - 1), (y0 + 1).clamp(0, h - 1))
    flat = image.reshape(b, c, h * w).expand(bo, -1, -1)
    vals, oks, wts = [], [], []
    for r, wy in zip(rows, (1 - ty, ty)):
        for col, wx in zip(cols, (1 - tx, tx)):
            idx = (r * w + col).reshape(bg, 1, hd * wd).expand(bo, c, -1)
            v = torch.gather(flat, 2, idx).reshape(bo, c, hd, wd)
            ok = torch.isfinite(v) if invalid != invalid else torch.isfinite(v) & (v != invalid)
            vals.append(v)
            oks.append(ok)
            wts.append((wy * wx).unsqueeze(1) * ok)
    ref = torch.full((), invalid if invalid == invalid else 0.0, dtype=image.dtype, device=image.device)
    ref = ref.expand(bo, c, hd, wd)
    for v, ok in zip(reversed(vals), reversed(oks)):
        ref = torch.where(ok, v, ref)
    den = wts[0] + wts[1] + wts[2] + wts[3]
    num = sum(wk * (torch.where(ok, v, ref) - ref) for v, ok, wk in zip(vals, oks, wts))
    has = den >= 1e-6
    out = ref + num / torch.where(has, den, torch.ones_like(den))
    out = torch.where(has, out, torch.full((), invalid, dtype=out.dtype, device=out.device))
    return out, has.all(dim=1, keepdim=True)


def sample_grid(image: Tensor, grid: WarpGrid, mode: str = "bilinear",
                invalid: float | None = None) -> tuple[Tensor, Tensor]:
    """Sample ``image (B, C, Hs, Ws)`` at ``grid`` -> ``(out (B, C, Hd, Wd), valid (B, 1, Hd, Wd))``.

    The batch sizes of the image and the grid broadcast (either may be 1). ``mode``: ``"bilinear"``,
    ``"nearest"`` or ``"masked"`` (bilinear over the taps that are finite and not ``invalid``; see the
    module doc). Invalid output pixels are ``invalid`` when given, else 0.
    """
    mode, invalid = _resolve_mode(mode, invalid)
    b, c, h, w = image.shape
    if (h, w) != (grid.src_height, grid.src_width):
        raise ValueError(f"image is {w}x{h} (WxH) but the source camera is {grid.src_width}x{grid.src_height}")
    bg = grid.uv.shape[0]
    if b != bg and b != 1 and bg != 1:
        raise ValueError(f"image batch {b} and rotation batch {bg} do not broadcast")
    bo = max(b, bg)
    uv = grid.uv.to(image.device)
    valid = grid.valid.to(image.device)
    hd, wd = uv.shape[1:3]
    if bg != bo:
        valid = valid.expand(bo, -1, -1)
    if mode == "nearest":
        iu = torch.floor(uv[..., 0]).long()
        iu = torch.remainder(iu, w) if grid.wrap else iu.clamp(0, w - 1)
        iv = torch.floor(uv[..., 1]).long().clamp(0, h - 1)
        idx = (iv * w + iu).reshape(bg, 1, hd * wd).expand(bo, c, -1)
        flat = image.reshape(b, c, h * w).expand(bo, -1, -1)
        out = torch.gather(flat, 2, idx).reshape(bo, c, hd, wd)
    else:
        if not image.is_floating_point():
            raise TypeError(f"{mode} sampling needs a floating image, got {image.dtype}; use mode='nearest' "
                            "for labels")
        if mode == "masked":
            out, has = _masked_bilinear(image, grid, uv, bo, invalid)
            valid = valid & has[:, 0]
        else:
            out = _bilinear(image, grid, uv, bo)
    if not bool(valid.all()):  # a full panorama seen from a full panorama needs no masking
        fill = torch.zeros((), dtype=out.dtype, device=out.device) if invalid is None else \
            torch.full((), invalid, dtype=out.dtype, device=out.device)
        out = torch.where(valid.unsqueeze(1), out, fill)
    return out, valid.unsqueeze(1)


def reproject(image: Tensor, src_camera: Camera, dst_camera: Camera, rotation: Tensor | None = None,
              mode: str = "bilinear", cache: bool = True, invalid: float | None = None) -> tuple[Tensor, Tensor]:
    """Render ``dst_camera``'s image from ``image`` taken by the central ``src_camera``.

    Args:
        image: ``(B, C, Hs, Ws)`` (also ``(C, H, W)`` or ``(H, W)``; the outputs then drop the
            same leading dims). Floating for ``bilinear``; any dtype for ``nearest``.
        src_camera: central camera of ``image`` (its size must match the image).
        dst_camera: camera to render (any model; non-central ones use ray directions only).
        rotation: ``R_src_dst`` ``(3, 3)`` or ``(B, 3, 3)``: a direction ``d`` in the dst frame is
            ``R_src_dst @ d`` in the src frame. ``None`` = the cameras share their orientation.
        mode: ``"bilinear"`` (images), ``"masked"`` (depth and any map with an invalid value: bilinear
            over the valid taps only) or ``"nearest"`` (labels, exact values).
        cache: keep the sampling grid for the next call with the same geometry (:func:`warp_grid`);
            ``False`` for rotations that change every call (e.g. a new one per video frame).
        invalid: the value marking "no measurement" (``masked`` default: 0, the invalid depth); with
            ``bilinear`` it switches to ``masked``. Invalid output pixels get this value.

    Returns:
        ``(image (B, C, Hd, Wd), valid (B, 1, Hd, Wd) bool)``; invalid pixels are 0 (or ``invalid``).
        Differentiable w.r.t. ``image`` (and ``rotation`` for ``bilinear``).
    """
    x, ndim = _as_bchw(image)
    dtype = x.dtype if x.is_floating_point() else torch.float32
    if isinstance(rotation, Tensor) and rotation.dtype == torch.float64:
        dtype = torch.float64  # precise grid; sampled in the image's dtype
    _resolve_mode(mode, invalid)  # a bad mode fails before the grid is built
    grid = warp_grid(src_camera, dst_camera, rotation, dtype=dtype, device=x.device, cache=cache)
    out, valid = sample_grid(x, grid, mode, invalid)
    return _restore(out, ndim), _restore(valid, ndim)


class Reprojector(torch.nn.Module):
    """``nn.Module`` wrapper of :func:`reproject` for fixed cameras (the grid is cached)."""

    def __init__(self, src_camera: Camera, dst_camera: Camera, mode: str = "bilinear",
                 invalid: float | None = None) -> None:
        super().__init__()
        _resolve_mode(mode, invalid)
        self.src_camera, self.dst_camera, self.mode, self.invalid = src_camera, dst_camera, mode, invalid

    def forward(self, image: Tensor, rotation: Tensor | None = None) -> tuple[Tensor, Tensor]:
        return reproject(image, self.src_camera, self.dst_camera, rotation, self.mode, invalid=self.invalid)
