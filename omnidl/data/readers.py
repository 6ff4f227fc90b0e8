"""The one image / video reading policy of omnidl (``docs/data.md``): every dataset adapter, ``omnidl predict``
and the CLIs read pictures through these functions, so the same file gives the same pixels everywhere.

Policy:

* **Bytes**: a file is read by Python (:func:`~omnidl.data.validate.read_bytes`) and decoded from memory, so a
  name of any bytes works; OpenCV's own file functions (``VideoCapture``, which segfaults on a name it cannot
  encode) get a name it can encode (:func:`cv2_path`).
* **Orientation**: the EXIF orientation is applied (as PIL's ``ImageOps.exif_transpose``), by every reader and
  for every format (JPEG, PNG, WebP, TIFF); labels were drawn on the upright image a viewer shows.
* **Failures**: a missing, empty, truncated or undecodable file, or one over OpenCV's pixel limit
  (``CV_IO_MAX_IMAGE_PIXELS``), is an :class:`~omnidl.data.validate.UnreadableFileError` naming it: a
  :class:`~omnidl.data.robust.CorruptSampleError`, so training skips the sample with a warning.
* **Colour images** (:func:`read_rgb`, :func:`read_rgb_array`): 8-bit values / 255, 16-bit / 65535; grayscale
  repeated to RGB; an alpha channel dropped (not composited: the stored colour is kept); a palette PNG
  expanded to its colours; float or 32-bit images refused (:class:`~omnidl.data.validate.DataValidationError`).
* **Label maps** (:func:`read_label_map`): one channel: 8/16-bit grey values, or the palette *indices* of a
  palette PNG (never its colours); colour or alpha maps refused.
* **Depth PNGs** (:func:`read_depth_png`): 16-bit only; ``value / scale`` metres, with a unit check
  (:func:`~omnidl.data.validate.check_depth_units`).
* **Tensors** (:func:`image_to_float`): an integer image tensor is converted to float before any arithmetic
  (uint8 / 255, uint16 / 65535), never normalised in its integer dtype.
* **Videos** (:func:`iter_video_frames`): every frame as :func:`read_rgb` gives an image; OpenCV's FFmpeg
  backend applies the stream's rotation metadata (``CAP_PROP_ORIENTATION_AUTO``), as EXIF for images.
"""
from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import torch

from .validate import (UnreadableFileError, check_depth_units, check_size, decode_raw, invalid, read_bytes,
                       read_image, read_raw)

__all__ = ["read_raw", "read_rgb", "read_rgb_array", "array_to_tensor", "rgb_to_tensor", "image_to_float",
           "read_label_map", "read_depth_png", "resize_labels", "cv2_path", "iter_video_frames"]


def read_rgb_array(path: str | Path, field: str = "image") -> np.ndarray:
    """``(H, W, 3)`` RGB uint8 or uint16 array of an image file, upright (module docstring)."""
    return read_image(path, field, channels=3, dtypes=(np.uint8, np.uint16))


def array_to_tensor(rgb: np.ndarray, size: tuple[int, int] | None = None) -> torch.Tensor:
    """An ``(H, W, 3)`` RGB uint8/uint16 array -> ``(3, H, W)`` float32 in ``[0, 1]``, resized to ``size=(W, H)``
    (area when shrinking, linear when enlarging; in the stored dtype, then divided)."""
    if rgb.dtype not in (np.uint8, np.uint16):
        raise TypeError(f"array_to_tensor: expected a uint8 or uint16 RGB array, got {rgb.dtype}")
    if size is not None and (rgb.shape[1], rgb.shape[0]) != tuple(size):
        shrink = rgb.shape[1] > size[0]
        rgb = cv2.resize(rgb, tuple(int(s) for s in size), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    scale = 65535.0 if rgb.dtype == np.uint16 else 255.0
    return torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1).float().div_(scale)


