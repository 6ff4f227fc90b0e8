"""Kannala–Brandt calibration text (CalibratedConvolutions): ``cx cy fx fy W H FOV k1 k2 k3 k4``.

Adapter to :func:`omnidl.cameras.read_kb_calibration` (``k0 = 1``, FOV in degrees) and its writer.
Pixel convention: the file's centre is used as omnidl's as is (the existing reader's convention).

The FOV is in degrees: a value under 10 deg (:data:`~omnidl.cameras.io._common.MIN_FOV_DEG`) is refused as
probably radians (``ValueError`` naming the file, the value and its reading in radians). The writer picks
the decimal FOV that reads back to the camera's ``max_fov`` bit for bit when one exists (otherwise the
nearest, one unit in the last place away).
"""
from __future__ import annotations

import math
from pathlib import Path

from ...utils.io import atomic_write_bytes
from ..base import Camera
from ._common import family_of, make, unsupported

FORMAT = "kb_txt"


def read(path: str | Path) -> Camera:
    from ..kannala_brandt import read_kb_calibration
    where = f"Kannala-Brandt calibration file {str(path)!r}"
    fields = read_kb_calibration(path)          # refuses a FOV under MIN_FOV_DEG (probably radians)
    return make("kannala_brandt", where, **fields)


def fov_degrees(max_fov: float) -> float:
    """A float ``d`` with ``math.radians(d) == max_fov`` when one exists near ``degrees(max_fov)``, else the nearest."""
    d = math.degrees(max_fov)
    for cand in (d, math.nextafter(d, math.inf), math.nextafter(d, -math.inf)):
        if math.radians(cand) == max_fov:
            return cand
    return d


def dumps(camera: Camera, path: str | Path) -> bytes:
    """The bytes :func:`write` writes (``path`` only picks the layout by its suffix)."""
    if family_of(camera) != "kannala_brandt":
        raise unsupported(FORMAT, camera, ("kannala_brandt",))
    c = camera
    if c.k0 != 1:
        raise unsupported(FORMAT, c, ("kannala_brandt",), f"the file format has k0 = 1, got k0 = {c.k0}")
    vals = [c.cx, c.cy, c.fx, c.fy, c.width, c.height, fov_degrees(c.max_fov), c.k1, c.k2, c.k3, c.k4]
    return ("\n".join(repr(v) if isinstance(v, float) else str(v) for v in vals) + "\n").encode()


def write(camera: Camera, path: str | Path) -> None:
    """Write a ``kannala_brandt`` camera with ``k0 = 1`` as the eleven-number text file."""
    atomic_write_bytes(path, dumps(camera, path))



def looks_like(text: str) -> bool:
    try:
        return len([float(t) for t in text.replace(",", " ").split()]) == 11
    except ValueError:
        return False
