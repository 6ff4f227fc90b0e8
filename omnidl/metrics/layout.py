"""Layout metrics (thesis §5.6): corner error in metres (CE), normalised corner error (CEN), 3D IoU,
up-to-scale 3D IoU, 2D IoU, and the edge/corner map precision/recall/accuracy/IoU of Table 5.1.

Conventions: layouts are top-view polygons ``(N, 2)`` extruded between ``h_floor < h_ceiling``
(metres, camera circle at ``z = 0``, see :mod:`omnidl.postprocess.layout`). Polygon areas and
intersections are computed exactly for simple (possibly non-convex) polygons of any orientation:
``area(P ∩ Q) = sum_e sum_f s_e s_f area(T_e ∩ T_f)`` where ``T_e`` is the triangle (origin, edge
``e``) with orientation sign ``s_e``, and each convex ``T_e ∩ T_f`` is clipped with
Sutherland–Hodgman.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch


# ---------------------------------------------------------------------------------------------
# polygons
# ---------------------------------------------------------------------------------------------

def polygon_area(poly: np.ndarray) -> float:
    """Signed area of a ``(N, 2)`` polygon (positive counter-clockwise)."""
    p = np.asarray(poly, float)
    if len(p) < 3:
        return 0.0
    return 0.5 * float(np.sum(p[:, 0] * np.roll(p[:, 1], -1) - np.roll(p[:, 0], -1) * p[:, 1]))


def _clip_convex(subject: list, clip: np.ndarray) -> list:
    """Sutherland–Hodgman: ``subject`` polygon clipped by convex CCW ``clip`` (3 vertices here)."""
    out = subject
    n = len(clip)
    for i in range(n):
        if not out:
            break
        a, b = clip[i], clip[(i + 1) % n]
        ex, ey = b[0] - a[0], b[1] - a[1]
        inp = out
        out = []
        m = len(inp)
        for j in range(m):
            p, q = inp[j], inp[(j + 1) % m]
            sp = ex * (p[1] - a[1]) - ey * (p[0] - a[0])
            sq = ex * (q[1] - a[1]) - ey * (q[0] - a[0])
            if sp >= 0:
                out.append(p)
            if (sp >= 0) != (sq >= 0):
                t = sp / (sp - sq)
                out.append((p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1])))
    return out


def _area_list(pts: list) -> float:
    if len(pts) < 3:
        return 0.0
    s = 0.0
    for i in range(len(pts)):
        x1, y1 = pts[i]
        x2, y2 = pts[(i + 1) % len(pts)]
        s += x1 * y2 - x2 * y1
    return 0.5 * s


def polygon_intersection_area(p: np.ndarray, q: np.ndarray) -> float:
    """Exact area of the intersection of two simple polygons ``(N, 2)``, ``(M, 2)`` (any orientation)."""
    p, q = np.asarray(p, float), np.asarray(q, float)
    if len(p) < 3 or len(q) < 3:
        return 0.0
    # origin at a common point keeps the fan triangles small
    c = p.mean(0)
    p, q = p - c, q - c
    total = 0.0
    tp = [(np.zeros(2), p[i], p[(i + 1) % len(p)]) for i in range(len(p))]
    tq = [(np.zeros(2), q[i], q[(i + 1) % len(q)]) for i in range(len(q))]
    def orient(t):
        a = _area_list([tuple(v) for v in t])
        return (1.0 if a > 0 else -1.0), (np.array(t) if a > 0 else np.array(t[::-1]))
    oq = [orient(t) for t in tq if abs(_area_list([tuple(v) for v in t])) > 0]
    for t in tp:
        a = _area_list([tuple(v) for v in t])
        if a == 0:
            continue
        sp, T = (1.0, t) if a > 0 else (-1.0, t[::-1])
        subj = [tuple(v) for v in T]
        for sq, U in oq:
            total += sp * sq * _area_list(_clip_convex(subj, U))
    sign = np.sign(polygon_area(p)) * np.sign(polygon_area(q))
    return float(abs(total) if sign != 0 else 0.0)


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
    Returns: ``ce`` (m), ``cen`` (% of the ground-truth 3D bounding-box diagonal), ``iou_3d``,
    ``iou_3d_u2s`` (prediction rescaled so its floor distance equals the ground truth's, as
    methods without scale are evaluated with a known camera height), ``iou_2d`` (all in %).
    """
    def c3(c, h):
        c = np.asarray(c, float)
        n = len(c)
        return np.concatenate([np.c_[c, np.full(n, h[1])], np.c_[c, np.full(n, h[0])]])
    gt3 = c3(gt_corners, gt_h)
    ce = corner_error(c3(pred_corners, pred_h), gt3)
    k = gt_h[0] / pred_h[0] if pred_h[0] != 0 else 1.0
    return {"ce": ce, "cen": 100.0 * ce / max(bbox_diagonal(gt3), 1e-12),
            "iou_3d": 100.0 * iou_3d(pred_corners, pred_h, gt_corners, gt_h),
            "iou_3d_u2s": 100.0 * iou_3d(np.asarray(pred_corners) * k, (pred_h[0] * k, pred_h[1] * k), gt_corners, gt_h),
            "iou_2d": 100.0 * iou_2d(pred_corners, gt_corners)}


