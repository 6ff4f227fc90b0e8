"""Lossless-or-refuse: does the camera read back from a written calibration file see what the original sees?

:func:`omnidl.cameras.io.save` writes every file to a temporary place first, reads it back with the same
reader and calls :func:`check_round_trip`; only a camera that passes is written to the destination. A camera
passes when the read-back camera is equal field by field, or else when both project a dense grid of
directions (points at two distances, so non-central cameras are covered) to the same pixels with the same
validity mask and unproject a lattice of pixels with the same validity mask. Pixels must agree to
:data:`PIXEL_TOL` (floating rounding only: formats that store a ratio of two numbers, such as COLMAP's
``DIVISION`` read as a Scaramuzza camera, can differ in the last bit of a parameter); a validity mask may
not change at all. Anything else raises :class:`UnsupportedModelError` naming the format, the family, the
fields that would change (old -> new value) and how many grid directions change.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any

import torch

from ..base import Camera
from ._common import UnsupportedModelError, family_of

#: largest pixel difference a lossless round trip may show (floating rounding of stored ratios)
PIXEL_TOL = 1e-9
#: directions of the grid (a Fibonacci sphere: evenly spread over the whole sphere)
N_DIRECTIONS = 12288
#: at most this many pixels per side of the unprojection lattice
LATTICE = 96


@functools.lru_cache(maxsize=4)
def direction_grid(n: int = N_DIRECTIONS) -> torch.Tensor:
    """``(n, 3)`` float64 unit directions evenly spread over the sphere (Fibonacci lattice) plus the six axes."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (1 + 5 ** 0.5) * i
    r = torch.sqrt(1 - z * z)
    grid = torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1)
    axes = torch.tensor([[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0]],
                        dtype=torch.float64)
    return torch.cat([grid, axes])


def pixel_lattice(camera: Camera, n: int = LATTICE) -> torch.Tensor:
    """``(m, 2)`` float64 pixels spread over the whole image (pixel centres of a coarser grid, edges included)."""
    nu, nv = min(n, camera.width), min(n, camera.height)
    u = (torch.arange(nu, dtype=torch.float64) + 0.5) * camera.width / nu
    v = (torch.arange(nv, dtype=torch.float64) + 0.5) * camera.height / nv
    edges_u = torch.tensor([0.0, camera.width - 1e-9], dtype=torch.float64)
    edges_v = torch.tensor([0.0, camera.height - 1e-9], dtype=torch.float64)
    uu, vv = torch.meshgrid(torch.cat([u, edges_u]), torch.cat([v, edges_v]), indexing="ij")
    return torch.stack([uu.reshape(-1), vv.reshape(-1)], -1)


def projection_difference(a: Camera, b: Camera) -> tuple[int, int, float]:
    """``(directions whose validity differs, pixels whose unprojection validity differs, max pixel difference
    where both are valid)`` of ``a`` and ``b`` over :func:`direction_grid` (at distances 1 and 7.25) and
    :func:`pixel_lattice` (of ``a``)."""
    d = direction_grid()
    pts = torch.cat([d, 7.25 * d])
    uv_a, ok_a = a.project(pts)
    uv_b, ok_b = b.project(pts)
    both = ok_a & ok_b
    du = float((uv_a[both] - uv_b[both]).abs().max()) if bool(both.any()) else 0.0
    n_dir = int((ok_a != ok_b).sum())
    if (a.width, a.height) != (b.width, b.height):
        return n_dir, a.width * a.height, du
    px = pixel_lattice(a)
    n_pix = int((a.unproject(px).valid != b.unproject(px).valid).sum())
    return n_dir, n_pix, du


def _changed_fields(a: Camera, b: Camera) -> dict[str, tuple[Any, Any]]:
    if type(a) is not type(b):
        return {"family": (family_of(a), family_of(b))}
    return {f.name: (getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a)
            if getattr(a, f.name) != getattr(b, f.name)}


def _show(name: str, old: Any, new: Any) -> str:
    if "fov" in name and isinstance(old, float) and isinstance(new, float):
        return f"{name} {math.degrees(old):.6g} deg -> {math.degrees(new):.6g} deg"
    return f"{name} {old!r} -> {new!r}"


def check_round_trip(camera: Camera, back: Camera, fmt: str, where: str = "") -> None:
    """Raise :class:`UnsupportedModelError` unless ``back`` (read from the written file) sees what ``camera`` sees."""
    if back == camera:
        return
    n_dir, n_pix, du = projection_difference(camera, back)
    if n_dir == 0 and n_pix == 0 and du <= PIXEL_TOL:
        return
    changed = _changed_fields(camera, back)
    what = ", ".join(_show(k, *v) for k, v in changed.items()) or "no field (numerical difference only)"
    at = f" ({where})" if where else ""
    raise UnsupportedModelError(
        f"format {fmt!r} cannot hold this {family_of(camera)!r} camera losslessly{at}: reading the file back "
        f"would change {what}; {n_dir} of {2 * len(direction_grid())} grid directions change validity, "
        f"{n_pix} lattice pixels change validity, pixels move by up to {du:.3g} px. Nothing was written; save "
        "it as 'omnidl' camera YAML (holds every family exactly) or to a format that holds this model")
