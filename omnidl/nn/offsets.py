"""Sampling offsets of a distortion-aware (projected) convolution, computed from a camera model.

Conventions (see :mod:`omnidl.cameras.base`): pixel ``(u, v)`` continuous, the centre
of pixel (row ``i``, column ``j``) is ``(j + .5, i + .5)``. Offsets use the layout of
:func:`torchvision.ops.deform_conv2d`: for kernel tap ``t = i * kw + j`` (row-major),
channel ``2t`` is the row offset ``dy`` and ``2t + 1`` the column offset ``dx``, so tap
``t`` of output position ``(oy, ox)`` samples the input at (integer pixel indices)::

    y = oy * stride_h - pad_h + i * dil_h + dy
    x = ox * stride_w - pad_w + j * dil_w + dx

How the kernel is built, for an input (feature map) of size ``H x W``:

1. ``cam = camera.resized(W, H)`` — the optics on the feature map (padding-aware).
2. **Reference pixel** ``p0``: the projection of the optical axis ``+z`` (the principal
   point of pinhole/fisheye/catadioptric models, the centre of a full panorama, which lies
   on the equator), or the image centre when ``+z`` is not seen, or (blind centre, e.g. a
   mirror camera) the seen pixel centre nearest the image centre. ``r0`` is its ray.
3. **Reference kernel** (the kernel-pitch rule): the kernel's taps at ``p0`` are
   exactly the regular pixel grid — tap ``(i, j)`` is the ray of pixel
   ``p0 + ((j - kw//2) dil_w, (i - kh//2) dil_h)``. So at ``p0`` the kernel spans exactly
   the pixel pitch (``dil`` pixels with dilation) and the offsets there are zero.
   Expressed on the tangent plane of ``r0`` these taps are (nearly) a square lattice of
   angular pitch = the angle one pixel subtends at ``p0``. ``kernel="tangent"`` uses that
   square lattice exactly instead (the EquiConv / calibrated-conv recipe of thesis §4.3.4,
   §7.3.2, with pitch ``tan(delta)`` on the tangent plane, ``delta`` = angle between the
   rays of ``p0`` and ``p0 + (dil, 0)``, resp. ``(0, dil)`` vertically).
4. **Anchor** of each OUTPUT position: the input pixel under the kernel centre,
   ``(ox * s_w - pad_w + (kw//2) dil_w + .5, oy * s_h - pad_h + (kh//2) dil_h + .5)``; its
   ray ``a`` (for non-central cameras: the ray direction, taken from the camera origin;
   tap points are projected at a far distance, see ``FAR``).
5. The reference kernel is rotated rigidly so that ``r0`` goes to ``a``: ``"upright"``
   rotation (yaw about the camera ``y`` axis then pitch, so kernel rows stay along
   latitude circles — used for panoramas, ``camera.panoramic``) or ``"axial"`` (the smallest rotation taking ``r0`` to ``a`` —
   used for the others: fisheye/pinhole/catadioptric, radially symmetric).
6. Taps are projected with ``cam`` and turned into offsets. For cameras that wrap
   horizontally the tap column is taken as the representative nearest the anchor (so
   ``|dx|`` stays small), and the sampler wraps column indices modulo ``W``.

Invalid samples (tap ray not seen by the camera, e.g. outside a fisheye circle, or
outside the image) get ``mask = 0`` and offset 0: a sampler must read zero there. An
invalid anchor (its pixel is not seen) keeps the regular grid (offsets 0), taps on pixels
the camera does not see reading zero: there the layer is ``nn.Conv2d`` on the seen pixels.
"""
from __future__ import annotations

import math
from typing import Literal

import torch
from torch import Tensor

from omnidl.cameras.base import Camera, in_image

#: distance (camera units, metres) at which tap points of NON-central cameras are projected
FAR = 1.0e4

Pair = tuple[int, int]


def _pair(v: int | tuple[int, int], name: str) -> Pair:
    if isinstance(v, int):
        return (v, v)
    v = tuple(int(a) for a in v)
    if len(v) != 2:
        raise ValueError(f"{name} must be an int or a pair of ints, got {v!r}")
    return v  # type: ignore[return-value]