# ---------------------------------------------------------------------------------------------
# edge / corner maps (Table 5.1)
# ---------------------------------------------------------------------------------------------

def boundary_rows(boundary: torch.Tensor, height: int) -> torch.Tensor:
    """HorizonNet boundary angles ``(..., W)`` (radians below the horizon) -> continuous rows."""
    return (boundary / math.pi + 0.5) * height


def edge_map(boundary: torch.Tensor, corner_cols: list[torch.Tensor] | None, height: int,
             thickness: float = 1.0) -> torch.Tensor:
    """Binary edge map ``(B, H, W)``: ceiling/floor boundary pixels (``|row - v| <= thickness``) and the
    vertical wall-wall edges between them at the given corner columns (integer indices per image)."""
    B, _, W = boundary.shape
    rows = boundary_rows(boundary, height)                                    # (B, 2, W)
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
    rows = boundary_rows(boundary, height)
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


def corner_columns_from_prob(corner_prob: torch.Tensor, threshold: float = 0.5) -> list[torch.Tensor]:
    """Integer peak columns per image from ``(B, W)`` probabilities (see :func:`...find_peaks`)."""
    from ..postprocess.layout.corners import find_peaks
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
    * Layout metrics (when ``solver`` is set and the batch has ground-truth corners: the data engine's
      ``corners_cam``/``num_walls`` or ``corners_3d``): the pipeline runs on the predictions
      (``outputs["layout"]`` from a hook is used if present; ``camera_height`` selects the central
      pipeline) and CE, CEN, 3D IoU, up-to-scale 3D IoU and 2D IoU are averaged over the images where
      a layout was recovered; ``layout_fail_rate`` counts the others. The rig radius comes from ``rc``,
      ``camera`` or the batch ``meta`` (``rig_radius``).
    """

    def __init__(self, solver: str | None = "atlanta", corner_threshold: float = 0.5, edge_thickness: float = 1.0,
                 corner_radius: float = 3.0, rc: float | None = None, camera: Any = None,
                 camera_height: float | None = None, central: bool = False, target_units: str = "rows"):
        self.solver = solver
        self.corner_threshold = corner_threshold
        self.edge_thickness = edge_thickness
        self.corner_radius = corner_radius
        self.rc = rc
        self.camera = camera
        self.camera_height = camera_height
        self.central = bool(central) or camera_height is not None
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
                gt_b = (gt_b / H - 0.5) * math.pi
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
        if self.solver is None or not ("corners_3d" in batch or "corners_cam" in batch):
            return
        from ..postprocess.layout.hooks import gt_layout_from_batch, layouts_from_outputs
        layouts = outputs.get("layout")
        if layouts is None:
            layouts = layouts_from_outputs(outputs, batch, world=self.solver, rc=self.rc, camera=self.camera,
                                           camera_height=self.camera_height, central=self.central)
        for b in range(B):
            gt = gt_layout_from_batch(batch, b)
            if gt is None or len(gt[0]) < 3:
                continue
            gt_poly, gt_h = gt
            lay = layouts[b]
            if isinstance(lay, dict):
                from ..postprocess.layout.layout import Layout
                lay = Layout.from_dict(lay)
            self._add("layout_fail_rate", 0.0 if lay.ok else 1.0)
            if not lay.ok:
                continue
            for k, v in layout_scores(lay.corners, (lay.h_floor, lay.h_ceiling), gt_poly, gt_h).items():
                self._add(k, v)

    def compute(self) -> dict[str, float]:
        return {k: self._sums[k] / self._counts[k] for k in sorted(self._sums)}
