"""Post-processing hooks: ``layout_manhattan``, ``layout_atlanta`` (non-central, metric scale from
the rig radius) and ``layout_manhattan_central``, ``layout_atlanta_central`` (equirectangular, scale
from a given camera height; the Table 5.3 baseline).

``hook(outputs, batch, **options) -> {"layout": [Layout.to_dict(), ...], "layout_ok": ..., ...}``
with ``outputs["boundary"] (B, 2, W)`` (radians below the horizon) and ``outputs["corner"]
(B, 1, W)`` logits. Options: ``rc`` (metres; default from the batch ``meta["rig_radius"]`` or
``meta["camera"]["rc"]``), ``camera`` (a camera or camera config; its ``unproject`` gives the rays),
``camera_height`` (central variants; default ``batch["camera_height"]``, else 1.6 m),
``export_dir`` (write ``<name>.json``, ``<name>.obj`` and ``<name>_overlay.png`` per image), and any
:class:`~.pipeline.LayoutOptions` field. When the batch carries ground-truth corners
(``corners_cam``/``corners_valid`` from the data engine, or ``corners_3d``) the scalar scores
``layout_ce``, ``layout_iou_3d``, ... of the batch are returned too.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..registry import register_hook
from .layout import Layout
from .pipeline import LayoutOptions, estimate_layout
from .rays import R_WORLD_FROM_CAM, column_rays_from_boundary


def _meta(batch: dict, b: int) -> dict:
    meta = batch.get("meta")
    if isinstance(meta, list) and b < len(meta) and isinstance(meta[b], dict):
        return meta[b]
    if isinstance(meta, dict):
        out = {}
        for k, v in meta.items():
            try:
                out[k] = v[b]
            except (TypeError, IndexError, KeyError):
                out[k] = v
        return out
    return {}


def _rc_for(batch: dict, b: int, rc: float | None, camera: Any) -> tuple[float | None, Any]:
    if camera is not None:
        if not hasattr(camera, "unproject"):
            from ...cameras import build
            camera = build(camera)
        return None, camera
    if rc is not None:
        return float(rc), None
    m = _meta(batch, b)
    for key in ("rig_radius", "rc"):
        if key in m and m[key] is not None:
            v = m[key]
            return float(v.item() if isinstance(v, torch.Tensor) else v), None
    cam = m.get("camera")
    if isinstance(cam, dict):
        if "rc" in cam:
            return float(cam["rc"]), None
        if cam.get("type") == "equirect":
            return 0.0, None
    return None, None


def gt_layout_from_batch(batch: dict, b: int) -> tuple[np.ndarray, tuple[float, float]] | None:
    """Ground-truth ``(polygon (N, 2), (h_floor, h_ceiling))`` in the layout frame, if the batch has it.

    Reads the data engine's ``corners_cam (N_MAX, 2, 3)`` + ``corners_valid``/``num_walls``, or a
    ``corners_3d (2N, 3)`` already in the layout frame (N ceiling corners then N floor corners).
    """
    if "corners_cam" in batch:
        c = batch["corners_cam"][b].detach().cpu().double().numpy()
        n = int(batch["num_walls"][b]) if "num_walls" in batch else len(c)
        c = c[:n] @ R_WORLD_FROM_CAM.T                                    # (N, 2, 3)
        return c[:, 0, :2], (float(c[:, 1, 2].mean()), float(c[:, 0, 2].mean()))
    if "corners_3d" in batch:
        g = batch["corners_3d"][b]
        g = g.detach().cpu().double().numpy() if isinstance(g, torch.Tensor) else np.asarray(g, float)
        g = g[np.all(np.isfinite(g), -1)]
        n = len(g) // 2
        return g[:n, :2], (float(g[n:, 2].mean()), float(g[:n, 2].mean()))
    return None


def layouts_from_outputs(outputs: dict, batch: dict, world: str = "atlanta", rc: float | None = None,
                         camera: Any = None, camera_height: float | None = None, central: bool = False,
                         **options: Any) -> list[Layout]:
    """Run :func:`~.pipeline.estimate_layout` on every image of a batch of network outputs."""
    bon = outputs["boundary"].detach()
    B, _, W = bon.shape
    prob = torch.sigmoid(outputs["corner"].detach().float()).reshape(B, W).cpu().double().numpy()
    img = batch.get("image")
    H = int(img.shape[-2]) if isinstance(img, torch.Tensor) else W // 2
    opt = LayoutOptions(**{k: v for k, v in options.items() if k in LayoutOptions.__dataclass_fields__})
    out = []
    for b in range(B):
        if central:
            h = camera_height
            if h is None and "camera_height" in batch:
                h = float(batch["camera_height"][b])
            h = 1.6 if h is None else float(h)
            r, cam = 0.0, None
            if camera is not None:
                r, cam = _rc_for(batch, b, None, camera)
            rays = column_rays_from_boundary(bon[b], rc=0.0 if cam is None else None, camera=cam, height=H)
            out.append(estimate_layout(rays, prob[b], world=world, camera_height=h, options=opt))
            continue
        r, cam = _rc_for(batch, b, rc, camera)
        if r is None and cam is None:
            out.append(Layout.failed("unknown rig radius: give the hook option rc= or camera=, or a batch meta "
                                     "with rig_radius", world=world))
            continue
        rays = column_rays_from_boundary(bon[b], rc=r, camera=cam, height=H)
        out.append(estimate_layout(rays, prob[b], world=world, options=opt))
    return out


def _run(outputs: dict, batch: dict, world: str, central: bool, export_dir: str | None = None, **options):
    from ...metrics.layout import layout_scores
    layouts = layouts_from_outputs(outputs, batch, world=world, central=central, **options)
    res: dict[str, Any] = {"layout": [l.to_dict() for l in layouts],
                           "layout_ok": float(np.mean([l.ok for l in layouts]))}
    scores: dict[str, list[float]] = {}
    for b, lay in enumerate(layouts):
        gt = gt_layout_from_batch(batch, b)
        if gt is None or not lay.ok:
            continue
        for k, v in layout_scores(lay.corners, (lay.h_floor, lay.h_ceiling), gt[0], gt[1]).items():
            scores.setdefault(f"layout_{k}", []).append(v)
    res.update({k: float(np.mean(v)) for k, v in scores.items()})
    if export_dir:
        _export(Path(export_dir), layouts, outputs, batch, options)
    return res


def _export(out: Path, layouts: list[Layout], outputs: dict, batch: dict, options: dict) -> None:
    from .viz import draw_wireframe
    from ...utils.io import atomic_imwrite
    for b, lay in enumerate(layouts):
        m = _meta(batch, b)
        name = str(m.get("name", m.get("index", b)))
        lay.save_json(out / f"{name}.json")
        lay.save_obj(out / f"{name}.obj")
        img = batch.get("image")
        if lay.ok and isinstance(img, torch.Tensor):
            rgb = (img[b].detach().cpu().permute(1, 2, 0).numpy() * 255).clip(0, 255).astype(np.uint8)
            rc = options.get("rc")
            if rc is None:
                rc, _ = _rc_for(batch, b, None, None)
            over = draw_wireframe(rgb, lay, rc=rc or 0.0)
            atomic_imwrite(out / f"{name}_overlay.png", over[:, :, ::-1])


@register_hook("layout_manhattan")
def layout_manhattan(outputs: dict, batch: dict, **options) -> dict:
    """Metric Manhattan layout from a non-central panorama (scale from the rig radius)."""
    return _run(outputs, batch, "manhattan", False, **options)


@register_hook("layout_atlanta")
def layout_atlanta(outputs: dict, batch: dict, **options) -> dict:
    """Metric Atlanta layout from a non-central panorama (scale from the rig radius)."""
    return _run(outputs, batch, "atlanta", False, **options)


@register_hook("layout_manhattan_central")
def layout_manhattan_central(outputs: dict, batch: dict, **options) -> dict:
    """Manhattan layout from an equirectangular panorama, scale from ``camera_height``."""
    return _run(outputs, batch, "manhattan", True, **options)


@register_hook("layout_atlanta_central")
def layout_atlanta_central(outputs: dict, batch: dict, **options) -> dict:
    """Atlanta layout from an equirectangular panorama, scale from ``camera_height``."""
    return _run(outputs, batch, "atlanta", True, **options)
