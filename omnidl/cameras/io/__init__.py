"""Calibration interchange: :func:`load` any common calibration file as a :class:`Camera`, :func:`save` one.

Formats (one module each; see their docs for fields, model mapping and pixel convention):

===========  =========================================================  ===========================
format       files                                                      omnidl families
===========  =========================================================  ===========================
colmap       ``cameras.txt`` / ``cameras.bin`` (multi-camera: ``camera=``)  pinhole, opencv, kannala_brandt,
                                                                        fov, fisheye624, eucm, equirect
kalibr       ``camchain.yaml`` (multi-camera: ``camera='cam1'`` or ``1``)   pinhole, opencv, kannala_brandt,
                                                                        fov, unified, double_sphere, eucm
opencv       ``cv::FileStorage`` YAML/XML of ``calibrateCamera``,          pinhole, opencv, kannala_brandt,
             ``cv2.fisheye``, ``cv2.omnidir``                             unified
orbslam3     ORB-SLAM3 settings YAML (PinHole, KannalaBrandt8)           pinhole, opencv, kannala_brandt
ocamcalib    OCamCalib ``calib_results.txt``                             scaramuzza
kb_txt       ``cx cy fx fy W H FOV k1 k2 k3 k4`` text                    kannala_brandt
woodscape    WoodScape calibration JSON (``intrinsic`` block; read only)  woodscape
omnidl       omnidl's camera YAML (``{type: ..., **fields}``)            every registered family
===========  =========================================================  ===========================

Detection (:func:`detect_format`) uses the suffix and the content: ``.bin`` is COLMAP; a text file whose
first data line is ``ID MODEL W H ...`` is COLMAP, one with OCamCalib's comments is OCamCalib, eleven
numbers are the KB text; YAML/XML is ORB-SLAM3 (``Camera.*``/``Camera1.*`` keys), Kalibr (``camN`` nodes
with ``camera_model``), omnidl (``type``) or OpenCV (``camera_matrix``/``Camera_Matrix``/``K``...).

Safety and trust. Every YAML file is read with a safe loader: a tag that would construct a Python object
(``!!python/object``...) raises :class:`UnsafeYAMLError`. :func:`load` warns
(:class:`ImplausibleCalibrationWarning`) about a principal point outside the image or a ``max_fov`` under
10 deg (see :mod:`~omnidl.cameras.io._plausible`). :func:`save` is lossless or refuses: it writes to a
temporary file, reads it back and writes the destination only when the camera read back projects a dense
grid of directions to the same pixels with the same validity mask (:mod:`~omnidl.cameras.io._lossless`);
otherwise :class:`UnsupportedModelError` names what the format cannot hold (e.g. a 195 deg Kannala-Brandt
camera in COLMAP, Kalibr, OpenCV or ORB-SLAM3, whose models stop at 180 deg) and nothing is written.
"""
from __future__ import annotations

import os
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from ...utils.io import atomic_write_bytes
from ..base import Camera
from . import colmap, kalibr, kb_txt, ocamcalib, opencv_storage, orbslam3
from ._common import (OPENCV_SHIFT, ImplausibleCalibrationWarning, UnsafeYAMLError, UnsupportedModelError, family_of,
                      make, safe_yaml)
from ._lossless import check_round_trip
from ._plausible import check_plausible

FORMATS = ("colmap", "kalibr", "opencv", "orbslam3", "ocamcalib", "kb_txt", "woodscape", "omnidl")
#: suffixes :func:`load` (and ``resolve_camera``) treat as calibration files
SUFFIXES = (".txt", ".calib", ".dat", ".bin", ".yaml", ".yml", ".xml", ".json")
MULTI = ("colmap", "kalibr", "orbslam3")

__all__ = ["load", "load_all", "save", "detect_format", "FORMATS", "SUFFIXES", "OPENCV_SHIFT",
           "UnsupportedModelError", "UnsafeYAMLError", "ImplausibleCalibrationWarning"]


