"""The one validation layer of every dataset reader: read a file, check what is in it, or raise an error that
names the file, the field, the value found and what was expected.

Errors (both are :class:`~omnidl.data.robust.CorruptSampleError`, so :class:`~omnidl.data.robust.SkipCorrupt`
turns them into a flagged skip during training; called directly they are plain errors):

* :class:`UnreadableFileError` (also an ``OSError``): missing, empty, undecodable or truncated file;
* :class:`DataValidationError` (also a ``ValueError``): the file reads but its content is wrong (size,
  channels, bit depth, shape, NaN/inf, value out of range).

Readers: :func:`read_bytes`, :func:`read_raw` (bytes -> OpenCV array, EXIF orientation applied),
:func:`read_image` (channels / bit depth / size checked),
:func:`load_npy` (shape, dtype, finite), :func:`read_text` (UTF-8 text). Checks on arrays already in memory:
:func:`check_shape`, :func:`check_size`, :func:`check_finite`, :func:`check_range`, :func:`check_class_ids`,
:func:`check_label_cor` (HorizonNet ``label_cor`` corners). Every function takes ``path`` (the file the array
came from) and ``field`` (what it is, e.g. ``"depth_coded"``) only to write the message.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from .robust import CorruptSampleError

__all__ = ["DataValidationError", "UnreadableFileError", "invalid", "read_bytes", "decode_raw", "read_raw",
           "read_image", "load_npy", "read_text", "check_shape", "check_size", "check_finite", "check_range", "check_class_ids",
           "check_label_cor", "check_depth_units", "DEPTH_MEDIAN_RANGE"]

_PNG_END = b"IEND\xaeB`\x82"


class UnreadableFileError(CorruptSampleError, OSError):
    """A file is missing, empty, truncated or cannot be decoded; the message names it."""


class DataValidationError(CorruptSampleError, ValueError):
    """A file reads but holds the wrong thing; the message names file, field, value and expectation."""


def invalid(path: str | Path, field: str, got: object, expected: str) -> DataValidationError:
    """The error ``"<path>: <field> is <got>, expected <expected>"`` (returned, for ``raise invalid(...)``)."""
    return DataValidationError(f"{path}: {field} is {got}, expected {expected}")


def _describe(arr: np.ndarray) -> str:
    ch = 1 if arr.ndim == 2 else arr.shape[2]
    return f"{arr.shape[1]}x{arr.shape[0]} {ch}-channel {arr.dtype}"


# ------------------------------------------------------------------------------------------------
# readers
# ------------------------------------------------------------------------------------------------

def _max_pixels() -> int:
    """OpenCV's decode limit: the environment variable ``OPENCV_IO_MAX_IMAGE_PIXELS`` (read by OpenCV), else 2^30."""
    try:
        return int(os.environ.get("OPENCV_IO_MAX_IMAGE_PIXELS", 1 << 30))
    except ValueError:
        return 1 << 30


def read_bytes(path: str | Path, field: str = "file") -> bytes:
    """Every byte of a file, read by Python (so a name of any bytes works, never passed to OpenCV).

    A missing, unreadable or empty file is an :class:`UnreadableFileError` naming it."""
    path = Path(path)
    if not path.is_file():
        raise UnreadableFileError(f"missing file {path} ({field})")
    try:
        data = path.read_bytes()
    except OSError as e:
        raise UnreadableFileError(f"cannot read {path} ({field}: {e.strerror or e})") from e
    if not data:
        raise UnreadableFileError(f"empty file {path} ({field}: 0 bytes)")
    return data


