"""Cube maps: equirectangular -> 6 perspective faces and back (or to any central camera).

Face order and orientation (the same as py360convert's ``F R B L U D`` "dice" layout):

=====  =======  ===================  ==========================  =========================
index  name     looks along (camera)  ``R_pano_face`` (roll, pitch, yaw)  face image "up" is
=====  =======  ===================  ==========================  =========================
0      front    ``+z``               (0, 0, 0)                    ``-y`` (up)
1      right    ``+x``               yaw +90°                     ``-y``
2      back     ``-z``               yaw 180°                     ``-y``
3      left     ``-x``               yaw -90°                     ``-y``
4      up       ``-y``               pitch +90°                   ``-z`` (its bottom edge meets front)
5      down     ``+y``               pitch -90°                   ``+z`` (its top edge meets front)
=====  =======  ===================  ==========================  =========================

Each face is a :class:`~omnidl.cameras.Pinhole` ``F x F`` camera with a 90° field of view
(``f = F / 2``, principal point ``(F/2, F/2)``, pixel centres at ``j + 0.5``), rotated by
``R_pano_face`` (a face-frame direction ``d`` is ``R_pano_face @ d`` in the panorama frame),
so the six faces tile the sphere exactly. Angles follow :func:`~omnidl.geometry.rotations.euler_to_matrix`.

Cube maps are tensors ``(B, 6, C, F, F)`` in that face order.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from omnidl.cameras.base import Camera
from omnidl.cameras.equirectangular import Equirectangular
from omnidl.cameras.pinhole import Pinhole

from .rotations import euler_to_matrix
from .warp import WarpGrid, _as_bchw, _check_rotation, sample_grid, warp_grid

FACE_NAMES = ("front", "right", "back", "left", "up", "down")
#: (roll, pitch, yaw) in degrees of every face, in FACE_NAMES order
FACE_EULER_DEG = ((0, 0, 0), (0, 0, 90), (0, 0, 180), (0, 0, -90), (0, 90, 0), (0, -90, 0))


def cube_face_rotations(dtype: torch.dtype = torch.float32, device=None) -> Tensor:
    """``(6, 3, 3)`` ``R_pano_face`` of the faces in :data:`FACE_NAMES` order (exact 0/±1 entries)."""
    ang = torch.tensor(FACE_EULER_DEG, dtype=torch.float64) * (math.pi / 180)
    R = euler_to_matrix(ang[:, 0], ang[:, 1], ang[:, 2]).round()  # entries are exactly 0, +-1
    return R.to(dtype=dtype, device=device)


def cube_face_camera(face_size: int) -> Pinhole:
    """The ``F x F`` 90° pinhole camera of every face."""
    if int(face_size) < 1:
        raise ValueError(f"face_size must be a positive integer, got {face_size}")
    f = face_size / 2
    return Pinhole(width=int(face_size), height=int(face_size), fx=f, fy=f, cx=f, cy=f)


def equirect_to_cubemap(image: Tensor, face_size: int, mode: str = "bilinear", camera: Camera | None = None,
                        face_camera: Camera | None = None) -> Tensor:
    """Six cube faces from a panorama.

    Args:
        image: ``(B, C, H, W)`` (or ``(C, H, W)``) panorama.
        face_size: ``F``.
        mode: ``"bilinear"`` or ``"nearest"`` (labels).
        camera: the panorama's central camera (default: full equirect of the image size).
        face_camera: override the face camera (e.g. to match another library's pixel grid).

    Returns:
        ``(B, 6, C, F, F)`` (``(6, C, F, F)`` for an unbatched image).
    """
    x, ndim = _as_bchw(image)
    if ndim == 2:
        raise ValueError(f"image must have shape (B, C, H, W) or (C, H, W), got {tuple(image.shape)}")
    b, c, h, w = x.shape
    camera = camera or Equirectangular(width=w, height=h)
    face_camera = face_camera or cube_face_camera(face_size)
    dtype = x.dtype if x.is_floating_point() else torch.float32
    grid = warp_grid(camera, face_camera, cube_face_rotations(torch.float64, x.device), dtype=dtype,
                     device=x.device)  # (6, F, F)
    rep = WarpGrid(grid.uv.repeat(b, 1, 1, 1), grid.valid.repeat(b, 1, 1), grid.src_width, grid.src_height,
                   grid.wrap)
    xx = x.unsqueeze(1).expand(b, 6, c, h, w).reshape(b * 6, c, h, w)
    out, _ = sample_grid(xx, rep, mode)
    out = out.reshape(b, 6, c, *out.shape[-2:])
    return out if ndim == 4 else out[0]


def cubemap_to_camera(faces: Tensor, dst_camera: Camera, rotation: Tensor | None = None, mode: str = "bilinear",
                      face_camera: Camera | None = None) -> tuple[Tensor, Tensor]:
    """Render any camera from a cube map (the cube map plays the central source camera).

    Args:
        faces: ``(B, 6, C, F, F)`` (or ``(6, C, F, F)``) in :data:`FACE_NAMES` order.
        dst_camera: camera to render (non-central ones use ray directions only).
        rotation: ``R_cube_dst`` ``(3, 3)`` or ``(B, 3, 3)`` as in :func:`~omnidl.geometry.reproject`.
        mode: ``"bilinear"`` or ``"nearest"``. Each output pixel samples the one face its ray
            hits (the largest forward component); bilinear taps at face borders repeat the
            face's border pixels.
        face_camera: override the face camera (default :func:`cube_face_camera`).

    Returns:
        ``(image (B, C, Hd, Wd), valid (B, 1, Hd, Wd))`` — valid wherever ``dst_camera`` has a ray.
    """
    if faces.dim() == 4:
        out, valid = cubemap_to_camera(faces.unsqueeze(0), dst_camera, rotation, mode, face_camera)
        return out[0], valid[0]
    if faces.dim() != 5 or faces.shape[1] != 6 or faces.shape[-1] != faces.shape[-2]:
        raise ValueError(f"faces must have shape (B, 6, C, F, F), got {tuple(faces.shape)}")
    b, _, c, fs, _ = faces.shape
    face_camera = face_camera or cube_face_camera(fs)
    if (face_camera.width, face_camera.height) != (fs, fs):
        raise ValueError(f"face_camera is {face_camera.width}x{face_camera.height} but the faces are {fs}x{fs}")
    dtype = faces.dtype if faces.is_floating_point() else torch.float32
    if isinstance(rotation, Tensor) and rotation.dtype == torch.float64:
        dtype = torch.float64
    rays = dst_camera.unproject_grid(dtype=dtype, device=faces.device)
    d = rays.direction.unsqueeze(0)
    rotation = _check_rotation(rotation, dtype, faces.device)
    if rotation is not None:
        rot = rotation if rotation.dim() == 3 else rotation.unsqueeze(0)
        d = torch.einsum("bij,bhwj->bhwi", rot, d)
    Rf = cube_face_rotations(dtype, faces.device)  # (6, 3, 3)
    local = torch.einsum("kji,bhwj->kbhwi", Rf, d)  # face-frame directions
    face = local[..., 2].argmax(0)  # (Bg, Hd, Wd)
    bg = d.shape[0]
    if b != bg and b != 1 and bg != 1:
        raise ValueError(f"cube map batch {b} and rotation batch {bg} do not broadcast")
    out = None
    for k in range(6):
        # keep the (finite) pinhole pixel even where it leaves the face: border taps clamp
        uv, _ = face_camera.project(torch.where(local[k][..., 2:] > 0, local[k], torch.ones_like(local[k])))
        sel = face == k
        grid = WarpGrid(uv, sel, fs, fs, False)
        o, _ = sample_grid(faces[:, k], grid, mode)
        out = o if out is None else out + o
    valid = rays.valid.unsqueeze(0).expand(max(b, bg), -1, -1).unsqueeze(1)
    out = torch.where(valid, out, torch.zeros((), dtype=out.dtype, device=out.device))
    return out, valid


def cubemap_to_equirect(faces: Tensor, width: int, height: int, mode: str = "bilinear",
                        face_camera: Camera | None = None) -> Tensor:
    """Panorama ``(B, C, height, width)`` from a cube map ``(B, 6, C, F, F)`` (full equirect camera)."""
    out, _ = cubemap_to_camera(faces, Equirectangular(width=int(width), height=int(height)), mode=mode,
                               face_camera=face_camera)
    return out
