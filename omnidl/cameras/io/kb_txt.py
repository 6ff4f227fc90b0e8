"""Kannala–Brandt calibration text (CalibratedConvolutions): ``cx cy fx fy W H FOV k1 k2 k3 k4``.

Adapter to :func:`omnidl.cameras.read_kb_calibration` (``k0 = 1``, FOV in degrees) and its writer.
Pixel convention: the file's centre is used as omnidl's as is (the existing reader's convention).
"""
from __future__ import annotations

import math
from pathlib import Path

from ...utils.io import atomic_write_text
from ..base import Camera
from ._common import family_of, make, unsupported

FORMAT = "kb_txt"


def read(path: str | Path) -> Camera:
    from ..kannala_brandt import read_kb_calibration
    return make("kannala_brandt", f"Kannala-Brandt calibration file {str(path)!r}", **read_kb_calibration(path))


def write(camera: Camera, path: str | Path) -> None:
    """Write a ``kannala_brandt`` camera with ``k0 = 1`` as the eleven-number text file."""
    if family_of(camera) != "kannala_brandt":
        raise unsupported(FORMAT, camera, ("kannala_brandt",))
    c = camera
    if c.k0 != 1:
        raise unsupported(FORMAT, c, ("kannala_brandt",), f"the file format has k0 = 1, got k0 = {c.k0}")
    vals = [c.cx, c.cy, c.fx, c.fy, c.width, c.height, math.degrees(c.max_fov), c.k1, c.k2, c.k3, c.k4]
    atomic_write_text(path, "\n".join(repr(v) if isinstance(v, float) else str(v) for v in vals) + "\n")


def looks_like(text: str) -> bool:
    try:
        return len([float(t) for t in text.replace(",", " ").split()]) == 11
    except ValueError:
        return False
