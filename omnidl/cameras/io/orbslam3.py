"""ORB-SLAM3 settings YAML (``cv::FileStorage``; reader and writer).

Keys (ORB-SLAM3's ``Settings.cc`` and the example ``Examples/*/*.yaml``): ``Camera.type`` ``"PinHole"`` or
``"KannalaBrandt8"``; intrinsics ``Camera1.fx, fy, cx, cy`` (file version 1.0) or ``Camera.fx ...`` (older
files); distortion ``Camera1.k1, k2, p1, p2[, k3]`` (PinHole, OpenCV order) or ``Camera1.k1..k4``
(KannalaBrandt8 = ``cv2.fisheye``); ``Camera.width``, ``Camera.height``. Stereo files also hold ``Camera2.*``
(``camera=2``).

PinHole -> ``pinhole`` (zero distortion) or ``opencv``; KannalaBrandt8 -> ``kannala_brandt`` with ``k0 = 1``.
Pixel convention: OpenCV's (first pixel centre ``(0, 0)``): omnidl's ``cx = Camera1.cx + 0.5`` (same for
``cy``); the writer subtracts 0.5.
"""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from ...utils.io import atomic_write_bytes
from ..base import Camera
from ._common import (OPENCV_SHIFT, family_of, make, positive_int, require_max_fov, require_zero, theta_poly_max_fov,
                      unsupported)
from .opencv_storage import parse

FORMAT = "orbslam3"
TYPES = ("PinHole", "KannalaBrandt8")
WRITES = ("pinhole", "opencv", "kannala_brandt")


def from_nodes(data: Mapping[str, Any], where: str, camera: int | None = None) -> Camera:
    """The camera ``camera`` (1 or 2; default 1) of parsed ORB-SLAM3 settings."""
    idx = 1 if camera is None else int(camera)
    prefixes = [f"Camera{idx}."] + (["Camera."] if idx == 1 else [])
    prefix = next((p for p in prefixes if f"{p}fx" in data), None)
    if prefix is None:
        raise ValueError(f"{where}: no {' or '.join(p + 'fx' for p in prefixes)} (camera {idx})")
    ctype = str(data.get("Camera.type", "PinHole")).strip('"')
    if ctype not in TYPES:
        raise ValueError(f"{where}: Camera.type {ctype!r} is not one of {TYPES}")

    def num(key: str, default: float | None = None) -> float:
        if prefix + key in data:
            val = data[prefix + key]
        elif default is not None:
            return default
        else:
            raise ValueError(f"{where}: missing {prefix}{key}")
        try:
            return float(val)
        except (TypeError, ValueError):
            raise ValueError(f"{where}: {prefix}{key} must be a number, got {val!r}") from None

    for key in ("Camera.width", "Camera.height"):
        if key not in data:
            raise ValueError(f"{where}: missing {key}")
    base = dict(width=positive_int(data["Camera.width"], where, "Camera.width"),
                height=positive_int(data["Camera.height"], where, "Camera.height"),
                fx=num("fx"), fy=num("fy"), cx=num("cx") + OPENCV_SHIFT, cy=num("cy") + OPENCV_SHIFT)
    if ctype == "KannalaBrandt8":
        k = [num(f"k{i}") for i in range(1, 5)]
        return make("kannala_brandt", where, **base, k0=1.0, k1=k[0], k2=k[1], k3=k[2], k4=k[3],
                    max_fov=theta_poly_max_fov({1: 1.0, 3: k[0], 5: k[1], 7: k[2], 9: k[3]}))
    d = {n: num(n, 0.0) for n in ("k1", "k2", "p1", "p2", "k3")}
    if not any(d.values()):
        return make("pinhole", where, **base)
    return make("opencv", where, **base, **d)


def read(path: str | Path, camera: int | None = None) -> Camera:
    """The camera of an ORB-SLAM3 settings file (``camera=2``: the second camera of a stereo rig)."""
    return from_nodes(parse(path), f"ORB-SLAM3 settings {str(path)!r}", camera)


def dumps(camera: Camera, path: str | Path) -> bytes:
    """The bytes :func:`write` writes (``path`` only picks the layout by its suffix)."""
    fam, c = family_of(camera), camera
    if fam not in WRITES:
        raise unsupported(FORMAT, c, WRITES)
    if fam == "kannala_brandt":
        if c.k0 != 1:
            raise unsupported(FORMAT, c, WRITES, f"KannalaBrandt8 has k0 = 1, got k0 = {c.k0}")
        require_max_fov(c, {1: 1.0, 3: c.k1, 5: c.k2, 7: c.k3, 9: c.k4}, FORMAT, WRITES,
                        "omnidl's reader of KannalaBrandt8")
        ctype, dist = "KannalaBrandt8", {f"k{i}": getattr(c, f"k{i}") for i in range(1, 5)}
    elif fam == "opencv":
        require_zero(c, ("k4", "k5", "k6", "s1", "s2", "s3", "s4"), FORMAT, WRITES)
        ctype, dist = "PinHole", {n: getattr(c, n) for n in ("k1", "k2", "p1", "p2")}
        if c.k3:
            dist["k3"] = c.k3
    else:
        ctype, dist = "PinHole", {n: 0.0 for n in ("k1", "k2", "p1", "p2")}
    vals = {"fx": c.fx, "fy": c.fy, "cx": c.cx - OPENCV_SHIFT, "cy": c.cy - OPENCV_SHIFT, **dist}
    lines = ["%YAML:1.0", "", 'File.version: "1.0"', "", f'Camera.type: "{ctype}"', ""]
    lines += [f"Camera1.{k}: {float(v)!r}" for k, v in vals.items()]
    lines += ["", f"Camera.width: {int(c.width)}", f"Camera.height: {int(c.height)}"]
    return ("\n".join(lines) + "\n").encode()


def write(camera: Camera, path: str | Path) -> None:
    """Write ``camera`` as ORB-SLAM3 settings (file version 1.0, ``Camera1.*`` keys; camera part only)."""
    atomic_write_bytes(path, dumps(camera, path))



def looks_like(data: Mapping[str, Any]) -> bool:
    return any(str(k).startswith(("Camera.", "Camera1.")) for k in data)
