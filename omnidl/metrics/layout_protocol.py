"""Layout metrics under the published evaluation protocols, selected by name (``metrics.protocol=...``).

Every protocol scores one image at a time and averages over images (as both peer scripts do):

* ``iou_2d``, ``iou_3d`` (fractions): floor-plan IoU of the two room polygons and IoU of the extruded rooms. Both
  rooms are first scaled so that the floor lies ``camera_height`` below the camera (the datasets' fixed
  camera height, 1.6 m), so the floors coincide and the volume overlap is ``area(P ∩ Q) * min(h_P, h_Q)``
  (``h`` = floor-to-ceiling height). Polygons may be non-convex; areas are exact
  (:mod:`omnidl.geometry.polygon`).
* ``depth_rmse`` (m), ``depth_delta1`` (fraction): RMSE and ``max(p/g, g/p) < 1.25`` over every pixel of the
  *layout depth* maps (range from the camera to the first ceiling / wall / floor surface along each pixel's
  ray) of a ``width x height`` panorama, for both rooms at the fixed camera height.
* cuboids only (ground truth and prediction with 4 corners): ``corner_error`` (fraction): mean distance of
  the 8 matched corner pixels (ceiling and floor of each corner, both sets sorted by column) over the image
  diagonal; ``pixel_error`` (fraction): pixels whose surface label (ceiling / wall /
  floor) differs.
* ``iou_2d@4|6|8|10+|odd`` / ``iou_3d@...``: the IoUs grouped by the ground truth's corner count.

Units: every score is a fraction in [0, 1] except ``depth_rmse`` (the rooms' units, metres); the peers' papers
print the IoUs, CE and PE in percent (multiply by 100 for such a table and label its columns ``(%)``).

Protocols (how each matches the peer script's documented behaviour):

``horizonnet``
    HorizonNet's ``eval_general.py`` (2D/3D IoU, RMSE, δ1 of layout depth at 1024 x 512, grouped by
    4/6/8/10+/odd corners; a ground truth that is not a valid polygon is skipped) and ``eval_cuboid.py``
    (CE, PE as above, at 1024 x 512). Its 3D IoU takes each room height from the corners' ceiling rows at
    camera height 1.6: the same as here. Its layout depth interpolates the boundary between corners; here
    it is the exact ray/wall hit (identical for straight walls seen without occlusion).
``lgtnet``
    LGT-Net's ``evaluation/`` (``calc_IoU`` with heights ``1 + ratio`` at camera height 1 - IoU is scale
    free, so equal to the 1.6 m figure; CE/PE at 1024 x 512 with corners rolled to the left-most floor
    corner; layout depth at 256 x 128 with camera height 1.6, the size of its processed boundary).
``metric``
    omnidl's own: no rescaling (rooms as predicted, metres), everything else as ``horizonnet``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from ..geometry.polygon import is_simple, ray_polygon_hit
from .layout import LayoutMetrics, gt_layout_from_batch, iou_2d, iou_3d, layout_fields

CORNER_GROUPS = ("4", "6", "8", "10+", "odd")


@dataclass(frozen=True)
class LayoutProtocol:
    """Settings of one named protocol (module docstring)."""

    name: str
    camera_height: float | None = 1.6        # None: rooms as given (metric)
    width: int = 1024                        # corner / pixel error resolution
    height: int = 512
    depth_width: int = 1024                  # layout depth resolution
    depth_height: int = 512
    groups: bool = True


LAYOUT_PROTOCOLS: dict[str, LayoutProtocol] = {
    "horizonnet": LayoutProtocol("horizonnet"),
    "lgtnet": LayoutProtocol("lgtnet", depth_width=256, depth_height=128),
    "metric": LayoutProtocol("metric", camera_height=None),
}


def get_layout_protocol(name: str) -> LayoutProtocol:
    if name not in LAYOUT_PROTOCOLS:
        raise ValueError(f"unknown layout protocol {name!r}; expected one of {', '.join(LAYOUT_PROTOCOLS)}")
    return LAYOUT_PROTOCOLS[name]


def corner_group(n: int) -> str:
    """HorizonNet's grouping of a ground truth by its corner count: ``4``, ``6``, ``8``, ``10+`` or ``odd``."""
    return "odd" if n % 2 else (str(n) if n < 10 else "10+")


