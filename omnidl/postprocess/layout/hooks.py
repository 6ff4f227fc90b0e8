"""Post-processing hooks: ``layout_manhattan``, ``layout_atlanta`` (metric scale from a non-central
panorama's rays) and ``layout_manhattan_central``, ``layout_atlanta_central`` (central panorama, scale
from a given camera height; the Table 5.3 baseline).

``hook(outputs, batch, camera=..., **options) -> {"layout": [Layout.to_dict(), ...], "layout_ok": ..., ...}``
with ``outputs["boundary"] (B, 2, W)`` (radians below the horizon) and ``outputs["corner"]
(B, 1, W)`` logits. Options:

* ``camera``: the panorama's camera (a :class:`~omnidl.cameras.Camera` or any spec of
  :func:`~omnidl.cameras.resolve_camera`; configs pass ``camera: ${camera}``). Its ``unproject``
  gives the rays, so the rig radius (the metric scale) comes from the camera model itself.
* ``camera_height`` (central variants; default ``batch["camera_height"]``, else 1.6 m);
* ``export_dir``: write ``<name>.json``, ``<name>.obj`` and ``<name>_overlay.png`` per image;
* ``fallback`` (Manhattan hooks; default ``"atlanta"``): when a Manhattan layout fails its assumption or
  residual check (:mod:`.checks`), the Atlanta solver is run instead and the layout's ``info`` says
  ``fallback_from: "manhattan"`` and why; ``None`` keeps the failed Manhattan result;
* any :class:`~.pipeline.LayoutOptions` field.

When the batch carries ground-truth corners (``corners_cam``/``num_walls`` from the data engine, or
``corners_3d``) the scalar scores ``layout_ce``, ``layout_iou_3d``, ... of the batch are returned too
(:func:`~omnidl.metrics.layout.layout_scores`: CE in metres; CEN and the IoUs as fractions in [0, 1]).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from ...metrics.layout import gt_layout_from_batch, layout_scores
from ..registry import register_hook
from .layout import Layout
from .pipeline import LayoutOptions, estimate_layout
from .rays import column_camera, column_rays_from_boundary

#: camera height (metres) of the central hooks when neither the option nor the batch gives one
DEFAULT_CAMERA_HEIGHT = 1.6


def layouts_from_outputs(outputs: dict, batch: dict, camera: Any = None, world: str = "atlanta",
                         camera_height: float | None = None, central: bool = False,
                         fallback: str | None = "atlanta", **options: Any) -> list[Layout]:
    """Run :func:`~.pipeline.estimate_layout` on every image of a batch of network outputs.

    Without a ``camera`` every layout fails with the reason (no rays, no rig radius, no scale).
    ``fallback``: the world to try when a ``world`` layout fails its assumption/residual check
    (``info["assumptions_ok"] is False``); ``None`` for no fallback.
    """
    if fallback not in (None, "atlanta", "manhattan"):
        raise ValueError(f"fallback must be None, 'atlanta' or 'manhattan', got {fallback!r}")
    bon = outputs["boundary"].detach()
    B, _, W = bon.shape
    prob = torch.sigmoid(outputs["corner"].detach().float()).reshape(B, W).cpu().double().numpy()
    if camera is None:
        return [Layout.failed("no camera: give the hook option camera= (e.g. camera: ${camera}); the rays and the "
                              "rig radius that fixes the metric scale come from it", world=world) for _ in range(B)]
    cam = column_camera(camera, W)
    opt = LayoutOptions(**{k: v for k, v in options.items() if k in LayoutOptions.__dataclass_fields__})
    out = []
    for b in range(B):
        h = None
        if central:
            h = camera_height
            if h is None and "camera_height" in batch:
                h = float(batch["camera_height"][b])
            h = DEFAULT_CAMERA_HEIGHT if h is None else float(h)
        rays = column_rays_from_boundary(bon[b], cam)
        lay = estimate_layout(rays, prob[b], world=world, camera_height=h, options=opt)
        if not lay.ok and lay.info.get("assumptions_ok") is False and fallback not in (None, world):
            alt = estimate_layout(rays, prob[b], world=fallback, camera_height=h, options=opt)
            alt.info.update({"fallback_from": world, "fallback_reason": lay.reason})
            lay = alt
        out.append(lay)
    return out


def _run(outputs: dict, batch: dict, world: str, central: bool, export_dir: str | None = None, **options):
    layouts = layouts_from_outputs(outputs, batch, world=world, central=central, **options)
    res: dict[str, Any] = {"layout": [l.to_dict() for l in layouts],
                           "layout_ok": float(np.mean([l.ok for l in layouts]))}
    scores: dict[str, list[float]] = {}
    gts = [gt_layout_from_batch(batch, b) for b in range(len(layouts))]
    res["layout_gt"] = [None if gt is None else _gt_dict(*gt) for gt in gts]   # for report.html's 3D view
    for lay, gt in zip(layouts, gts):
        if gt is None or not lay.ok:
            continue
        for k, v in layout_scores(lay.corners, (lay.h_floor, lay.h_ceiling), gt[0], gt[1]).items():
            scores.setdefault(f"layout_{k}", []).append(v)
    res.update({k: float(np.mean(v)) for k, v in scores.items()})
    if export_dir:
        _export(Path(export_dir), layouts, batch, options.get("camera"))
    return res


def _gt_dict(poly: np.ndarray, heights: tuple[float, float]) -> dict[str, list]:
    """A ground-truth layout as :meth:`Layout.to_dict` gives its corners: ``floor_corners``/``ceiling_corners``
    ``(N, 3)`` in the layout frame (z up, metres)."""
    poly = np.asarray(poly, float)
    return {kind: np.concatenate([poly, np.full((len(poly), 1), float(h))], 1).tolist()
            for kind, h in (("floor_corners", heights[0]), ("ceiling_corners", heights[1]))}


def _name(batch: dict, b: int) -> str:
    """File name of image ``b``: ``meta["name"]`` (or ``meta["index"]``) of the batch, else ``b``."""
    meta = batch.get("meta")
    m: dict = meta[b] if isinstance(meta, list) and b < len(meta) and isinstance(meta[b], dict) else {}
    if isinstance(meta, dict):
        for k, v in meta.items():
            try:
                m[k] = v[b]
            except (TypeError, IndexError, KeyError):
                m[k] = v
    return str(m.get("name", m.get("index", b)))


def _export(out: Path, layouts: list[Layout], batch: dict, camera: Any) -> None:
    from ...utils.io import atomic_imwrite
    from .viz import draw_wireframe
    img = batch.get("image")
    for b, lay in enumerate(layouts):
        name = _name(batch, b)
        lay.save_json(out / f"{name}.json")
        lay.save_obj(out / f"{name}.obj")
        if lay.ok and camera is not None and isinstance(img, torch.Tensor):
            rgb = (img[b].detach().cpu().permute(1, 2, 0).numpy() * 255).clip(0, 255).astype(np.uint8)
            over = draw_wireframe(rgb, lay, camera)
            atomic_imwrite(out / f"{name}_overlay.png", over[:, :, ::-1])


@register_hook("layout_manhattan")
def layout_manhattan(outputs: dict, batch: dict, **options) -> dict:
    """Metric Manhattan layout from a non-central panorama (scale from the rays' rig radius)."""
    return _run(outputs, batch, "manhattan", False, **options)


@register_hook("layout_atlanta")
def layout_atlanta(outputs: dict, batch: dict, **options) -> dict:
    """Metric Atlanta layout from a non-central panorama (scale from the rays' rig radius)."""
    return _run(outputs, batch, "atlanta", False, **options)


@register_hook("layout_manhattan_central")
def layout_manhattan_central(outputs: dict, batch: dict, **options) -> dict:
    """Manhattan layout from a central panorama, scale from ``camera_height``."""
    return _run(outputs, batch, "manhattan", True, **options)


@register_hook("layout_atlanta_central")
def layout_atlanta_central(outputs: dict, batch: dict, **options) -> dict:
    """Atlanta layout from a central panorama, scale from ``camera_height``."""
    return _run(outputs, batch, "atlanta", True, **options)