def read_rgb(path: str | Path, size: tuple[int, int] | None = None, field: str = "image") -> torch.Tensor:
    """An image file -> ``(3, H, W)`` float32 RGB in ``[0, 1]``, upright; ``size=(W, H)`` resizes. The reading
    policy of the module docstring (errors name the file)."""
    return array_to_tensor(read_rgb_array(path, field), size)


def rgb_to_tensor(img: np.ndarray, size: tuple[int, int] | None = None) -> torch.Tensor:
    """A BGR[A] / grayscale array from :func:`read_raw` -> ``(3, H, W)`` float32 RGB in ``[0, 1]``, optionally
    resized to ``size=(W, H)`` (grayscale repeated, alpha dropped, 16-bit / 65535)."""
    if img.ndim == 2:
        img = img[..., None]
    if img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    return array_to_tensor(np.ascontiguousarray(img[..., 2::-1]), size)


def image_to_float(image: torch.Tensor, what: str = "image") -> torch.Tensor:
    """An image tensor as float in ``[0, 1]``: uint8 / 255, uint16 / 65535, float kept as is; bool and other
    integer types are refused (their range is unknown). Integer images are converted *before* any
    arithmetic (normalising a uint8 tensor in uint8 wraps around)."""
    t = torch.as_tensor(image)
    if t.is_floating_point():
        return t
    if t.dtype == torch.uint8:
        return t.float().div_(255.0)
    if t.dtype == torch.uint16:
        return t.float().div_(65535.0)
    raise TypeError(f"{what}: an image tensor of dtype {t.dtype}; expected float in [0, 1], uint8 (0..255) or "
                    "uint16 (0..65535)")


def _is_palette_png(data: bytes) -> bool:
    return data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR" and len(data) > 25 and data[25] == 3


def read_label_map(path: str | Path, field: str = "label map", dtypes=(np.uint8, np.uint16),
                   size: tuple[int, int] | None = None) -> np.ndarray:
    """``(H, W)`` integer label map: the values of a one-channel 8/16-bit image, or the palette indices of a
    palette PNG (as ``numpy.asarray(PIL.Image.open(f))`` gives them, the ids tools such as Structured3D's
    store), upright. A colour (or alpha) image is a :class:`~omnidl.data.validate.DataValidationError`; so is a
    size other than ``size=(W, H)``."""
    data = read_bytes(path, field)
    if _is_palette_png(data):
        arr = decode_raw(data, path, cv2.IMREAD_UNCHANGED, field)        # checks truncation / limits first
        import io
        from PIL import Image
        from .exif import apply_orientation, exif_orientation
        try:
            with Image.open(io.BytesIO(data)) as im:
                if im.mode != "P":
                    raise invalid(path, field, f"a PNG of mode {im.mode}", "a palette or one-channel label map")
                arr = np.asarray(im).astype(np.uint8)
        except (OSError, Image.DecompressionBombError) as e:
            raise UnreadableFileError(f"cannot decode image {path} ({field}: {e})") from e
        arr = apply_orientation(arr, exif_orientation(data))
    else:
        arr = decode_raw(data, path, cv2.IMREAD_UNCHANGED, field)
        if arr.ndim == 3 and arr.shape[2] == 1:
            arr = arr[..., 0]
        if arr.ndim != 2:
            raise invalid(path, field, f"{arr.shape[1]}x{arr.shape[0]} {arr.shape[2]}-channel {arr.dtype}",
                          "a single-channel (or palette) label map")
    if arr.dtype not in tuple(np.dtype(d) for d in dtypes):
        raise invalid(path, field, f"{arr.shape[1]}x{arr.shape[0]} 1-channel {arr.dtype}",
                      "pixel type " + " or ".join(np.dtype(d).name for d in dtypes))
    if size is not None:
        check_size(arr, size, path, field)
    return arr