def output_size(in_hw: Pair, kernel_size: Pair, stride: Pair, padding: Pair, dilation: Pair) -> Pair:
    """Output ``(Ho, Wo)`` of a convolution (same formula as ``nn.Conv2d``)."""
    out = tuple((n + 2 * p - d * (k - 1) - 1) // s + 1
                for n, k, s, p, d in zip(in_hw, kernel_size, stride, padding, dilation))
    if min(out) < 1:
        raise ValueError(f"input size {tuple(in_hw)} is too small for kernel {kernel_size}, stride {stride}, "
                         f"padding {padding}, dilation {dilation}: output would be {out}")
    return out  # type: ignore[return-value]


def _project_dirs(cam: Camera, dirs: Tensor) -> tuple[Tensor, Tensor]:
    return cam.project(dirs if cam.central else dirs * FAR)


def _reference(cam: Camera) -> tuple[Tensor, Tensor]:
    """Reference pixel ``p0 (2,)`` and unit ray ``r0 (3,)`` (float64)."""
    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    uv, valid = _project_dirs(cam, z)
    if bool(valid):
        return uv, z
    centre = torch.tensor([cam.width / 2, cam.height / 2], dtype=torch.float64)
    rays = cam.unproject(centre)
    if bool(rays.valid):
        return centre, rays.direction
    # blind centre (e.g. a mirror's own reflection): the seen pixel centre nearest the image centre
    grid = cam.pixel_grid(torch.float64).reshape(-1, 2)
    rays = cam.unproject(grid)
    ok = rays.valid & torch.isfinite(rays.direction).all(-1)
    if not bool(ok.any()):
        raise ValueError(f"camera {cam!r} sees no pixel: cannot choose the reference pixel of the projected kernel")
    dist = torch.where(ok, (grid - centre).norm(dim=-1), torch.full_like(grid[:, 0], math.inf))
    i = int(dist.argmin())
    return grid[i], rays.direction[i]


def _upright_frame(d: Tensor) -> Tensor:
    """``d (..., 3)`` unit -> rotation ``(..., 3, 3)`` with columns (right, down, d); right is horizontal."""
    right = torch.stack([d[..., 2], torch.zeros_like(d[..., 0]), -d[..., 0]], -1)
    n = right.norm(dim=-1, keepdim=True)
    pole = n < 1e-12
    right = torch.where(pole, torch.tensor([1.0, 0.0, 0.0], dtype=d.dtype), right / torch.where(pole, 1.0, n))
    down = torch.linalg.cross(d, right, dim=-1)
    return torch.stack([right, down, d], -1)


def _axial_rotation(r0: Tensor, a: Tensor) -> Tensor:
    """Smallest rotations ``(..., 3, 3)`` taking unit ``r0 (3,)`` to unit ``a (..., 3)``."""
    v = torch.linalg.cross(r0.expand_as(a), a, dim=-1)
    c = (a * r0).sum(-1)
    zero = torch.zeros_like(c)
    vx = torch.stack([torch.stack([zero, -v[..., 2], v[..., 1]], -1),
                      torch.stack([v[..., 2], zero, -v[..., 0]], -1),
                      torch.stack([-v[..., 1], v[..., 0], zero], -1)], -2)
    eye = torch.eye(3, dtype=a.dtype).expand(vx.shape)
    opposite = (1 + c) < 1e-12
    k = 1.0 / torch.where(opposite, torch.ones_like(c), 1 + c)
    rot = eye + vx + (vx @ vx) * k[..., None, None]
    if bool(opposite.any()):  # half turn about an axis perpendicular to r0
        perp = torch.linalg.cross(r0, torch.tensor([1.0, 0.0, 0.0], dtype=a.dtype))
        if perp.norm() < 1e-6:
            perp = torch.linalg.cross(r0, torch.tensor([0.0, 1.0, 0.0], dtype=a.dtype))
        perp = perp / perp.norm()
        half = 2 * torch.outer(perp, perp) - torch.eye(3, dtype=a.dtype)
        rot = torch.where(opposite[..., None, None], half, rot)
    return rot