def detect_format(path: str | os.PathLike) -> str:
    """The format of a calibration file (one of :data:`FORMATS`), from its suffix and content."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"calibration file {str(path)!r} does not exist")
    if path.suffix.lower() == ".bin":
        return "colmap"
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise ValueError(f"calibration file {str(path)!r}: cannot read it as text ({e})") from None
    if colmap.looks_like(text):
        return "colmap"
    if ocamcalib.looks_like(text):
        return "ocamcalib"
    if kb_txt.looks_like(text):
        return "kb_txt"
    if text.lstrip().startswith("<"):
        return "opencv"
    try:
        data = opencv_storage.parse_yaml(text, f"calibration file {str(path)!r}")
    except UnsafeYAMLError:
        raise
    except ValueError:
        data = None
    if data is not None:
        if orbslam3.looks_like(data):
            return "orbslam3"
        if kalibr.looks_like(data):
            return "kalibr"
        if isinstance(data.get("intrinsic"), dict):
            return "woodscape"
        if "type" in data or (isinstance(data.get("camera"), dict) and "type" in data["camera"]):
            return "omnidl"
        if opencv_storage.looks_like(data):
            return "opencv"
    raise ValueError(f"calibration file {str(path)!r}: format not recognised; known formats: {list(FORMATS)} "
                     "(COLMAP cameras.txt/.bin, Kalibr camchain, OpenCV FileStorage, ORB-SLAM3 settings, "
                     "OCamCalib calib_results.txt, KB text, omnidl camera YAML); pass format= to say which")


def _read(path: Path, fmt: str, camera: Any, options: dict[str, Any]) -> Camera:
    if camera is not None and fmt not in MULTI:
        raise ValueError(f"camera={camera!r} selects a camera of a multi-camera file ({'/'.join(MULTI)}); "
                         f"{str(path)!r} is a {fmt} file with one camera")
    if fmt == "colmap":
        return colmap.read(path, camera)
    if fmt == "kalibr":
        return kalibr.read(path, camera)
    if fmt == "orbslam3":
        return orbslam3.read(path, camera)
    if fmt == "opencv":
        return opencv_storage.read(path, options.pop("file_image_size", None), options.pop("model", None))
    if fmt == "ocamcalib":
        return ocamcalib.read(path, options.pop("one_based", None))
    if fmt == "kb_txt":
        return kb_txt.read(path)
    if fmt == "woodscape":
        from ..woodscape import read_woodscape_json
        return make("woodscape", f"WoodScape calibration file {str(path)!r}", **read_woodscape_json(path))
    if fmt == "omnidl":
        from ..registry import build
        from ..resolve import _load_yaml
        safe_yaml(path.read_text(), f"camera YAML {str(path)!r}")  # refuses Python tags with a clear error
        return build(_load_yaml(path))  # OmegaConf's loader (a yaml.SafeLoader) for ${...} interpolations
    raise ValueError(f"unknown calibration format {fmt!r}; known: {list(FORMATS)}")


def _fit(cam: Camera, image_size: Any, size_policy: str | None, source: str | None) -> Camera:
    """``cam`` on an image of ``image_size = (W, H)`` (``resolve_camera``'s size semantics)."""
    if image_size is None:
        return cam
    w, h = (int(v) for v in image_size)
    try:
        from ..resolve import fit_camera_to_image
    except ImportError:  # pragma: no cover (older resolve without size policies)
        from ..resolve import check_image_size
        check_image_size((h, w), cam, "image")
        return cam if (cam.width, cam.height) == (w, h) else cam.resized(w, h)
    return fit_camera_to_image(cam, w, h, size_policy or "error", source, "image")


def load(path_or_spec: Any, image_size: tuple[int, int] | None = None, *, camera: Any = None,
         format: str | None = None, size_policy: str | None = None, **options: Any) -> Camera:
    """A :class:`Camera` from a calibration file of any supported format (or any ``resolve_camera`` spec).

    Args:
        path_or_spec: a calibration file (format detected, see :func:`detect_format`), or anything
            :func:`omnidl.cameras.resolve_camera` accepts (a ``Camera``, a config mapping, a config name).
        image_size: ``(W, H)`` of the images the camera is used with; a size that is not the calibrated
            image uniformly resized needs ``size_policy`` (``'pad'``, ``'crop'``, ``'scale'``), otherwise
            ``ValueError`` naming the file and both sizes.
        camera: which camera of a multi-camera file (COLMAP id, Kalibr ``'cam1'``/``1``, ORB-SLAM3 ``2``);
            default the first.
        format: one of :data:`FORMATS` to skip detection.
        options: format options: ``model=`` (OpenCV: ``'pinhole'``/``'fisheye'``/``'omnidir'``),
            ``file_image_size=(W, H)`` (OpenCV files without a size), ``one_based=`` (OCamCalib centre).
    """
    if not isinstance(path_or_spec, (str, os.PathLike)) or not Path(path_or_spec).is_file():
        if isinstance(path_or_spec, (str, os.PathLike)) and Path(path_or_spec).suffix.lower() in SUFFIXES:
            raise FileNotFoundError(f"calibration file {os.fspath(path_or_spec)!r} does not exist")
        if camera is not None or format is not None or options:
            raise ValueError(f"camera=/format=/options apply to calibration files, not to {path_or_spec!r}")
        from ..resolve import resolve_camera
        return _fit(resolve_camera(path_or_spec), image_size, size_policy, None)
    path = Path(path_or_spec)
    fmt = format or detect_format(path)
    cam = _read(path, fmt, camera, dict(options))
    check_plausible(cam, f"{fmt} calibration file {str(path)!r}")
    return _fit(cam, image_size, size_policy, str(path))


def load_all(path: str | os.PathLike, format: str | None = None) -> dict[Any, Camera]:
    """Every camera of a calibration file as ``{id: Camera}`` (single-camera formats: ``{0: camera}``)."""
    path = Path(path)
    fmt = format or detect_format(path)
    if fmt == "colmap":
        cams = dict(colmap.read_all(path))
    elif fmt == "kalibr":
        cams = dict(kalibr.read_all(path))
    else:
        cams = {0: _read(path, fmt, None, {})}
    for key, cam in cams.items():
        check_plausible(cam, f"{fmt} calibration file {str(path)!r} camera {key!r}")
    return cams


def _format_for(path: Path, camera: Any) -> str:
    name, suffix = path.name.lower(), path.suffix.lower()
    if suffix == ".bin" or name.endswith("cameras.txt"):
        return "colmap"
    if suffix == ".xml":
        return "opencv"
    if "camchain" in name and suffix in (".yaml", ".yml"):
        return "kalibr"
    if suffix in (".yaml", ".yml"):
        return "omnidl"
    if suffix == ".txt" and isinstance(camera, Camera) and family_of(camera) == "scaramuzza":
        return "ocamcalib"
    raise ValueError(f"save({str(path)!r}): cannot tell the format from the file name; pass format= (one of "
                     f"{list(FORMATS)})")


def _dumps(camera: Camera | Mapping[Any, Camera], path: Path, fmt: str) -> bytes:
    """The bytes of ``camera`` as a ``fmt`` file named like ``path``."""
    writers = {"colmap": colmap, "kalibr": kalibr, "opencv": opencv_storage, "orbslam3": orbslam3,
               "ocamcalib": ocamcalib, "kb_txt": kb_txt}
    if fmt in writers:
        return writers[fmt].dumps(camera, path)
    if fmt == "woodscape":
        first = next(iter(camera.values())) if isinstance(camera, Mapping) else camera
        raise UnsupportedModelError(f"format 'woodscape' is read-only in omnidl (no writer), cannot save this "
                                    f"{family_of(first)!r} camera; save it as 'omnidl' YAML or another format")
    import yaml
    return yaml.safe_dump(camera.to_config(), sort_keys=False).encode()


def _verify(camera: Camera | Mapping[Any, Camera], probe: Path, fmt: str) -> None:
    """Read ``probe`` back and check every camera with :func:`check_round_trip`."""
    cams = dict(camera) if isinstance(camera, Mapping) else {None: camera}
    try:
        if isinstance(camera, Mapping):
            back = load_all(probe, format=fmt)
            back = {k: back[int(k) if fmt == "colmap" else kalibr.node_name(k)] for k in cams}
        else:
            back = {None: _read(probe, fmt, None, {})}
    except (ValueError, KeyError) as e:
        first = next(iter(cams.values()))
        raise UnsupportedModelError(f"format {fmt!r} cannot hold this {family_of(first)!r} camera: the file it "
                                    f"would write does not read back ({e}); nothing was written") from None
    for key, cam in cams.items():
        check_round_trip(cam, back[key], fmt, "" if key is None else f"camera {key!r}")


def save(camera: Camera | Mapping[Any, Camera], path: str | os.PathLike, format: str | None = None) -> Path:
    """Write ``camera`` (COLMAP/Kalibr also ``{id: Camera}``) to ``path`` in ``format``; returns the path.

    ``format`` defaults from the name: ``*.bin``/``*cameras.txt`` COLMAP, ``*.xml`` OpenCV, ``*camchain*.yaml``
    Kalibr, other ``.yaml`` omnidl's camera YAML, ``.txt`` of a Scaramuzza camera OCamCalib.

    Lossless or refused: the file is written to a temporary folder first and read back; only when every camera
    read back sees what the given one sees (same projection of a dense grid of directions, validity mask
    included; :func:`~omnidl.cameras.io._lossless.check_round_trip`) is it written (atomically) to ``path``.
    A model the format cannot represent, or a camera it would change (a 195 deg fisheye cut to 180 deg, a
    dropped coefficient), raises :class:`UnsupportedModelError` naming the format, the model and what would
    change, and ``path`` is left untouched.
    """
    path = Path(path)
    fmt = format or _format_for(path, camera)
    if fmt not in FORMATS:
        raise ValueError(f"unknown calibration format {fmt!r}; known: {list(FORMATS)}")
    if isinstance(camera, Mapping) and fmt not in ("colmap", "kalibr"):
        raise ValueError(f"format {fmt!r} holds one camera; got a mapping of {len(camera)}")
    data = _dumps(camera, path, fmt)
    with tempfile.TemporaryDirectory(prefix="omnidl-save-") as tmp:
        probe = Path(tmp) / path.name
        probe.write_bytes(data)
        _verify(camera, probe, fmt)
    atomic_write_bytes(path, data)
    return path
