"""``omnidl calib``: calibration files between tools, and what a camera sees.

    omnidl calib convert IN OUT --to FORMAT [--from FORMAT] [--camera ID] [--overwrite]
    omnidl calib show FILE|PRESET [--camera ID] [--out PICTURE.png] [--overwrite]

``convert`` reads IN with :func:`omnidl.cameras.io.load` (format detected unless ``--from``) and writes OUT with
:func:`omnidl.cameras.io.save` in ``--to`` (COLMAP, Kalibr, OpenCV, ORB-SLAM3, OCamCalib, KB text or omnidl's
camera YAML). A file with several cameras converts whole into a multi-camera format (COLMAP, Kalibr; ids become
``1..N`` / ``cam0..camN-1`` in the file's order) or one camera with ``--camera ID``. The written file is read
back and must reproduce IN's camera: the rays of a grid of pixels project to pixels that agree within 1e-3 px
(the difference is printed) and are valid for both cameras or for neither (a format that narrows a 195 degree
lens to 180 degrees fails here), else OUT is not written. A model the format cannot hold is refused by the writer, naming both. OUT is
never IN and never overwritten without ``--overwrite``; it appears only complete (written beside, then renamed).

``show`` prints the model, the image size, the field of view (the widest angle between a pixel's ray and the
optical axis ``+z``, doubled; and through the image centre's row and column, all between pixel centres), the
share of pixels with a valid ray and the reprojection consistency (``project(unproject(uv)) - uv``), for a
calibration file or a camera preset name (``kb_f195``, see ``omnidl/configs/camera``). ``--out`` writes a
picture: the valid region in grey, invalid pixels black, the boundary of the valid region (the image circle of
a fisheye) in red, circles of equal angle from the optical axis every 30 degrees in green, the principal
axis as a cross. Large images are analysed on every ``s``-th pixel centre (at most 1024 on the long side;
printed).
"""
from __future__ import annotations

import argparse
import math
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

#: formats ``convert`` writes (WoodScape is read only)
WRITE_FORMATS = ("colmap", "kalibr", "opencv", "orbslam3", "ocamcalib", "kb_txt", "omnidl")
MULTI_WRITE = ("colmap", "kalibr")
#: largest side of the pixel grid ``show`` analyses and draws
MAX_SIDE = 1024
#: pixel tolerance of ``convert``'s read-back check
ROUND_TRIP_PX = 1e-3


# ----------------------------------------------------------------------------------------------- analysis

def grid(camera, max_side: int = MAX_SIDE) -> tuple[torch.Tensor, int]:
    """``(uv (h, w, 2) float64, stride)``: every ``stride``-th pixel centre of ``camera`` (``stride`` the
    smallest making both sides at most ``max_side``)."""
    stride = max(1, math.ceil(max(camera.width, camera.height) / max_side))
    u = torch.arange(0, camera.width, stride, dtype=torch.float64) + 0.5
    v = torch.arange(0, camera.height, stride, dtype=torch.float64) + 0.5
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    return torch.stack([uu, vv], -1), stride


def _angles_deg(direction: torch.Tensor) -> torch.Tensor:
    """Angle between unit rays ``(..., 3)`` and the optical axis ``+z``, degrees."""
    return torch.rad2deg(torch.acos(direction[..., 2].clamp(-1.0, 1.0)))


def _spread_deg(direction: torch.Tensor, valid: torch.Tensor, axis: int) -> float:
    """Angular extent (degrees) of the valid rays of one image line, about the ``y`` axis (``axis=0``: a row,
    angle ``atan2(x, z)``) or the ``x`` axis (``axis=1``: a column, ``atan2(y, z)``), unwrapped along the line."""
    d = direction[valid]
    if len(d) < 2:
        return 0.0
    a = torch.atan2(d[:, axis], d[:, 2]).numpy()
    a = np.unwrap(a)
    return float(np.rad2deg(a.max() - a.min()))


def describe(camera) -> dict[str, Any]:
    """What ``show`` prints: ``{"model", "class", "central", "width", "height", "fov_deg", "fov_h_deg",
    "fov_v_deg", "valid_fraction", "reprojection_px", "stride"}`` (FOVs between pixel centres; ``fov_deg`` is
    twice the widest angle from the optical axis over the analysed pixels)."""
    from omnidl.cameras.io._common import family_of
    uv, stride = grid(camera)
    rays = camera.unproject(uv)
    valid = rays.valid
    theta = _angles_deg(rays.direction)
    info: dict[str, Any] = {"model": family_of(camera), "class": type(camera).__name__,
                            "central": bool(getattr(camera, "central", True)), "width": camera.width,
                            "height": camera.height, "stride": stride}
    info["valid_fraction"] = float(valid.double().mean())
    info["fov_deg"] = float(2 * theta[valid].max()) if valid.any() else 0.0
    # the centre row and column at full resolution
    u = torch.arange(camera.width, dtype=torch.float64) + 0.5
    v = torch.arange(camera.height, dtype=torch.float64) + 0.5
    row = camera.unproject(torch.stack([u, torch.full_like(u, camera.height / 2)], -1))
    col = camera.unproject(torch.stack([torch.full_like(v, camera.width / 2), v], -1))
    info["fov_h_deg"] = _spread_deg(row.direction, row.valid, 0)
    info["fov_v_deg"] = _spread_deg(col.direction, col.valid, 1)
    if valid.any():
        pts = rays.origin[valid] + 2.0 * rays.direction[valid]  # a point 2 m along each ray (non-central too)
        back, ok = camera.project(pts)
        err = (back - uv[valid]).norm(dim=-1)
        info["reprojection_px"] = float(err[ok].max()) if ok.any() else float("inf")
        info["reprojection_lost"] = int((~ok).sum())
    else:
        info["reprojection_px"], info["reprojection_lost"] = float("nan"), 0
    return info