def at_camera_height(polygon: np.ndarray, heights: tuple[float, float], camera_height: float | None
                     ) -> tuple[np.ndarray, tuple[float, float]]:
    """Scale a room (``polygon (N, 2)``, ``(h_floor, h_ceiling)``, camera at the origin) so that
    ``h_floor = -camera_height``; unchanged for ``camera_height=None``."""
    p = np.asarray(polygon, dtype=np.float64)
    if camera_height is None:
        return p, (float(heights[0]), float(heights[1]))
    if not heights[0] < 0:
        raise ValueError(f"layout floor height {heights[0]} must be below the camera (< 0) to scale it to the camera "
                         "height")
    k = camera_height / -heights[0]
    return p * k, (heights[0] * k, heights[1] * k)


def layout_surfaces(polygon: np.ndarray, heights: tuple[float, float], width: int, height: int
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Layout depth ``(H, W)`` (range in the room's units) and surface labels ``(H, W)`` (0 ceiling, 1 wall,
    2 floor) of the equirectangular panorama of a room whose polygon contains the camera.

    Pixel centres: longitude ``2 pi (j + 0.5) / W - pi``, latitude ``pi / 2 - pi (i + 0.5) / H``; the layout-frame
    horizontal direction of a column is ``(sin lon, cos lon)``."""
    poly = np.asarray(polygon, dtype=np.float64)
    lon = 2 * math.pi * (np.arange(width) + 0.5) / width - math.pi
    lat = math.pi / 2 - math.pi * (np.arange(height) + 0.5) / height
    b = np.stack([np.sin(lon), np.cos(lon)], -1)
    r, _ = ray_polygon_hit(poly, np.zeros((width, 2)), b)
    if not np.isfinite(r).all():
        raise ValueError("layout_surfaces: the room polygon does not surround the camera (a column sees no wall)")
    h_f, h_c = heights
    t = np.tan(lat)[:, None]
    z = t * r[None]                                     # height where each pixel ray meets its column's wall
    labels = np.where(z > h_c, 0, np.where(z < h_f, 2, 1))
    s, c = np.sin(lat)[:, None], np.cos(lat)[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.where(labels == 0, h_c / s, np.where(labels == 2, h_f / s, r[None] / c))
    return depth, labels


def corner_pixels(polygon: np.ndarray, heights: tuple[float, float], width: int, height: int) -> np.ndarray:
    """``(N, 2, 2)`` ``[ceiling, floor]`` pixel positions ``(x, y)`` (continuous ``u, v``) of each corner, sorted by
    column (left to right, as ``label_cor`` files and LGT-Net's rolled corner lists are; either orientation of
    the polygon gives the same order)."""
    p = np.asarray(polygon, dtype=np.float64)
    lon = np.arctan2(p[:, 0], p[:, 1])
    r = np.hypot(p[:, 0], p[:, 1])
    u = (lon + math.pi) / (2 * math.pi) * width
    out = np.zeros((len(p), 2, 2))
    for k, h in enumerate((heights[1], heights[0])):
        lat = np.arctan2(h, r)
        out[:, k, 0], out[:, k, 1] = u, (math.pi / 2 - lat) / math.pi * height
    return out[np.argsort(u, kind="stable")]


def cuboid_errors(pred: tuple, gt: tuple, width: int, height: int) -> dict[str, float]:
    """``corner_error`` and ``pixel_error`` (fractions) of two 4-corner rooms ``(polygon, (h_floor, h_ceiling))``."""
    cp, cg = corner_pixels(*pred, width, height), corner_pixels(*gt, width, height)
    ce = np.linalg.norm(cp - cg, axis=-1).mean() / math.hypot(width, height)
    _, lp = layout_surfaces(*pred, width, height)
    _, lg = layout_surfaces(*gt, width, height)
    return {"corner_error": float(ce), "pixel_error": float((lp != lg).mean())}


def layout_depth_errors(pred: tuple, gt: tuple, width: int, height: int) -> dict[str, float]:
    """RMSE and δ1 of the layout depth maps of two rooms ``(polygon, (h_floor, h_ceiling))``."""
    dp, _ = layout_surfaces(*pred, width, height)
    dg, _ = layout_surfaces(*gt, width, height)
    ratio = np.maximum(dp / dg, dg / dp)
    return {"depth_rmse": float(np.sqrt(np.mean((dp - dg) ** 2))), "depth_delta1": float(np.mean(ratio < 1.25))}


def protocol_scores(pred_polygon: np.ndarray, pred_heights: tuple[float, float], gt_polygon: np.ndarray,
                    gt_heights: tuple[float, float], protocol: str | LayoutProtocol = "horizonnet") -> dict[str, float]:
    """All scores of one image under ``protocol`` (module docstring). Heights are ``(h_floor, h_ceiling)``
    relative to the camera. A prediction that is not a simple polygon (fewer than 3 corners, crossing walls)
    scores 0 IoU; one that does not surround the camera gets its IoUs only (no layout depth / corner
    metrics)."""
    proto = get_layout_protocol(protocol) if isinstance(protocol, str) else protocol
    gp, gh = at_camera_height(gt_polygon, gt_heights, proto.camera_height)
    pred_polygon = np.asarray(pred_polygon, dtype=np.float64)
    if len(pred_polygon) < 3 or not is_simple(pred_polygon, 0.0):
        return {"iou_2d": 0.0, "iou_3d": 0.0}
    pp, ph = at_camera_height(pred_polygon, pred_heights, proto.camera_height)
    out = {"iou_2d": iou_2d(pp, gp), "iou_3d": iou_3d(pp, ph, gp, gh)}
    try:
        out.update(layout_depth_errors((pp, ph), (gp, gh), proto.depth_width, proto.depth_height))
        if len(pp) == 4 and len(gp) == 4:
            out.update(cuboid_errors((pp, ph), (gp, gh), proto.width, proto.height))
    except ValueError:
        pass                                            # camera outside the predicted room: IoU only
    return out


class LayoutProtocolMetrics:
    """Engine metric (``reset / update / compute``): protocol layout scores of ``outputs["layout"]`` (written by a
    layout hook, e.g. ``layout_manhattan_central``) against the batch's ground-truth room, averaged over images.

    Args:
        protocol: ``horizonnet`` | ``lgtnet`` | ``metric`` (see :data:`LAYOUT_PROTOCOLS`).
        maps: also report the boundary / edge / corner map metrics of :class:`~omnidl.metrics.layout.LayoutMetrics`.
        corner_threshold: for those maps.

    A failed prediction (no layout) counts as 0 IoU and in ``layout_fail_rate`` (the peers' scripts need a
    layout for every image); a ground truth that is not a simple polygon is skipped (``gt_skipped``), as
    HorizonNet's ``eval_general.py`` does.
    """

    def __init__(self, protocol: str = "horizonnet", maps: bool = True, corner_threshold: float = 0.5) -> None:
        self.protocol = get_layout_protocol(protocol)
        self.maps = LayoutMetrics(corner_threshold=corner_threshold) if maps else None
        self.reset()

    def reset(self) -> None:
        self._sums: dict[str, float] = {}
        self._counts: dict[str, int] = {}
        if self.maps is not None:
            self.maps.reset()

    def _add(self, key: str, val: float) -> None:
        if not math.isfinite(val):
            raise ValueError(f"LayoutProtocolMetrics: {key} is {val} (expected a finite score)")
        self._sums[key] = self._sums.get(key, 0.0) + float(val)
        self._counts[key] = self._counts.get(key, 0) + 1

    def add(self, pred: tuple | None, gt: tuple) -> dict[str, float]:
        """Score one image: ``pred = (polygon, (h_floor, h_ceiling))`` or ``None`` (failed), ``gt`` likewise."""
        g_poly, g_h = np.asarray(gt[0], float), gt[1]
        if len(g_poly) < 3 or not is_simple(g_poly, 0.0):
            self._add("gt_skipped", 1.0)
            return {}
        self._add("gt_skipped", 0.0)
        self._add("layout_fail_rate", 0.0 if pred is not None else 1.0)
        scores = protocol_scores(pred[0], pred[1], g_poly, g_h, self.protocol) if pred is not None \
            else {"iou_2d": 0.0, "iou_3d": 0.0}
        for k, v in scores.items():
            self._add(k, v)
        if self.protocol.groups:
            grp = corner_group(len(g_poly))
            for k in ("iou_2d", "iou_3d"):
                self._add(f"{k}@{grp}", scores[k])
        return scores

    @torch.no_grad()
    def update(self, outputs: dict, batch: dict) -> None:
        if self.maps is not None and "boundary" in outputs and "corner" in outputs:
            self.maps.update(outputs, batch)
        layouts = outputs.get("layout")
        if layouts is None:
            return
        for b in range(len(layouts)):
            gt = gt_layout_from_batch(batch, b)
            if gt is None:
                continue
            ok, corners, h = layout_fields(layouts[b])
            self.add((corners, h) if ok and len(corners) >= 3 else None, gt)

    def compute(self) -> dict[str, Any]:
        out = self.maps.compute() if self.maps is not None else {}
        out.update({k: self._sums[k] / self._counts[k] for k in sorted(self._sums)})
        return out