def decode_raw(data: bytes, path: str | Path, flags: int = cv2.IMREAD_UNCHANGED, field: str = "image") -> np.ndarray:
    """The reading policy of every image reader (``docs/data.md``): ``cv2.imdecode`` of a file's bytes, then the
    EXIF orientation applied (:mod:`omnidl.data.exif`, as PIL's ``ImageOps.exif_transpose``), whatever ``flags``.

    An undecodable or truncated file (a PNG without ``IEND``, a JPEG without its end marker) and an image over
    OpenCV's pixel limit (``CV_IO_MAX_IMAGE_PIXELS``) are :class:`UnreadableFileError` naming ``path``, so
    training skips the sample."""
    from .exif import DECODER_APPLIES, apply_orientation, exif_orientation, image_format, jpeg_complete
    fmt = image_format(data)
    if flags != cv2.IMREAD_UNCHANGED:
        flags |= cv2.IMREAD_IGNORE_ORIENTATION                      # the orientation is applied below, once
    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    except cv2.error as e:
        msg = str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__
        if "MAX_IMAGE_PIXELS" in str(e) or "validateInputImageSize" in str(e):
            raise UnreadableFileError(f"image {path} ({field}) has more pixels than OpenCV decodes "
                                      f"(CV_IO_MAX_IMAGE_PIXELS = {_max_pixels()}); downscale it, or set the "
                                      "environment variable OPENCV_IO_MAX_IMAGE_PIXELS before starting Python") from e
        raise UnreadableFileError(f"cannot decode image {path} ({field}: OpenCV: {msg})") from e
    if img is None:
        raise UnreadableFileError(f"cannot decode image {path} ({field}: truncated or not an image?)")
    if fmt == "png" and not data[-12:].endswith(_PNG_END):
        raise UnreadableFileError(f"truncated PNG {path} ({field}: no IEND chunk)")
    if fmt == "jpeg" and not jpeg_complete(data):
        raise UnreadableFileError(f"truncated JPEG {path} ({field}: no end-of-image marker after the scan)")
    if fmt not in DECODER_APPLIES:
        img = apply_orientation(img, exif_orientation(data))
    return img


def read_raw(path: str | Path, flags: int = cv2.IMREAD_UNCHANGED, field: str = "image") -> np.ndarray:
    """An image file -> the array as stored (BGR[A] order, uint8/uint16/float32), turned upright by its EXIF
    orientation: :func:`read_bytes` + :func:`decode_raw` (the one reading policy, ``docs/data.md``).

    Raises :class:`UnreadableFileError` for a missing, empty, undecodable, truncated or too large file."""
    return decode_raw(read_bytes(path, field), Path(path), flags, field)


def read_image(path: str | Path, field: str = "image", channels: int | None = 3,
               dtypes: Sequence = (np.uint8, np.uint16), size: tuple[int, int] | None = None,
               convert: bool = True, reference: str = "the size of its RGB image") -> np.ndarray:
    """Read an image and check it: ``(H, W, 3)`` in **RGB** order for ``channels=3``, ``(H, W)`` for
    ``channels=1``, as stored for ``channels=None``.

    Args:
        channels: 3, 1 or None (any). With ``convert=True`` a grayscale file is repeated to RGB and an alpha
            channel dropped (``channels=3``), or a colour file refused (``channels=1``: never guessed);
            with ``convert=False`` any other channel count is a :class:`DataValidationError`.
        dtypes: allowed pixel types (e.g. ``(np.uint16,)`` for a depth PNG: an 8-bit one is refused).
        size: ``(W, H)`` the stored image must have (``reference`` says why, in the message).
    """
    arr = read_raw(path, cv2.IMREAD_UNCHANGED, field)
    if arr.dtype not in tuple(np.dtype(d) for d in dtypes):
        raise invalid(path, field, _describe(arr), "pixel type " + " or ".join(np.dtype(d).name for d in dtypes))
    ch = 1 if arr.ndim == 2 else arr.shape[2]
    if channels == 3:
        if ch == 1 and convert:
            arr = np.repeat((arr if arr.ndim == 3 else arr[..., None]), 3, axis=2)
        elif ch == 4 and convert:
            arr = arr[..., :3]
        elif ch != 3:
            raise invalid(path, field, _describe(arr), "a 3-channel (RGB) image")
        arr = np.ascontiguousarray(arr[..., ::-1])
    elif channels == 1:
        if ch != 1:
            raise invalid(path, field, _describe(arr), "a single-channel image")
        arr = arr.reshape(arr.shape[0], arr.shape[1])
    if size is not None:
        check_size(arr, size, path, field, reference)
    return arr


