"""Layout metrics (thesis §5.6): corner error in metres (CE), normalised corner error (CEN), 3D IoU,
up-to-scale 3D IoU, 2D IoU, and the edge/corner map precision/recall/accuracy/IoU of Table 5.1.

The metrics only *read* layouts: predicted ones come from ``outputs["layout"]`` (written there by a
layout post-processing hook, e.g. ``layout_atlanta``), ground-truth ones from the batch
(:func:`gt_layout_from_batch`). Nothing here runs the geometric pipeline.

Conventions: layouts are top-view polygons ``(N, 2)`` extruded between ``h_floor < h_ceiling``
(metres, layout frame ``X_w = UPRIGHT_TO_WORLD @ X_cam``, camera at ``z = 0``). Polygon areas and
intersections are exact for simple (possibly non-convex) polygons of any orientation
(:mod:`omnidl.geometry.polygon`).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from ..geometry.boundary import angles_to_rows, rows_to_angles
from ..geometry.polygon import polygon_area, polygon_intersection_area
from ..geometry.rotations import UPRIGHT_TO_WORLD

#: camera frame -> layout frame (float64 numpy)
_R = np.asarray(UPRIGHT_TO_WORLD, dtype=np.float64)


# ---------------------------------------------------------------------------------------------
# layouts: ground truth from the batch, predictions from outputs["layout"]
# ---------------------------------------------------------------------------------------------

def corners_to_layout(corners_cam: np.ndarray) -> tuple[np.ndarray, float, float]:
    """``(N, 2, 3)`` camera-frame ``[ceiling, floor]`` corners -> top-view polygon ``(N, 2)``, ``h_c``, ``h_f``
    (layout frame; heights are the means over the corners)."""
    c = np.asarray(corners_cam, float) @ _R.T
    return c[:, 0, :2], float(c[:, 0, 2].mean()), float(c[:, 1, 2].mean())


def gt_layout_from_batch(batch: dict, b: int) -> tuple[np.ndarray, tuple[float, float]] | None:
    """Ground-truth ``(polygon (N, 2), (h_floor, h_ceiling))`` of image ``b`` in the layout frame, if any.

    Reads the data engine's ``corners_cam (N_MAX, 2, 3)`` + ``num_walls``, or a ``corners_3d (2N, 3)``
    already in the layout frame (N ceiling corners then N floor corners); ``None`` without either.
    """
    if "corners_cam" in batch:
        c = batch["corners_cam"][b].detach().cpu().double().numpy()
        n = int(batch["num_walls"][b]) if "num_walls" in batch else len(c)
        poly, h_c, h_f = corners_to_layout(c[:n])
        return poly, (h_f, h_c)
    if "corners_3d" in batch:
        g = batch["corners_3d"][b]
        g = g.detach().cpu().double().numpy() if isinstance(g, torch.Tensor) else np.asarray(g, float)
        g = g[np.all(np.isfinite(g), -1)]
        n = len(g) // 2
        return g[:n, :2], (float(g[n:, 2].mean()), float(g[:n, 2].mean()))
    return None


def layout_fields(layout: Any) -> tuple[bool, np.ndarray, tuple[float, float]]:
    """``(ok, corners (N, 2), (h_floor, h_ceiling))`` of a predicted layout.

    Accepts the post-processing ``Layout`` object (attributes ``ok``, ``corners``, ``h_floor``,
    ``h_ceiling``) or its ``to_dict()`` form (keys ``ok``, ``corners_2d``, ``h_floor``, ``h_ceiling``),
    which is what the layout hooks put in ``outputs["layout"]``.
    """
    if isinstance(layout, dict):
        if not layout.get("ok", False):
            return False, np.zeros((0, 2)), (math.nan, math.nan)
        return True, np.asarray(layout["corners_2d"], float), (float(layout["h_floor"]), float(layout["h_ceiling"]))
    if not layout.ok:
        return False, np.zeros((0, 2)), (math.nan, math.nan)
    return True, np.asarray(layout.corners, float), (float(layout.h_floor), float(layout.h_ceiling))


# ---------------------------------------------------------------------------------------------
# IoU of extruded polygons
# ---------------------------------------------------------------------------------------------

def iou_2d(p: np.ndarray, q: np.ndarray) -> float:
    """Top-view (floor plan) IoU of two polygons."""
    ap, aq = abs(polygon_area(p)), abs(polygon_area(q))
    inter = polygon_intersection_area(p, q)
    union = ap + aq - inter
    return float(inter / union) if union > 0 else 0.0


def iou_3d(p: np.ndarray, hp: tuple[float, float], q: np.ndarray, hq: tuple[float, float]) -> float:
    """IoU of two extruded polygons; ``hp = (h_floor, h_ceiling)`` of ``p`` and ``hq`` of ``q``."""
    ap, aq = abs(polygon_area(p)), abs(polygon_area(q))
    lp, lq = hp[1] - hp[0], hq[1] - hq[0]
    overlap = max(0.0, min(hp[1], hq[1]) - max(hp[0], hq[0]))
    inter = polygon_intersection_area(p, q) * overlap
    union = ap * lp + aq * lq - inter
    return float(inter / union) if union > 0 else 0.0


# ---------------------------------------------------------------------------------------------
# corner errors
# ---------------------------------------------------------------------------------------------

def corner_error(pred: np.ndarray, gt: np.ndarray) -> float:
    """Mean L2 distance (metres) between matched 3D corners ``(N, 3)`` and ``(M, 3)``.

    Corners are matched one-to-one by the Hungarian algorithm; when the counts differ, every
    unmatched corner (either side) contributes its distance to the nearest corner of the other set.
    """
    from scipy.optimize import linear_sum_assignment
    pred, gt = np.asarray(pred, float), np.asarray(gt, float)
    if len(pred) == 0 or len(gt) == 0:
        return math.inf
    D = np.linalg.norm(pred[:, None] - gt[None], axis=-1)
    r, c = linear_sum_assignment(D)
    d = list(D[r, c])
    d += list(D[np.setdiff1d(np.arange(len(pred)), r)].min(1)) if len(pred) > len(r) else []
    d += list(D[:, np.setdiff1d(np.arange(len(gt)), c)].min(0)) if len(gt) > len(c) else []
    return float(np.mean(d))


def bbox_diagonal(points: np.ndarray) -> float:
    p = np.asarray(points, float)
    return float(np.linalg.norm(p.max(0) - p.min(0)))


def layout_scores(pred_corners: np.ndarray, pred_h: tuple[float, float], gt_corners: np.ndarray,
                  gt_h: tuple[float, float]) -> dict[str, float]:
    """All layout scores of one prediction against the ground truth.

    Args:
        pred_corners, gt_corners: ``(N, 2)`` / ``(M, 2)`` top-view polygons (metres).
        pred_h, gt_h: ``(h_floor, h_ceiling)``.
    Returns: ``ce`` (m), ``cen`` (``ce`` as a fraction of the ground-truth 3D bounding-box diagonal),
    ``iou_3d``, ``iou_3d_u2s`` (prediction rescaled so its floor distance equals the ground truth's, as
    methods without scale are evaluated with a known camera height), ``iou_2d``. ``cen`` and the IoUs are
    fractions in [0, 1] like every omnidl metric (printed tables show them in percent, labelled ``(%)``).
    """
    def c3(c, h):
        c = np.asarray(c, float)
        n = len(c)
        return np.concatenate([np.c_[c, np.full(n, h[1])], np.c_[c, np.full(n, h[0])]])
    gt3 = c3(gt_corners, gt_h)
    ce = corner_error(c3(pred_corners, pred_h), gt3)
    k = gt_h[0] / pred_h[0] if pred_h[0] != 0 else 1.0
    return {"ce": ce, "cen": ce / max(bbox_diagonal(gt3), 1e-12),
            "iou_3d": iou_3d(pred_corners, pred_h, gt_corners, gt_h),
            "iou_3d_u2s": iou_3d(np.asarray(pred_corners) * k, (pred_h[0] * k, pred_h[1] * k), gt_corners, gt_h),
            "iou_2d": iou_2d(pred_corners, gt_corners)}


# ---------------------------------------------------------------------------------------------
# edge / corner maps (Table 5.1)
# ---------------------------------------------------------------------------------------------

def edge_map(boundary: torch.Tensor, corner_cols: list[torch.Tensor] | None, height: int,
             thickness: float = 1.0) -> torch.Tensor:
    """Binary edge map ``(B, H, W)``: ceiling/floor boundary pixels (``|row - v| <= thickness``) and the
    vertical wall-wall edges between them at the given corner columns (integer indices per image)."""
    B, _, W = boundary.shape
    rows = angles_to_rows(boundary, height)                                    # (B, 2, W)
    r = torch.arange(height, dtype=rows.dtype, device=rows.device).view(1, height, 1) + 0.5
    m = ((r - rows[:, 0:1]).abs() <= thickness) | ((r - rows[:, 1:2]).abs() <= thickness)
    if corner_cols is not None:
        for b in range(B):
            for c in corner_cols[b].tolist():
                c = int(c) % W
                m[b, :, c] |= (r[0, :, 0] >= rows[b, 0, c]) & (r[0, :, 0] <= rows[b, 1, c])
    return m


def corner_map(boundary: torch.Tensor, corner_cols: list[torch.Tensor], height: int, radius: float = 3.0) -> torch.Tensor:
    """Binary corner map ``(B, H, W)``: discs of ``radius`` px at the ceiling and floor ends of each corner column."""
    B, _, W = boundary.shape
    rows = angles_to_rows(boundary, height)
    vv = torch.arange(height, dtype=rows.dtype, device=rows.device).view(height, 1) + 0.5
    uu = torch.arange(W, dtype=rows.dtype, device=rows.device).view(1, W) + 0.5
    out = torch.zeros(B, height, W, dtype=torch.bool, device=rows.device)
    for b in range(B):
        for c in corner_cols[b].tolist():
            ci = int(c) % W
            du = (uu - (ci + 0.5)).abs()
            du = torch.minimum(du, W - du)
            for k in (0, 1):
                out[b] |= (du ** 2 + (vv - rows[b, k, ci]) ** 2) <= radius ** 2
    return out


def binary_scores(pred: torch.Tensor, gt: torch.Tensor) -> dict[str, float]:
    """Precision, recall, accuracy and IoU of binary maps (any shape)."""
    pred, gt = pred.bool(), gt.bool()
    tp = (pred & gt).sum().item()
    fp = (pred & ~gt).sum().item()
    fn = (~pred & gt).sum().item()
    tn = (~pred & ~gt).sum().item()
    return {"precision": tp / (tp + fp) if tp + fp else 0.0, "recall": tp / (tp + fn) if tp + fn else 0.0,
            "accuracy": (tp + tn) / max(tp + tn + fp + fn, 1), "iou": tp / (tp + fp + fn) if tp + fp + fn else 0.0}


def find_peaks(prob: np.ndarray, threshold: float = 0.5, radius: int | None = None) -> np.ndarray:
    """Sub-pixel columns (continuous ``u``) of local maxima of a circular ``(W,)`` probability.

    A column is a peak when it is the maximum within ``radius`` columns (circularly; default
    ``W/200``, at least 2) and above ``threshold``. The position is refined by a parabola through the peak and
    its neighbours. Returns sorted ``u`` values in ``[0, W)``.
    """
    p = np.nan_to_num(np.asarray(prob, float).reshape(-1), nan=0.0)
    W = p.shape[0]
    r = max(2, int(round(W / 200))) if radius is None else max(1, int(radius))
    idx = np.arange(W)
    win = np.stack([np.roll(p, k) for k in range(-r, r + 1)], 0)
    is_max = (p >= win.max(0)) & (p > threshold)
    # plateaus: keep the first column of equal maxima
    is_max &= ~((np.roll(p, 1) == p) & np.roll(is_max, 1))
    peaks = idx[is_max]
    if len(peaks) == 0:
        return np.zeros(0)
    l, c, rr = p[(peaks - 1) % W], p[peaks], p[(peaks + 1) % W]
    den = l - 2 * c + rr
    off = np.where(np.abs(den) > 1e-12, 0.5 * (l - rr) / np.where(np.abs(den) > 1e-12, den, 1.0), 0.0)
    off = np.clip(off, -0.5, 0.5)
    return np.sort(np.mod(peaks + 0.5 + off, W))


def corner_columns_from_prob(corner_prob: torch.Tensor, threshold: float = 0.5) -> list[torch.Tensor]:
    """Integer peak columns per image from ``(B, W)`` probabilities (see :func:`find_peaks`)."""
    return [torch.as_tensor(np.floor(find_peaks(p.detach().cpu().double().numpy(), threshold)), dtype=torch.long)
            for p in corner_prob]


# ---------------------------------------------------------------------------------------------
# engine metric object
# ---------------------------------------------------------------------------------------------

class LayoutMetrics:
    """Engine metric: ``reset() / update(outputs, batch) / compute()``.

    * Map metrics (always): from ``outputs["boundary"] (B, 2, W)`` and ``outputs["corner"] (B, 1, W)``
      logits against ``batch["boundary"]`` (pixel rows, or radians with ``target_units="radians"``;
      ``boundary_valid`` masks) and ``batch["corner_heat"]``/``batch["corner"]`` targets (Table 5.1:
      P/R/Acc/IoU of the edge and corner maps, plus the mean absolute boundary error in pixels).
    * Layout metrics (when ``outputs["layout"]`` holds the layouts of a layout hook, e.g.
      ``postprocess: [layout_atlanta]``, and the batch has ground-truth corners: the data engine's
      ``corners_cam``/``num_walls`` or ``corners_3d``): CE, CEN, 3D IoU, up-to-scale 3D IoU and 2D IoU
      averaged over the images where a layout was recovered; ``layout_fail_rate`` counts the others.

    Units: metres (``ce``), pixels (``boundary_px``); everything else is a fraction in [0, 1].
    """

    def __init__(self, corner_threshold: float = 0.5, edge_thickness: float = 1.0, corner_radius: float = 3.0,
                 target_units: str = "rows"):
        self.corner_threshold = corner_threshold
        self.edge_thickness = edge_thickness
        self.corner_radius = corner_radius
        if target_units not in ("rows", "radians"):
            raise ValueError(f"target_units must be 'rows' or 'radians', got {target_units!r}")
        self.target_units = target_units
        self.reset()

    def reset(self) -> None:
        self._sums: dict[str, float] = {}
        self._counts: dict[str, int] = {}

    def _add(self, key: str, val: float) -> None:
        if math.isfinite(val):
            self._sums[key] = self._sums.get(key, 0.0) + float(val)
            self._counts[key] = self._counts.get(key, 0) + 1

    @torch.no_grad()
    def update(self, outputs: dict, batch: dict) -> None:
        bon = outputs["boundary"].detach().float()
        B, _, W = bon.shape
        img = batch.get("image")
        H = int(img.shape[-2]) if img is not None else W // 2
        prob = torch.sigmoid(outputs["corner"].detach().float()).reshape(B, W)
        if "boundary" in batch:
            gt_b = batch["boundary"].to(bon.device).float()
            if self.target_units == "rows":
                gt_b = rows_to_angles(gt_b, H)
            valid = batch.get("boundary_valid")
            valid = torch.ones_like(gt_b, dtype=torch.bool) if valid is None else valid.to(bon.device).bool()
            if valid.any():
                self._add("boundary_px", ((bon - gt_b).abs()[valid].mean().item()) * H / math.pi)
            gt_b = torch.where(valid, gt_b, bon)
            pc = corner_columns_from_prob(prob, self.corner_threshold)
            heat = batch.get("corner_heat", batch.get("corner"))
            gc = corner_columns_from_prob(heat.reshape(B, W).float(), 0.9) if heat is not None else pc
            ps = binary_scores(edge_map(bon, pc, H, self.edge_thickness), edge_map(gt_b, gc, H, self.edge_thickness))
            cs = binary_scores(corner_map(bon, pc, H, self.corner_radius), corner_map(gt_b, gc, H, self.corner_radius))
            for k, v in ps.items():
                self._add(f"edge_{k}", v)
            for k, v in cs.items():
                self._add(f"corner_{k}", v)
        layouts = outputs.get("layout")
        if layouts is None:
            return
        for b in range(B):
            gt = gt_layout_from_batch(batch, b)
            if gt is None or len(gt[0]) < 3:
                continue
            ok, corners, h = layout_fields(layouts[b])
            self._add("layout_fail_rate", 0.0 if ok else 1.0)
            if ok:
                for k, v in layout_scores(corners, h, gt[0], gt[1]).items():
                    self._add(k, v)

    def compute(self) -> dict[str, float]:
        return {k: self._sums[k] / self._counts[k] for k in sorted(self._sums)}
