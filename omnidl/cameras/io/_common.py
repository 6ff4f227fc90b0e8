"""Shared helpers of the calibration readers/writers: lazy model construction, field access, errors.

Pixel conventions. omnidl puts the centre of pixel ``(i, j)`` at ``(j + 0.5, i + 0.5)`` (see
:mod:`omnidl.cameras.base`); COLMAP does the same. OpenCV, Kalibr and ORB-SLAM3 put the centre of the
first pixel at ``(0, 0)``, so their principal point is read as ``c_omnidl = c_file + 0.5`` and written as
``c_file = c_omnidl - 0.5`` (:data:`OPENCV_SHIFT`; the half-pixel adapter of ``docs/fisheye.md``).
Focal lengths and distortion coefficients are unchanged.
"""
from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Iterable, Mapping
from typing import Any

from ..base import Camera, ResizedCamera
from ..registry import construct, get_camera_class

#: add to an OpenCV/Kalibr/ORB-SLAM3 principal point to get omnidl's (pixel centres at +0.5)
OPENCV_SHIFT = 0.5
#: a full field of view below this (degrees) is implausible for the fisheye families: likely radians
MIN_FOV_DEG = 10.0


class UnsupportedModelError(ValueError):
    """A camera model that a calibration format cannot represent (or a model family omnidl lacks)."""


class UnsafeYAMLError(ValueError):
    """A YAML calibration file uses a tag that would construct a Python object (refused: safe loading only)."""


class ImplausibleCalibrationWarning(UserWarning):
    """A calibration that loads but is probably wrong (a principal point outside the image, a FOV under
    10 degrees ...); the message names the file, the field, the value and what was expected."""


# -- YAML: one safe loader for every YAML calibration file ----------------------------------------------
_OPENCV_DIRECTIVE = re.compile(r"\A(\s*(#[^\n]*)?\n)*%YAML[: ]1\.\d+[ \t]*\n")


def safe_yaml(text: str, where: str) -> Any:
    """``yaml.safe_load(text)``: plain mappings, lists, numbers and strings only.

    OpenCV's ``%YAML:1.0`` directive (``cv::FileStorage``; VIO datasets ship Kalibr camchains with it) is
    accepted. A tag that would build a Python object (``!!python/object``, ``!!python/name`` ...) raises
    :class:`UnsafeYAMLError`; other syntax errors ``ValueError``; both name ``where``.
    """
    import yaml
    body = _OPENCV_DIRECTIVE.sub("", text, count=1)
    try:
        return yaml.safe_load(body)
    except yaml.constructor.ConstructorError as e:
        tag = re.search(r"tag '([^']+)'", str(e))
        name = tag.group(1).replace("tag:yaml.org,2002:", "!!") if tag else "?"
        raise UnsafeYAMLError(f"{where}: refused: the YAML tag {name!r} would construct a Python object; "
                              "calibration files are read with a safe loader (mappings, lists, numbers and "
                              "strings only)") from None
    except yaml.YAMLError as e:
        raise ValueError(f"{where}: cannot parse it as YAML ({e})") from None


def make(family: str, where: str, **fields: Any) -> Camera:
    """Build the registered camera ``family`` from ``fields`` (the class is looked up lazily).

    ``where`` names the file/entry for error messages.
    """
    try:
        cls = get_camera_class(family)
    except KeyError as e:
        raise UnsupportedModelError(f"{where}: needs the omnidl camera model {family!r}, which is not "
                                    f"registered in this omnidl ({e.args[0]})") from None
    try:
        return construct(cls, {k: float(v) if isinstance(v, (int, float)) and k not in ("width", "height")
                               else v for k, v in fields.items()})
    except (TypeError, ValueError) as e:
        raise ValueError(f"{where}: invalid {family} calibration: {e}") from e


def family_of(camera: Camera) -> str:
    """The registry name of ``camera`` (``'resized'`` for a :class:`ResizedCamera`)."""
    return "resized" if isinstance(camera, ResizedCamera) else type(camera).name


