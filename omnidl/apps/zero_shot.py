"""Zero-shot depth for any omnidirectional camera from a perspective depth model (Depth-Anything-V2) through views.

``python -m omnidl.apps.zero_shot INPUT --camera CALIB --weights DIR_OR_FILE --out DIR`` (the lead wires it to
``omnidl predict depth INPUT --camera CALIB --model depth_anything_v2 --weights DIR``). The input image is cut into
perspective views through its camera (:mod:`omnidl.geometry.views`), the model runs on each, the views are aligned
on their overlaps (metric models: one scale per view, geometric mean 1, so the model's metric scale is kept;
relative models: scale and shift of the inverse depth) and fused back onto the input's pixels, non-central cameras
through their own rays.

Writes, per input ``<stem>`` in ``--out`` (never over an existing file unless ``--overwrite``; atomically):

* ``<stem>_depth.npy``: float32 ``(H, W)`` range along each pixel's ray in metres (metric models) or up to one
  unknown scale (relative models: see ``<stem>_zero_shot.json``), ``NaN`` where no view sees the pixel;
* ``<stem>_zero_shot.json``: model, weights, kind (metric/relative), views, per-view scales and shifts, the
  alignment residual, coverage.

Weights are never downloaded: ``--weights`` is the published ``depth_anything_v2_vits.pth`` (etc.) or a folder
holding it, or a transformers folder (``model.safetensors`` + ``config.json``); see ``docs/foundation.md``.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from torch import nn

from omnidl.cameras import Camera
from omnidl.geometry.views import LAYOUTS, ViewDepth, depth_through_views, view_layout, visible_views

MODELS = ("depth_anything_v2",)


def build_depth_model(model: str | nn.Module, weights: str | Path | None, device: str = "cpu",
                      max_depth: float | None = None) -> nn.Module:
    """The perspective model: a registered name loaded from ``weights`` (required), or a module as it is."""
    if isinstance(model, nn.Module):
        return model.to(device).eval()
    if model not in MODELS:
        raise ValueError(f"--model {model!r}: zero-shot depth supports {MODELS}")
    if not weights:
        raise ValueError(f"--model {model}: --weights is required (omnidl ships no weights and downloads nothing; "
                         "see docs/foundation.md for the files)")
    from omnidl.models import create_model
    return create_model(model, pretrained=str(weights), max_depth=max_depth).to(device).eval()


def _output_kind(model: nn.Module) -> tuple[str, str, str]:
    """``(output key, view kind, alignment)`` of a depth model."""
    out = getattr(model, "output", None)
    if out == "disparity":
        return "disparity", "disparity", "affine"
    return "depth", "depth", "scale"


def predict_depth_zero_shot(image: torch.Tensor, camera: Camera, model: str | nn.Module = "depth_anything_v2",
                            weights: str | Path | None = None, *, layout: str = "tangent", size: int = 518,
                            fov: float | None = None, device: str = "cpu", batch: int = 4,
                            max_depth: float | None = None, assumed_range: float = 3.0) -> tuple[ViewDepth, dict]:
    """Depth of ``image (3, H, W)`` RGB in ``[0, 1]`` seen by ``camera`` (module doc).

    Returns the :class:`~omnidl.geometry.views.ViewDepth` (``depth (1, H, W)`` range along each pixel's ray) and a
    JSON-ready summary. ``size`` must be a multiple of 14 for Depth-Anything-V2 (518: its training size).
    """
    if image.dim() != 3 or image.shape[0] != 3:
        raise ValueError(f"image must be (3, H, W) RGB, got {tuple(image.shape)}")
    if (image.shape[2], image.shape[1]) != (camera.width, camera.height):
        raise ValueError(f"image is {image.shape[2]}x{image.shape[1]} (WxH) but the camera is "
                         f"{camera.width}x{camera.height}")
    net = build_depth_model(model, weights, device, max_depth)
    key, kind, align = _output_kind(net)
    patch = getattr(net, "patch_size", 1)
    if size % patch:
        raise ValueError(f"--size {size}: must be a multiple of the model's patch size {patch}")

    def predict(images: torch.Tensor, _views: list) -> torch.Tensor:
        with torch.no_grad():
            return net(images.to(device))[key].float().cpu()

    views = visible_views(camera, view_layout(layout, size, fov))
    res = depth_through_views(image.float(), camera, predict, views=views, kind=kind, align=align,
                              assumed_range=assumed_range, batch=batch)
    valid = res.valid[0]
    summary = {
        "model": model if isinstance(model, str) else type(model).__name__,
        "weights": None if weights is None else str(weights),
        "kind": "metric" if kind == "depth" else "relative (affine-invariant inverse depth; range up to one scale)",
        "depth": "range along each pixel's ray from the ray's origin, metres" if kind == "depth" else
                 "range along each pixel's ray, up to one unknown global scale",
        "camera": camera.to_config(),
        "views": {"layout": layout, "count": len(res.views), "size": int(size),
                  "fov_deg": float(fov) if fov is not None else None},
        "alignment": {"mode": res.alignment.mode, "scale": [float(s) for s in res.alignment.scale],
                      "shift": [float(s) for s in res.alignment.shift], "residual": res.alignment.residual,
                      "overlap_pixels": res.alignment.points},
        "coverage": float(valid.float().mean()),
    }
    return res, summary


def _write_outputs(out: Path, stem: str, res: ViewDepth, summary: dict, overwrite: bool) -> list[Path]:
    from omnidl.utils.io import atomic_write, atomic_write_json
    files = [out / f"{stem}_depth.npy", out / f"{stem}_zero_shot.json"]
    existing = [str(f) for f in files if f.exists()]
    if existing and not overwrite:
        raise FileExistsError(f"{existing}: already exist; pass --overwrite to replace them")
    depth = res.depth[0].numpy().astype(np.float32)
    depth[~res.valid[0].numpy()] = np.nan
    out.mkdir(parents=True, exist_ok=True)

    def save(tmp: str) -> None:
        with open(tmp, "wb") as f:
            np.save(f, depth)
    atomic_write(files[0], save)
    atomic_write_json(files[1], summary)
    return files


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m omnidl.apps.zero_shot", description=__doc__.split("\n\n")[0])
    p.add_argument("input", help="an image file")
    p.add_argument("--camera", required=True, help="calibration file or preset of the input's camera")
    p.add_argument("--model", default="depth_anything_v2", choices=MODELS)
    p.add_argument("--weights", required=True, help="checkpoint file or folder (docs/foundation.md)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--layout", default="tangent", choices=LAYOUTS)
    p.add_argument("--size", type=int, default=518, help="view side in pixels (multiple of 14)")
    p.add_argument("--fov", type=float, default=None, help="view field of view, degrees")
    p.add_argument("--max-depth", type=float, default=None, help="metric models: 20 (Hypersim) or 80 (VKITTI)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--overwrite", action="store_true")
    a = p.parse_args(argv)
    from omnidl.apps.predict.camera import input_camera
    from omnidl.apps.predict.inputs import read_image
    path = Path(a.input)
    if not path.is_file():
        print(f"error: input {path} does not exist", file=sys.stderr)
        return 2
    try:
        image = read_image(path)
        camera = input_camera(a.camera, image.shape[2], image.shape[1])
        if (camera.width, camera.height) != (image.shape[2], image.shape[1]):
            image = torch.nn.functional.interpolate(image[None], size=(camera.height, camera.width), mode="bilinear",
                                                    align_corners=False, antialias=True)[0]
        res, summary = predict_depth_zero_shot(image, camera, a.model, a.weights, layout=a.layout, size=a.size,
                                               fov=a.fov, device=a.device, max_depth=a.max_depth)
        files = _write_outputs(Path(a.out), path.stem, res, summary, a.overwrite)
    except (ValueError, FileNotFoundError, FileExistsError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    d = res.depth[0][res.valid[0]]
    print(f"{path.name}: {summary['views']['count']} {a.layout} views, {100 * summary['coverage']:.1f} % of the "
          f"pixels, depth {float(d.min()) if d.numel() else math.nan:.2f}-{float(d.max()) if d.numel() else math.nan:.2f}"
          f" ({summary['kind'].split(' ')[0]}), alignment residual {res.alignment.residual:.2e}; wrote "
          f"{', '.join(str(f) for f in files)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