def picture(camera, step_deg: float = 30.0) -> np.ndarray:
    """A BGR ``uint8`` picture of ``camera``'s analysed pixel grid (see the module docstring)."""
    import cv2
    uv, _ = grid(camera)
    rays = camera.unproject(uv)
    valid = rays.valid.numpy()
    theta = _angles_deg(rays.direction).numpy()
    h, w = valid.shape
    img = np.zeros((h, w, 3), np.uint8)
    img[valid] = (150, 150, 150)
    band = np.floor(theta / step_deg)
    iso = np.zeros_like(valid)
    iso[:, 1:] |= band[:, 1:] != band[:, :-1]
    iso[1:, :] |= band[1:, :] != band[:-1, :]
    img[iso & valid] = (0, 200, 0)
    # valid pixels next to an invalid one (the image frame itself is not a boundary)
    edge = valid & ~cv2.erode(valid.astype(np.uint8), np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE
                              ).astype(bool)
    img[edge] = (0, 0, 255)
    # the principal axis: the pixel of the ray +z, if the camera sees it
    if bool(getattr(camera, "central", True)):
        pt, ok = camera.project(torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))
        if bool(ok[0]):
            scale = w / camera.width
            c = (int(round(float(pt[0, 0]) * scale - 0.5)), int(round(float(pt[0, 1]) * h / camera.height - 0.5)))
            cv2.drawMarker(img, c, (255, 255, 255), cv2.MARKER_CROSS, max(5, w // 40), 1)
    return img


def round_trip_px(a, b) -> tuple[float, int]:
    """``(largest pixel difference, rays valid for one camera only)`` between projecting ``a``'s rays of a
    grid of pixels with ``a`` and with ``b`` (same size required)."""
    if (a.width, a.height) != (b.width, b.height):
        return float("inf"), 0
    uv, _ = grid(a, 64)
    rays = a.unproject(uv)
    pts = rays.origin + 2.0 * rays.direction
    pa, va = a.project(pts)
    pb, vb = b.project(pts)
    keep = rays.valid & va & vb
    diff = float((pa - pb)[keep].norm(dim=-1).max()) if keep.any() else 0.0
    return diff, int(((va & rays.valid) != (vb & rays.valid)).sum())


# ----------------------------------------------------------------------------------------------- commands

def _refuse_overwrite(out: Path, inputs: Sequence[Path], overwrite: bool) -> None:
    for p in inputs:
        if out.exists() and p.exists() and out.resolve() == p.resolve():
            raise ValueError(f"OUT {str(out)!r} is the input {str(p)!r}: choose another file name")
    if out.is_dir():
        raise IsADirectoryError(f"OUT {str(out)!r} is a folder: give a file name")
    if out.exists() and not overwrite:
        raise FileExistsError(f"OUT {str(out)!r} exists: pass --overwrite to replace it, or choose another name")


def _load(path: str, fmt: str | None, camera: str | None):
    from omnidl.cameras import io
    cam_id: Any = camera
    if camera is not None and camera.isdigit():
        cam_id = int(camera)
    return io.load(path, camera=cam_id, format=fmt)


def convert(src: str | os.PathLike, out: str | os.PathLike, to: str, *, src_format: str | None = None,
            camera: str | None = None, overwrite: bool = False) -> dict[str, Any]:
    """Convert a calibration file; returns ``{"out", "cameras": n, "round_trip_px", "validity_changed"}``."""
    from omnidl.cameras import io
    src, out = Path(src), Path(out)
    if to not in WRITE_FORMATS:
        raise ValueError(f"--to {to!r}: expected one of {list(WRITE_FORMATS)}")
    if not src.is_file():
        raise FileNotFoundError(f"calibration file {str(src)!r} does not exist")
    _refuse_overwrite(out, [src], overwrite)
    if camera is not None:
        cams: Any = _load(str(src), src_format, camera)
    else:
        every = io.load_all(src, src_format)
        if len(every) == 1:
            cams = next(iter(every.values()))
        elif to in MULTI_WRITE:
            vals = list(every.values())
            cams = ({i + 1: c for i, c in enumerate(vals)} if to == "colmap"
                    else {f"cam{i}": c for i, c in enumerate(vals)})
        else:
            raise ValueError(f"{str(src)!r} holds {len(every)} cameras {list(every)}; format {to!r} holds one: "
                             "choose it with --camera ID (or convert to colmap/kalibr)")
    tmp = out.with_name(f".{out.stem}.{os.getpid()}.part{out.suffix}")
    try:
        io.save(cams, tmp, format=to)
        back = io.load_all(tmp, to) if isinstance(cams, dict) else {0: io.load(tmp, format=to)}
        originals = list(cams.values()) if isinstance(cams, dict) else [cams]
        if len(back) != len(originals):
            raise ValueError(f"{to} file read back holds {len(back)} cameras, wrote {len(originals)}")
        worst, changed = 0.0, 0
        for a, b in zip(originals, back.values()):
            d, n = round_trip_px(a, b)
            worst, changed = max(worst, d), changed + n
        if not worst <= ROUND_TRIP_PX:
            raise ValueError(f"the {to} file does not reproduce {str(src)!r}: pixels differ by up to {worst:.3g} "
                             f"px after reading it back (tolerance {ROUND_TRIP_PX:g}); OUT not written")
        if changed:
            raise ValueError(f"the {to} file does not reproduce {str(src)!r}: {changed} of the checked rays are "
                             f"seen by one camera and not the other after reading it back (the format narrows or "
                             f"widens the field of view); OUT not written")
        if out.exists() and not overwrite:  # appeared meanwhile
            raise FileExistsError(f"OUT {str(out)!r} exists: pass --overwrite to replace it")
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    return {"out": str(out), "cameras": len(originals), "round_trip_px": worst, "validity_changed": changed}


def show(spec: str, *, src_format: str | None = None, camera: str | None = None, out: str | None = None,
         overwrite: bool = False) -> dict[str, Any]:
    """Describe a calibration file or preset (:func:`describe`), writing the picture to ``out`` if given."""
    cam = _load(spec, src_format, camera)
    info = describe(cam)
    if out is not None:
        from omnidl.utils.io import atomic_imwrite
        path = Path(out)
        if path.suffix.lower() != ".png":
            raise ValueError(f"--out {out!r}: the picture is a PNG file (name it *.png)")
        _refuse_overwrite(path, [Path(spec)], overwrite)
        atomic_imwrite(path, picture(cam))
        info["picture"] = str(path)
    return info


def format_info(name: str, info: dict[str, Any]) -> str:
    lines = [f"{name}: {info['model']} ({info['class']}, {'central' if info['central'] else 'non-central'})",
             f"  image size      {info['width']} x {info['height']} px (W x H)",
             f"  field of view   {info['fov_deg']:.2f} deg (widest ray from the optical axis, doubled); "
             f"{info['fov_h_deg']:.2f} deg along the centre row, {info['fov_v_deg']:.2f} deg along the centre column",
             f"  valid pixels    {100 * info['valid_fraction']:.2f} %"
             + (f" (analysed on a grid of every {info['stride']} pixels)" if info["stride"] > 1 else ""),
             f"  reprojection    max |project(unproject(uv)) - uv| = {info['reprojection_px']:.2e} px"
             + (f"; {info['reprojection_lost']} ray(s) do not project back" if info["reprojection_lost"] else "")]
    if "picture" in info:
        lines.append(f"  picture         {info['picture']}")
    return "\n".join(lines)


def build_parser(prog: str = "omnidl calib") -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="action", required=True)
    c = sub.add_parser("convert", help="convert a calibration file to another tool's format")
    c.add_argument("input", help="calibration file (COLMAP, Kalibr, OpenCV, ORB-SLAM3, OCamCalib, KB text, "
                                 "WoodScape, omnidl YAML)")
    c.add_argument("out", help="the file to write")
    c.add_argument("--to", required=True, choices=WRITE_FORMATS, help="format of OUT")
    c.add_argument("--from", dest="src_format", default=None, help="format of INPUT (default: detected)")
    c.add_argument("--camera", default=None, help="which camera of a multi-camera file (COLMAP id, Kalibr cam1)")
    c.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    s = sub.add_parser("show", help="model, size, field of view, validity; --out: a picture of the valid region")
    s.add_argument("input", help="calibration file or camera preset name (e.g. kb_f195)")
    s.add_argument("--from", dest="src_format", default=None, help="format of INPUT (default: detected)")
    s.add_argument("--camera", default=None, help="which camera of a multi-camera file")
    s.add_argument("--out", default=None, help="write the picture of the image circle / valid region (PNG)")
    s.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.action == "convert":
            r = convert(args.input, args.out, args.to, src_format=args.src_format, camera=args.camera,
                        overwrite=args.overwrite)
            print(f"{args.input} -> {r['out']} ({args.to}, {r['cameras']} camera(s)); read back: pixels agree "
                  f"within {r['round_trip_px']:.1e} px, validity identical")
        else:
            info = show(args.input, src_format=args.src_format, camera=args.camera, out=args.out,
                        overwrite=args.overwrite)
            print(format_info(args.input, info))
    except (FileNotFoundError, FileExistsError, IsADirectoryError, ValueError, TypeError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