def values(camera: Camera) -> dict[str, Any]:
    """The dataclass fields of ``camera`` as a dict."""
    return {f.name: getattr(camera, f.name) for f in dataclasses.fields(camera)}


def unsupported(fmt: str, camera: Camera, supported: Iterable[str], why: str = "") -> UnsupportedModelError:
    extra = f" ({why})" if why else ""
    return UnsupportedModelError(f"format {fmt!r} cannot represent a {family_of(camera)!r} camera{extra}; it "
                                 f"writes {', '.join(sorted(supported))}")


def require_zero(camera: Camera, names: Iterable[str], fmt: str, supported: Iterable[str]) -> None:
    nonzero = {n: getattr(camera, n) for n in names if getattr(camera, n) != 0}
    if nonzero:
        raise unsupported(fmt, camera, supported, f"it has no place for the non-zero {nonzero}")


def theta_poly_max_fov(coeffs: Mapping[int, float], theta_limit: float = math.pi / 2) -> float:
    """Full FOV ``2 * theta_max`` (<= ``2 * theta_limit``) on which ``d(theta) = sum c_n theta^n`` increases.

    Formats whose models project through ``atan(r)`` on the normalised plane (COLMAP, Kalibr, ORB-SLAM3,
    OpenCV) only see ``theta < 90 deg``; omnidl's Kannala–Brandt/Fisheye624 need a ``max_fov`` on which
    ``d`` is increasing, so it is ``pi`` unless ``d'`` reaches 0 before 90 deg (then just below that).
    """
    import numpy as np
    n = 20000
    t = theta_limit * np.arange(1, n + 1, dtype=np.float64) / n  # the grid theta_limit * i / n, i = 1..n
    deriv = np.zeros(n)
    for k, c in coeffs.items():
        deriv = deriv + k * c * t ** (k - 1)
    bad = np.flatnonzero(deriv <= 0)
    if bad.size == 0:
        return 2 * theta_limit
    if bad[0] == 0:
        raise ValueError(f"theta polynomial {dict(coeffs)} does not increase at theta = 0")
    return 2 * float(t[bad[0] - 1]) * (1 - 1e-9)


def require_max_fov(camera: Camera, coeffs: Mapping[int, float], fmt: str, supported: Iterable[str],
                    model: str) -> None:
    """Refuse a fisheye ``camera`` whose ``max_fov`` is wider than what the file implies when read back.

    The formats hold no field of view: their readers give ``theta_poly_max_fov(coeffs)`` (at most 180 deg,
    ``model`` sees only ``theta < 90 deg``). A wider ``max_fov`` would come back narrower (a 195 deg lens
    silently cut to 180 deg), so it is refused here; a narrower one is left to the round-trip check of
    :func:`omnidl.cameras.io.save` (it is lossless when the extra directions fall outside the image)."""
    implied = theta_poly_max_fov(coeffs)
    if camera.max_fov > implied:
        raise unsupported(fmt, camera, supported, f"max_fov = {math.degrees(camera.max_fov):.6g} deg does not fit: "
                          f"{model} sees only points in front of the camera (theta < 90 deg) and the file has "
                          f"no field of view, so it would read back with max_fov = {math.degrees(implied):.6g} deg; "
                          "save it as 'omnidl' camera YAML or 'kb_txt' (they hold max_fov)")


def positive_int(value: Any, where: str, name: str) -> int:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: {name} must be a positive integer, got {value!r}") from None
    if v != int(v) or v <= 0:
        raise ValueError(f"{where}: {name} must be a positive integer, got {value!r}")
    return int(v)


def select(entries: Mapping[Any, Any], camera: Any, where: str) -> Any:
    """``entries[camera]`` (the first entry for ``None``); clear error listing the ids."""
    if not entries:
        raise ValueError(f"{where}: holds no camera")
    if camera is None:
        return next(iter(entries.values()))
    for key in (camera, str(camera)):
        if key in entries:
            return entries[key]
    if isinstance(camera, str) and camera.lstrip("-").isdigit() and int(camera) in entries:
        return entries[int(camera)]
    raise KeyError(f"{where}: no camera {camera!r}; it holds {list(entries)}")