def compute_sampling(camera: Camera, in_hw: tuple[int, int], kernel_size: int | Pair, stride: int | Pair = 1,
                     padding: int | Pair = 0, dilation: int | Pair = 1, *, wrap: bool | None = None,
                     kernel: Literal["grid", "tangent"] = "grid",
                     rotation: Literal["auto", "upright", "axial"] = "auto",
                     image_padding: Pair = (0, 0)) -> tuple[Tensor, Tensor]:
    """Offsets and validity mask of a projected convolution (float64, CPU).

    Args:
        camera: the camera of the network's input image (any size; it is resized to ``in_hw``).
        in_hw: ``(H, W)`` of the feature map the convolution reads.
        kernel_size, stride, padding, dilation: as ``nn.Conv2d`` (int or pair).
        wrap: columns wrap around (360° cameras); ``None`` = ``camera.wraps_horizontally``.
            Without wrap, taps beyond the left/right border read zero.
        kernel: ``"grid"`` (default; exact pixel grid at the reference pixel) or ``"tangent"``
            (square lattice on the tangent plane), see the module docstring.
        rotation: ``"upright"``, ``"axial"`` or ``"auto"`` (upright for panoramas —
            :attr:`Camera.panoramic` — axial otherwise).
        image_padding: ``(pad_right, pad_bottom)`` pixels the calibrated image was padded with
            before the network (thesis Eq. 7.3); passed to ``camera.resized``.

    Returns:
        offsets ``(1, 2*kh*kw, Ho, Wo)`` in deform_conv2d layout (dy, dx per tap) and
        mask ``(1, kh*kw, Ho, Wo)`` (1 = valid sample, 0 = read zero), float64.
    """
    k, s, p, d = (_pair(kernel_size, "kernel_size"), _pair(stride, "stride"), _pair(padding, "padding"),
                  _pair(dilation, "dilation"))
    H, W = int(in_hw[0]), int(in_hw[1])
    Ho, Wo = output_size((H, W), k, s, p, d)
    if kernel not in ("grid", "tangent"):
        raise ValueError(f"kernel must be 'grid' or 'tangent', got {kernel!r}")
    if rotation not in ("auto", "upright", "axial"):
        raise ValueError(f"rotation must be 'auto', 'upright' or 'axial', got {rotation!r}")
    cam = camera.resized(W, H, pad_right=image_padding[0], pad_bottom=image_padding[1])
    if wrap is None:
        wrap = cam.wraps_horizontally
    if wrap and not cam.wraps_horizontally:
        raise ValueError(f"wrap=True needs a camera that covers 360° horizontally; {camera!r} does not")
    if rotation == "auto":
        rotation = "upright" if camera.panoramic else "axial"
    f64 = torch.float64
    kh, kw = k
    ti = (torch.arange(kh, dtype=f64) - kh // 2) * d[0]  # tap row displacement (pixels)
    tj = (torch.arange(kw, dtype=f64) - kw // 2) * d[1]
    gi, gj = torch.meshgrid(ti, tj, indexing="ij")  # (kh, kw)

    # reference kernel: unit directions (K, 3) in the camera frame
    p0, r0 = _reference(cam)
    frame0 = _upright_frame(r0) if rotation == "upright" else torch.eye(3, dtype=f64)
    if kernel == "grid":
        ref = cam.unproject(torch.stack([p0[0] + gj, p0[1] + gi], -1).reshape(-1, 2)).direction
    else:
        nb = cam.unproject(torch.stack([p0 + torch.tensor([d[1], 0.0], dtype=f64),
                                        p0 + torch.tensor([0.0, d[0]], dtype=f64)])).direction
        tx = math.tan(math.acos(min(1.0, float(nb[0] @ r0))))
        ty = math.tan(math.acos(min(1.0, float(nb[1] @ r0))))
        local = torch.stack([gj / d[1] * tx, gi / d[0] * ty, torch.ones_like(gi)], -1).reshape(-1, 3)
        local = local / local.norm(dim=-1, keepdim=True)
        basis = _upright_frame(r0) if rotation == "upright" else _axial_rotation(torch.tensor([0.0, 0.0, 1.0],
                                                                                            dtype=f64), r0)
        ref = local @ basis.T
    if not bool(torch.isfinite(ref).all()):
        raise ValueError(f"camera {camera!r}: the reference kernel around pixel {p0.tolist()} is not finite")
    ref_local = ref @ frame0  # coordinates in the reference frame (rows: K)

    # anchors at output positions (integer input indices of the kernel centre)
    ay = torch.arange(Ho, dtype=f64) * s[0] - p[0] + (kh // 2) * d[0]
    ax = torch.arange(Wo, dtype=f64) * s[1] - p[1] + (kw // 2) * d[1]
    AY, AX = torch.meshgrid(ay, ax, indexing="ij")  # (Ho, Wo)
    au = AX + 0.5
    if wrap:
        au = torch.remainder(au, W)
    rays = cam.unproject(torch.stack([au, AY + 0.5], -1))
    a = rays.direction
    anchor_ok = rays.valid & torch.isfinite(a).all(-1)
    a = torch.where(anchor_ok[..., None], a, r0.expand_as(a))
    if rotation == "upright":
        rot = _upright_frame(a)  # (Ho, Wo, 3, 3): reference frame -> anchor frame
    else:
        rot = _axial_rotation(r0, a)
    taps = torch.einsum("hwab,kb->hwka", rot, ref_local)  # (Ho, Wo, K, 3)
    uv, valid = _project_dirs(cam, taps)
    uv = torch.where(torch.isfinite(uv), uv, torch.zeros_like(uv))
    ty_, tx_ = uv[..., 1] - 0.5, uv[..., 0] - 0.5  # continuous input indices
    base_y = AY[..., None] + gi.reshape(-1)  # regular-grid tap indices (Ho, Wo, K)
    base_x = AX[..., None] + gj.reshape(-1)
    if cam.wraps_horizontally:  # nearest representative to the regular tap column
        tx_ = base_x + torch.remainder(tx_ - base_x + W / 2, W) - W / 2
        if not wrap:
            valid = valid & (tx_ > -1) & (tx_ < W)
    dy = ty_ - base_y
    dx = tx_ - base_x
    # invalid anchors: regular grid; taps on pixels the camera does not see read zero
    gu = base_x + 0.5
    if wrap:
        gu = torch.remainder(gu, W)
    grid_uv = torch.stack([gu, base_y + 0.5], -1)
    grid_ok = in_image(grid_uv, W, H) & cam.unproject(grid_uv).valid
    valid = torch.where(anchor_ok[..., None], valid, grid_ok)
    dy = torch.where(anchor_ok[..., None] & valid, dy, torch.zeros_like(dy))
    dx = torch.where(anchor_ok[..., None] & valid, dx, torch.zeros_like(dx))
    offsets = torch.stack([dy, dx], -1).reshape(Ho, Wo, 2 * kh * kw).permute(2, 0, 1).unsqueeze(0)
    mask = valid.to(f64).permute(2, 0, 1).unsqueeze(0)
    return offsets.contiguous(), mask.contiguous()


def compute_offsets(camera: Camera, in_hw: tuple[int, int], kernel_size: int | Pair, stride: int | Pair = 1,
                    padding: int | Pair = 0, dilation: int | Pair = 1, **kwargs) -> Tensor:
    """Offsets ``(1, 2*kh*kw, Ho, Wo)`` (float64) of a projected convolution; see :func:`compute_sampling`.

    Samples that must read zero (outside the camera's field of view or the image) have
    offset 0 here; use :func:`compute_sampling` to also get their mask (pass it to
    ``deform_conv2d(..., mask=mask)``).
    """
    return compute_sampling(camera, in_hw, kernel_size, stride, padding, dilation, **kwargs)[0]