def load_npy(path: str | Path, field: str, shape: Sequence[int | None] | None = None, finite: bool = True,
             dtype=np.float64) -> np.ndarray:
    """``np.load`` (never unpickling) cast to ``dtype``, with ``shape`` (``None`` = any length) and finite checks.

    A missing, truncated or object (pickled) file is an :class:`UnreadableFileError` naming it."""
    path = Path(path)
    if not path.is_file():
        raise UnreadableFileError(f"missing file {path} ({field})")
    try:
        arr = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:
        raise UnreadableFileError(f"cannot read {path} ({field}: {e}; expected a complete numeric .npy file)") from e
    if not isinstance(arr, np.ndarray) or arr.dtype.kind not in "biuf":
        raise invalid(path, field, f"of dtype {getattr(arr, 'dtype', type(arr).__name__)}", "a numeric array")
    arr = arr.astype(dtype)
    if shape is not None:
        check_shape(arr, path, field, shape)
    if finite:
        check_finite(arr, path, field)
    return arr


def read_text(path: str | Path, field: str) -> str:
    """UTF-8 text of a file; a missing or binary file is an :class:`UnreadableFileError` naming it."""
    path = Path(path)
    if not path.is_file():
        raise UnreadableFileError(f"missing file {path} ({field})")
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise UnreadableFileError(f"cannot read {path} ({field}: not UTF-8 text, byte {e.start}; expected a text "
                                  "file)") from e


# ------------------------------------------------------------------------------------------------
# checks
# ------------------------------------------------------------------------------------------------

def check_shape(arr: np.ndarray, path: str | Path, field: str, shape: Sequence[int | None]) -> np.ndarray:
    """``arr.shape`` must match ``shape`` (``None`` entries match any length)."""
    ok = arr.ndim == len(shape) and all(s is None or s == a for s, a in zip(shape, arr.shape))
    if not ok:
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise invalid(path, field, f"of shape {tuple(arr.shape)}", f"shape {want}")
    return arr


def check_size(arr: np.ndarray, size: tuple[int, int], path: str | Path, field: str,
               reference: str = "the size of its RGB image") -> np.ndarray:
    """An image ``(H, W[, C])`` must be ``size=(W, H)``."""
    if (arr.shape[1], arr.shape[0]) != tuple(size):
        raise invalid(path, field, f"{arr.shape[1]}x{arr.shape[0]}", f"{size[0]}x{size[1]} ({reference})")
    return arr


def check_finite(arr: np.ndarray, path: str | Path, field: str) -> np.ndarray:
    """No NaN or inf in a float array."""
    a = np.asarray(arr)
    if a.dtype.kind == "f" and not np.isfinite(a).all():
        bad = np.argwhere(~np.isfinite(a))
        raise invalid(path, field, f"{a[tuple(bad[0])]} at index {tuple(int(i) for i in bad[0])} "
                      f"({len(bad)} non-finite value(s))", "finite numbers")
    return arr


def check_range(arr: np.ndarray, path: str | Path, field: str, lo: float | None = None, hi: float | None = None,
                hi_inclusive: bool = True) -> np.ndarray:
    """Every value in ``[lo, hi]`` (``[lo, hi)`` with ``hi_inclusive=False``); NaN fails too."""
    a = np.asarray(arr, float)
    bad = ~np.isfinite(a)
    if lo is not None:
        bad |= a < lo
    if hi is not None:
        bad |= (a > hi) if hi_inclusive else (a >= hi)
    if bad.any():
        idx = np.argwhere(bad)[0]
        rng = f"[{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}{']' if hi_inclusive else ')'}"
        where = tuple(int(i) for i in idx)
        raise invalid(path, field, f"{a[tuple(idx)]:g} at index {where} ({int(bad.sum())} value(s) out of range)",
                      f"values in {rng}")
    return arr


def check_class_ids(labels: np.ndarray, path: str | Path, field: str, num_classes: int) -> np.ndarray:
    """Integer class ids in ``[0, num_classes)``."""
    bad = (labels < 0) | (labels >= num_classes)
    if bad.any():
        vals = np.unique(labels[bad])[:5].tolist()
        raise invalid(path, field, f"class id(s) {vals} at {int(bad.sum())} pixel(s)",
                      f"ids 0..{num_classes - 1} (omnidl.classes)")
    return labels


