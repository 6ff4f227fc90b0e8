"""Matterport3D skybox images stitched to an equirectangular panorama (through :mod:`omnidl.geometry` warping).

Files (the Matterport3D release)::

    <root>/<scene>/matterport_skybox_images/<pano_uuid>_skybox<k>_sami.jpg      k = 0..5, square, 90° faces

Face geometry (as the stitching scripts of PanoBasic / UniFuse's ``stitch.m`` use it): face ``k`` looks at
longitude ``yaw_k`` and latitude ``pitch_k`` with a 90° field of view,
``yaw = (-90, -90, 0, 90, 180, -90)°`` and ``pitch = (90, 0, 0, 0, 0, -90)°``: 0 is the top, 1-4 the side
views, 5 the bottom; the top and bottom faces are the face-1 view pitched up / down (their image's bottom /
top edge meets face 1). In omnidl's frame (longitude grows to the right, +x at +90°), the rotation of face
``k`` is ``R_pano_face = rotation_y(yaw_k) @ rotation_x(pitch_k)`` (``rotation_x(+90°)`` turns the optical
axis ``+z`` to up ``-y``), each face a :func:`~omnidl.geometry.cubemap.cube_face_camera`.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from torch import Tensor

from ..cameras import Equirectangular
from ..geometry.cubemap import cube_face_camera
from ..geometry.rotations import rotation_x, rotation_y
from ..geometry.warp import WarpGrid, sample_grid
from .validate import invalid, read_image

#: (yaw, pitch) in degrees of skybox faces 0..5
SKYBOX_VIEWS = ((-90.0, 90.0), (-90.0, 0.0), (0.0, 0.0), (90.0, 0.0), (180.0, 0.0), (-90.0, -90.0))


def skybox_rotations(dtype: torch.dtype = torch.float64) -> Tensor:
    """``(6, 3, 3)`` ``R_pano_face`` of the six skybox faces (exact 0/±1 entries)."""
    R = [rotation_y(torch.tensor(math.radians(y), dtype=torch.float64))
         @ rotation_x(torch.tensor(math.radians(p), dtype=torch.float64)) for y, p in SKYBOX_VIEWS]
    return torch.stack(R).round().to(dtype)


def stitch_skybox(faces: Tensor, width: int, height: int, mode: str = "bilinear") -> Tensor:
    """Equirectangular ``(C, height, width)`` from skybox faces ``(6, C, F, F)`` (face order 0..5 above).

    Every output pixel samples the face its ray hits (largest forward component); bilinear taps at a face
    border repeat the border pixels."""
    if faces.dim() != 4 or faces.shape[0] != 6 or faces.shape[-1] != faces.shape[-2]:
        raise ValueError(f"stitch_skybox: expected faces (6, C, F, F), got {tuple(faces.shape)}")
    fs = faces.shape[-1]
    cam = cube_face_camera(fs)
    dtype = faces.dtype if faces.is_floating_point() else torch.float32
    d = Equirectangular(width=int(width), height=int(height)).unproject_grid(dtype=dtype).direction  # (H, W, 3)
    Rf = skybox_rotations(dtype)
    local = torch.einsum("kji,hwj->khwi", Rf, d)                        # R^T d: face-frame directions
    face = local[..., 2].argmax(0)
    out = None
    for k in range(6):
        uv, _ = cam.project(torch.where(local[k][..., 2:] > 0, local[k], torch.ones_like(local[k])))
        grid = WarpGrid(uv[None], (face == k)[None], fs, fs, False)
        o, _ = sample_grid(faces[k][None].to(dtype), grid, mode)
        out = o if out is None else out + o
    return out[0]


def skybox_files(folder: str | Path, pano: str) -> list[Path]:
    """The six ``<pano>_skybox<k>_sami.jpg`` files of a panorama (missing ones are an error naming them)."""
    folder = Path(folder)
    files = [folder / f"{pano}_skybox{k}_sami.jpg" for k in range(6)]
    missing = [str(f) for f in files if not f.is_file()]
    if missing:
        raise FileNotFoundError(f"Matterport3D skybox {pano}: missing {missing}")
    return files


def read_skybox(files: Sequence[str | Path]) -> Tensor:
    """``(6, 3, F, F)`` float32 RGB in ``[0, 1]``; every face must be square and of the same size."""
    arrs, first = [], None
    for f in files:
        a = read_image(f, "skybox face", channels=3)
        if a.shape[0] != a.shape[1]:
            raise invalid(f, "skybox face", f"{a.shape[1]}x{a.shape[0]}", "a square image")
        first = first or a.shape
        if a.shape != first:
            raise invalid(f, "skybox face", f"{a.shape[1]}x{a.shape[0]}", f"{first[1]}x{first[0]} (the size of face 0)")
        scale = 65535.0 if a.dtype == np.uint16 else 255.0
        arrs.append(torch.from_numpy(a.astype(np.float32) / scale).permute(2, 0, 1))
    return torch.stack(arrs)


class Matterport3DSkybox(torch.utils.data.Dataset):
    """Panoramas stitched from Matterport3D skyboxes: ``{"image" (3, H, W), "meta"}`` (no labels).

    Args:
        root: the Matterport3D release root; scenes: scene ids (default: every ``<scene>/matterport_skybox_images``).
        height, width: output panorama size.
    """

    def __init__(self, root: str | Path, scenes: list[str] | None = None, height: int = 512, width: int = 1024,
                 max_samples: int | None = None) -> None:
        self.root = Path(root).expanduser()
        if not self.root.is_dir():
            raise FileNotFoundError(f"Matterport3DSkybox: dataset root {self.root} does not exist")
        if scenes is None:
            scenes = sorted(p.name for p in self.root.iterdir() if (p / "matterport_skybox_images").is_dir())
        self.items: list[tuple[str, str, Path]] = []
        for sc in scenes:
            d = self.root / sc / "matterport_skybox_images"
            if not d.is_dir():
                raise FileNotFoundError(f"Matterport3DSkybox: scene {sc!r} has no {d}")
            panos = sorted({p.name.split("_skybox")[0] for p in d.glob("*_skybox*_sami.jpg")})
            self.items += [(sc, p, d) for p in panos]
        if not self.items:
            raise FileNotFoundError(f"Matterport3DSkybox: no *_skybox<k>_sami.jpg under {self.root}")
        if max_samples:
            self.items = self.items[: int(max_samples)]
        self.height, self.width = int(height), int(width)

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> dict[str, Any]:
        sc, pano, d = self.items[i]
        img = stitch_skybox(read_skybox(skybox_files(d, pano)), self.width, self.height).clamp(0, 1)
        return {"image": img, "meta": {"name": f"{sc}_{pano}", "scene": sc, "index": int(i),
                                       "dataset": "matterport3d_skybox"}}
