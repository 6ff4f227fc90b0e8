"""Command line: render another camera's image from an image (a panorama by default).

    python -m omnidl.apps.reproject --src pano.png --dst-camera configs/camera/kb_f195.yaml --out f.png \
        [--src-camera cam.yaml] [--size-policy error|pad|crop|scale] [--rotation ROLL,PITCH,YAW]
        [--mode bilinear|masked|nearest] [--depth] [--invalid VALUE] [--mask-out valid.png] [--overwrite]

* ``--src-camera``/``--dst-camera`` take any spec of :func:`omnidl.cameras.resolve_camera` (a camera
  YAML file, a calibration file, a ``configs/camera`` name); ``--src-camera`` defaults to a full
  equirectangular camera of the image's size, which needs a 2:1 image (``W = 2 H``; any other source
  needs its ``--src-camera``). A source camera calibrated at another size than the
  image is used on the image uniformly resized; any other size is an error unless ``--size-policy``
  says how the image relates to the calibrated one (``pad``/``crop`` right-bottom, ``scale``).
* ``--rotation`` (degrees, :func:`omnidl.geometry.rotations.euler_to_matrix` convention) is
  ``R_src_dst``: ``0,30,0`` renders a camera looking 30° above the source's optical axis.
* Images are read and written with OpenCV (8/16-bit or float, any channel count); the
  output keeps the input's dtype; pixels without a source are 0.
* ``--depth`` says the source is a depth (range) map whose 0 means "no measurement": it is sampled with
  ``--mode masked`` (bilinear over the valid pixels only, so holes never blend into valid ranges) unless
  ``--mode nearest`` is given. ``--invalid VALUE`` does the same for another "no data" value.
* Outputs follow :mod:`omnidl.utils.outputs`: ``--out``/``--mask-out`` never replace ``--src`` or a camera file
  (not even with ``--overwrite``), an existing ``--out``/``--mask-out`` is replaced only with ``--overwrite``,
  and ``--out`` and ``--mask-out`` must be two files; all checked before any work.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
import torch

from omnidl.cameras import Camera, Equirectangular, resolve_camera
from omnidl.geometry import euler_to_matrix, reproject
from omnidl.utils.io import atomic_imwrite
from omnidl.utils.outputs import guard_outputs


class CLIError(Exception):
    """A user error with a message that names the file/field."""


def load_camera(spec: str, width: int | None = None, height: int | None = None,
                size_policy: str | None = None) -> Camera:
    """:func:`omnidl.cameras.resolve_camera` with its errors turned into a :class:`CLIError` naming ``spec``.

    With ``width``/``height`` (the source image's size) the camera is fitted to that size following
    ``size_policy`` (default ``"error"`` unless the size is the calibrated image uniformly resized).
    """
    try:
        if width is not None:
            return resolve_camera(spec, width, height, check_aspect=True, size_policy=size_policy)
        return resolve_camera(spec)
    except (ValueError, KeyError, TypeError, OSError) as e:
        raise CLIError(f"camera {spec!r}: {e}") from e


def parse_rotation(text: str | None) -> torch.Tensor | None:
    """``"roll,pitch,yaw"`` in degrees -> ``(3, 3)`` float64 ``R_src_dst`` (None for no rotation)."""
    if text is None:
        return None
    try:
        vals = [float(p) for p in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) != 3 or not all(math.isfinite(v) for v in vals):
        raise CLIError(f"--rotation must be three numbers 'roll,pitch,yaw' in degrees, got {text!r}")
    r, p, y = (torch.tensor(math.radians(v), dtype=torch.float64) for v in vals)
    return euler_to_matrix(r, p, y)


def read_image(path: str | Path) -> np.ndarray:
    """``(H, W)`` or ``(H, W, C)`` image as stored (any depth, channels unchanged, BGR order), upright by its EXIF
    orientation; a file name of any bytes: the datasets' reading policy (:func:`omnidl.data.validate.read_raw`)."""
    from omnidl.data.validate import read_raw
    path = Path(path)
    if not path.is_file():
        raise CLIError(f"source image {str(path)!r} does not exist")
    try:
        return read_raw(path, field="source image")
    except OSError as e:                  # UnreadableFileError: undecodable, truncated, over OpenCV's pixel limit
        raise CLIError(str(e)) from e


def reproject_array(img: np.ndarray, src_camera: Camera, dst_camera: Camera, rotation: torch.Tensor | None = None,
                    mode: str = "bilinear", invalid: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(H, W)`` or ``(H, W, C)`` numpy image -> (image of the same dtype, ``(Hd, Wd)`` bool valid).

    ``mode="masked"`` (or ``invalid`` given with ``bilinear``) interpolates over the pixels that are not
    ``invalid`` (default 0) only, for depth maps; see :func:`omnidl.geometry.reproject`."""
    h, w = img.shape[:2]
    if (src_camera.width, src_camera.height) != (w, h):
        raise CLIError(f"the source image is {w}x{h} but the source camera is {src_camera.width}x{src_camera.height}")
    x = torch.from_numpy(np.ascontiguousarray(img))
    x = x.unsqueeze(-1) if x.dim() == 2 else x
    x = x.permute(2, 0, 1).unsqueeze(0)
    if mode != "nearest":
        x = x.to(torch.float64 if img.dtype == np.float64 else torch.float32)
    out, valid = reproject(x, src_camera, dst_camera, rotation, mode=mode, invalid=invalid)
    out = out[0].permute(1, 2, 0)
    if mode != "nearest" and np.issubdtype(img.dtype, np.integer):
        info = np.iinfo(img.dtype)
        out = out.round().clamp(info.min, info.max)
    res = out.numpy().astype(img.dtype)
    if img.ndim == 2:
        res = res[..., 0]
    return res, valid[0, 0].numpy()


def check_output_path(path: str, what: str = "--out") -> None:
    """``CLIError`` unless OpenCV can write an image named ``path`` (checked before any work)."""
    import cv2
    if Path(path).suffix and not cv2.haveImageWriter(str(path)):  # no suffix: written as PNG
        raise CLIError(f"{what} {path!r}: OpenCV has no image writer for the suffix {Path(path).suffix!r}; use "
                       ".png, .tif, .exr, .jpg, ...")


def check_outputs(args: argparse.Namespace) -> None:
    """The output policy (:func:`omnidl.utils.outputs.guard_outputs`) for ``--out``/``--mask-out`` against
    ``--src`` and the camera files, as a :class:`CLIError`."""
    outputs = [args.out] + ([args.mask_out] if args.mask_out else [])
    inputs = [args.src] + [c for c in (args.src_camera, args.dst_camera) if c and Path(c).is_file()]
    try:
        guard_outputs(outputs, inputs, overwrite=args.overwrite, option="--overwrite")
    except (FileExistsError, ValueError) as e:
        raise CLIError(str(e)) from None


def default_panorama_camera(width: int, height: int, src: str) -> Camera:
    """The full equirectangular camera of a ``width x height`` source, which must be 2:1."""
    if width != 2 * height:
        raise CLIError(f"source image {src!r} is {width}x{height} (W x H); a full equirectangular panorama is 2:1 "
                       f"(W = 2 H). Give its camera with --src-camera (e.g. a configs/camera YAML)")
    return Equirectangular(width=width, height=height)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m omnidl.apps.reproject",
                                 description="Render a camera's image from a (panorama) image.")
    ap.add_argument("--src", required=True, help="source image (read with OpenCV)")
    ap.add_argument("--dst-camera", required=True, help="camera to render: YAML, calibration file or configs/camera name")
    ap.add_argument("--out", required=True, help="output image path (format from its suffix)")
    ap.add_argument("--src-camera", default=None, help="camera of the source image (default: equirect of the "
                                                        "image size)")
    ap.add_argument("--size-policy", default=None, choices=["error", "pad", "crop", "scale"],
                    help="how the source image relates to a source camera calibrated at another size "
                         "(default: error)")
    ap.add_argument("--rotation", default=None, help="R_src_dst as 'roll,pitch,yaw' in degrees")
    ap.add_argument("--mode", default=None, choices=["bilinear", "masked", "nearest"],
                    help="interpolation (default: bilinear; masked with --depth or --invalid)")
    ap.add_argument("--depth", action="store_true", help="the source is a depth map whose 0 means no measurement "
                                                         "(interpolated with --mode masked)")
    ap.add_argument("--invalid", type=float, default=None, help="the 'no data' value of the source (implies "
                                                                "--mode masked unless --mode nearest)")
    ap.add_argument("--mask-out", default=None, help="also write the valid mask (0/255 PNG)")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing --out/--mask-out (never --src)")
    args = ap.parse_args(argv)
    try:
        check_output_path(args.out)
        if args.mask_out:
            check_output_path(args.mask_out, "--mask-out")
        check_outputs(args)
        img = read_image(args.src)
        h, w = img.shape[:2]
        src_cam = (load_camera(args.src_camera, w, h, args.size_policy) if args.src_camera
                   else default_panorama_camera(w, h, args.src))
        dst_cam = load_camera(args.dst_camera)
        rotation = parse_rotation(args.rotation)
        invalid = args.invalid if args.invalid is not None else (0.0 if args.depth else None)
        mode = args.mode or ("masked" if invalid is not None else "bilinear")
        if mode == "bilinear" and invalid is not None:
            raise CLIError("--mode bilinear blends the invalid value into valid pixels; with --depth/--invalid use "
                           "--mode masked (the default) or nearest")
        out, valid = reproject_array(img, src_cam, dst_cam, rotation, mode, invalid)
        try:
            atomic_imwrite(args.out, out)
            if args.mask_out:
                atomic_imwrite(args.mask_out, valid.astype(np.uint8) * 255)
        except (IOError, OSError) as e:  # cv2.imencode / file system
            raise CLIError(f"cannot write {args.out!r}: {e}") from e
    except CLIError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {args.out} ({out.shape[1]}x{out.shape[0]}, {100.0 * valid.mean():.1f}% valid)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