def check_label_cor(cor: np.ndarray, path: str | Path, width: int, height: int, min_corners: int = 3,
                    field: str = "label_cor") -> np.ndarray:
    """HorizonNet ``label_cor`` corners ``(2K, 2)`` of a ``width x height`` panorama (``x y`` pixels,
    ceiling then floor of each corner).

    Checks: an even, non-zero count; finite values; every point on the image, ``-0.5 <= x < width`` and
    ``-0.5 <= y < height``: the format puts the centre of pixel ``j`` at ``j`` (the image spans ``[-0.5, W - 0.5]``,
    HorizonNet's ``u = (x + 0.5) / W``), and annotation tools that write ``[0, W)`` are accepted too; a column within
    half a pixel past the seam is the same on the circle (the targets wrap it). Anything further out is an error,
    never wrapped. Each ceiling point above its floor point, in its floor point's column (within ``W / 100``, the
    tolerance of HorizonNet's own loader: a vertical wall edge is one image column); no corner listed twice; at
    least ``min_corners`` corners in distinct columns."""
    cor = np.asarray(cor, float).reshape(-1, 2)
    if len(cor) == 0:
        raise invalid(path, field, "empty (0 points)", f"ceiling/floor pairs of at least {min_corners} corners")
    if len(cor) % 2:
        raise invalid(path, field, f"{len(cor)} points", "ceiling/floor pairs (an even count)")
    check_finite(cor, path, field)
    check_range(cor[:, 0], path, f"{field} x", -0.5, width, hi_inclusive=False)
    check_range(cor[:, 1], path, f"{field} y", -0.5, height, hi_inclusive=False)
    pairs = cor.reshape(-1, 2, 2)
    swapped = np.flatnonzero(pairs[:, 0, 1] >= pairs[:, 1, 1])
    if len(swapped):
        k = int(swapped[0])
        raise invalid(path, field, f"corner {k} with ceiling y={pairs[k, 0, 1]:g} and floor y={pairs[k, 1, 1]:g}",
                      "each ceiling point (odd lines) above its floor point (even lines)")
    dx = np.abs(pairs[:, 0, 0] - pairs[:, 1, 0])
    dx = np.minimum(dx, width - dx)                                  # columns are on the circle
    off = np.flatnonzero(dx > width / 100)
    if len(off):
        k = int(off[0])
        raise invalid(path, field, f"corner {k} with ceiling x={pairs[k, 0, 0]:g} and floor x={pairs[k, 1, 0]:g}",
                      f"the ceiling and floor point of a corner in one column (within W/100 = {width / 100:g} px)")
    ncols = len(np.unique(np.round(pairs[:, 1, 0], 3)))
    if len(pairs) < min_corners or ncols < min_corners:
        raise invalid(path, field, f"{len(pairs)} corner(s) in {ncols} distinct column(s)",
                      f"at least {min_corners} corners in distinct columns (a room)")
    flat = pairs.reshape(len(pairs), 4)
    close = np.abs(flat[:, None] - flat[None]).max(-1) <= 0.5
    close[np.arange(len(pairs)), np.arange(len(pairs))] = False
    if close.any():
        j, k = (int(i) for i in np.argwhere(close)[0])
        raise invalid(path, field, f"corner {max(j, k)} at x={pairs[k, 1, 0]:g} repeating corner {min(j, k)}",
                      "each corner once (a duplicated corner)")
    return cor


#: plausible median of the valid depths of an indoor panorama, metres (outside: a depth in the wrong unit)
DEPTH_MEDIAN_RANGE = (0.05, 100.0)


def check_depth_units(depth_m: np.ndarray, path: str | Path, field: str = "depth",
                      plausible: tuple[float, float] = DEPTH_MEDIAN_RANGE) -> np.ndarray:
    """The median of the valid (finite, > 0) depths, in metres, must be in ``plausible``: a depth map in
    millimetres read as metres has a median of thousands, one in metres read with a millimetre scale a
    median of millimetres. An all-invalid map passes (nothing to judge)."""
    d = np.asarray(depth_m, dtype=np.float64)
    v = d[np.isfinite(d) & (d > 0)]
    if v.size:
        med = float(np.median(v))
        if not plausible[0] <= med <= plausible[1]:
            raise invalid(path, field, f"of median {med:g} m over {v.size} valid pixel(s)",
                          f"an indoor depth in metres, median in [{plausible[0]:g}, {plausible[1]:g}] m (a depth in "
                          "the wrong unit, e.g. millimetres read as metres?)")
    return depth_m