def read_depth_png(path: str | Path, scale: float, invalid: int | None = None,
                   size: tuple[int, int] | None = None, expect: tuple[int, int] | None = None,
                   plausible: tuple[float, float] | None = None) -> torch.Tensor:
    """16-bit depth PNG -> ``(1, H, W)`` float32 metres (``value / scale``; ``invalid`` and 0 -> 0).

    Only 16-bit files are accepted: an 8-bit PNG cannot hold the range (it would load as centimetres), so it is
    a :class:`~omnidl.data.validate.DataValidationError` naming the file; so is a map whose median valid depth
    is outside ``plausible`` (default :data:`~omnidl.data.validate.DEPTH_MEDIAN_RANGE`: a depth in another unit).

    ``expect=(W, H)`` checks the stored size first (a depth map of the wrong size is an error naming both
    sizes); ``size=(W, H)`` then resizes with nearest neighbour (never blends valid and invalid depth).
    """
    raw = read_image(path, "depth map", channels=None, dtypes=(np.uint16,))     # an 8-bit depth PNG is refused
    if raw.ndim == 3:
        raw = raw[..., 0]
    if expect is not None:
        check_size(raw, expect, path, "depth map")
    depth = raw.astype(np.float32)
    bad = depth <= 0
    if invalid is not None:
        bad |= raw == invalid
    depth = np.where(bad, 0.0, depth / scale).astype(np.float32)
    if plausible is None:
        check_depth_units(depth, path, "depth map")
    else:
        check_depth_units(depth, path, "depth map", plausible)
    if size is not None and (depth.shape[1], depth.shape[0]) != tuple(size):
        depth = cv2.resize(depth, tuple(size), interpolation=cv2.INTER_NEAREST)
    return torch.from_numpy(np.ascontiguousarray(depth))[None]


def resize_labels(labels: np.ndarray, size: tuple[int, int] | None) -> np.ndarray:
    """Nearest-neighbour resize of an integer label map to ``size=(W, H)``."""
    if size is None or (labels.shape[1], labels.shape[0]) == tuple(size):
        return labels
    return cv2.resize(labels.astype(np.int32), tuple(size), interpolation=cv2.INTER_NEAREST).astype(labels.dtype)


def _encodable(name: str) -> bool:
    try:
        name.encode("utf-8")
        return True
    except UnicodeEncodeError:
        return False


@contextlib.contextmanager
def cv2_path(path: str | Path) -> Iterator[str]:
    """A name of ``path`` that OpenCV's (and other native libraries') file functions can take: the path itself
    when it is valid UTF-8, else a link (or, where links fail, a copy) with an ASCII name in a temporary folder,
    removed on exit. OpenCV's Python binding crashes the interpreter (segfault) on a ``str`` it cannot encode."""
    path = Path(path)
    if _encodable(str(path)):
        yield str(path)
        return
    tmp = tempfile.mkdtemp(prefix="omnidl-read-")
    try:
        link = os.path.join(tmp, "file" + (path.suffix if _encodable(path.suffix) else ""))
        try:
            os.symlink(os.path.abspath(path), link)
        except OSError:
            shutil.copyfile(path, link)
        yield link
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def iter_video_frames(path: str | Path, limit: int = 0) -> Iterator[torch.Tensor]:
    """Every frame of a video (up to ``limit`` when > 0) as ``(3, H, W)`` float32 RGB in ``[0, 1]``.

    A file OpenCV cannot open is an :class:`~omnidl.data.validate.UnreadableFileError` naming it; a name of any
    bytes works (:func:`cv2_path`)."""
    path = Path(path)
    if not path.is_file():
        raise UnreadableFileError(f"missing file {path} (video)")
    with cv2_path(path) as name:
        cap = cv2.VideoCapture(name)
        if not cap.isOpened():
            raise UnreadableFileError(f"cannot open video {path} (OpenCV cannot decode it)")
        if hasattr(cv2, "CAP_PROP_ORIENTATION_AUTO"):
            cap.set(cv2.CAP_PROP_ORIENTATION_AUTO, 1)
        try:
            n = 0
            while not limit or n < limit:
                ok, frame = cap.read()
                if not ok:
                    break
                yield rgb_to_tensor(frame)
                n += 1
        finally:
            cap.release()
