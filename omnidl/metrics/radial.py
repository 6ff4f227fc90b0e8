"""Depth and segmentation metrics binned by the distance to the principal point (thesis Fig. 7.2, 7.5,
7.8, 7.9): "the x-axis defines the distance of the pixels to the optical center and the y-axis the
computed error, defined as mean and one standard deviation".

For every radius bin and every image, the usual metrics are computed on the image's valid pixels
in that bin — depth: :func:`omnidl.metrics.depth.depth_errors` (``mre mae rmse rmse_log delta1..3``);
segmentation: :func:`omnidl.metrics.segmentation.scores_from_confusion` (``miou macc pixel_acc``,
unknown class excluded) — and the table reports, per bin, their mean and standard deviation over
the images that have pixels in the bin. For segmentation the dataset-wide per-bin scores (one
confusion matrix per bin, like :class:`~omnidl.metrics.segmentation.SegmentationMetrics`) are
reported too (``miou_all``, ``macc_all``, ``pixel_acc_all``).

The radius of each pixel comes from ``batch[radius_key]`` (``(B, 1, H, W)`` or ``(B, H, W)``, e.g.
the ``radius`` of :class:`omnidl.data.fisheye.ViewsFromPanoramas`, in pixels of the calibrated
image) or from a fixed ``radius`` map given at construction.
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .depth import DEPTH_METRICS, depth_errors
from .segmentation import confusion_matrix, scores_from_confusion

SEG_METRICS = ("miou", "macc", "pixel_acc")


def radial_bin_edges(max_radius: float, num_bins: int) -> list[float]:
    """``num_bins + 1`` equally spaced edges on ``[0, max_radius]``."""
    if not (max_radius > 0 and num_bins >= 1):
        raise ValueError(f"radial bins need max_radius > 0 and num_bins >= 1, got {max_radius}, {num_bins}")
    return [float(x) for x in np.linspace(0.0, float(max_radius), int(num_bins) + 1)]


class RadialMetrics:
    """Metrics per radius bin, mean ± std over images (engine metrics contract).

    Args:
        edges: increasing bin edges (pixels); a pixel with ``edges[b] <= r < edges[b+1]`` is in bin ``b``
            (the last bin includes its upper edge). Default: ``num_bins`` equal bins up to the largest
            radius of a valid pixel of the first batch.
        num_bins: used when ``edges`` is None.
        tasks: ``depth`` and/or ``semantic`` (outputs/batch keys of the same names).
        num_classes, ignore_index: segmentation classes (including unknown) and the ignored label.
        min_depth, max_depth: as :class:`omnidl.metrics.depth.DepthMetrics`.
        radius: optional fixed ``(H, W)`` radius map (instead of ``batch[radius_key]``).
    """

    def __init__(self, edges: Sequence[float] | None = None, num_bins: int = 8, tasks: Sequence[str] = ("depth",
                 "semantic"), num_classes: int = 14, ignore_index: int = 0, min_depth: float = 1e-7,
                 max_depth: float | None = None, radius: Tensor | None = None, radius_key: str = "radius") -> None:
        if edges is not None:
            edges = [float(e) for e in edges]
            if len(edges) < 2 or any(b <= a for a, b in zip(edges, edges[1:])):
                raise ValueError(f"RadialMetrics: edges must be increasing with at least 2 values, got {edges}")
        tasks = tuple(tasks)
        if not tasks or set(tasks) - {"depth", "semantic"}:
            raise ValueError(f"RadialMetrics: tasks must be a subset of ('depth', 'semantic'), got {tasks}")
        self.edges, self.num_bins, self.tasks = edges, int(num_bins), tasks
        self.num_classes, self.ignore_index = int(num_classes), ignore_index
        self.min_depth, self.max_depth = min_depth, max_depth
        self.radius, self.radius_key = radius, radius_key
        self.reset()

    def reset(self) -> None:
        nb = 0 if self.edges is None else len(self.edges) - 1
        self.values: dict[str, list[list[float]]] = {}
        self.pixels = [0] * nb
        self.confusion = [torch.zeros(self.num_classes, self.num_classes, dtype=torch.int64) for _ in range(nb)]

    def _bins(self, radius: Tensor, valid: Tensor) -> Tensor:
        if self.edges is None:
            rmax = float(radius[valid].max()) if bool(valid.any()) else float(radius.max())
            self.edges = radial_bin_edges(math.nextafter(rmax, math.inf), self.num_bins)
            self.reset()
        e = torch.tensor(self.edges, dtype=radius.dtype, device=radius.device)
        b = torch.bucketize(radius.contiguous(), e, right=True) - 1
        b = torch.where(radius == e[-1], torch.full_like(b, len(self.edges) - 2), b)
        return torch.where((b >= 0) & (b < len(self.edges) - 1), b, torch.full_like(b, -1))

    def _radius(self, batch: Mapping[str, Tensor], shape: torch.Size) -> Tensor:
        r = self.radius if self.radius is not None else batch.get(self.radius_key)
        if r is None:
            raise KeyError(f"RadialMetrics: batch[{self.radius_key!r}] is missing (have {sorted(batch)}); give a "
                           "dataset that provides the radius map (omnidl.data.fisheye) or radius=<(H, W) map>")
        r = r.detach().double().cpu()
        if r.dim() == 4:
            r = r[:, 0]
        if r.dim() == 2:
            r = r.expand(shape[0], *r.shape)
        if tuple(r.shape) != tuple(shape):
            raise ValueError(f"RadialMetrics: radius map {tuple(r.shape)} does not match the images {tuple(shape)}")
        return r

    def _add(self, key: str, b: int, value: float) -> None:
        rows = self.values.setdefault(key, [[] for _ in range(len(self.edges) - 1)])
        if not math.isnan(value):
            rows[b].append(value)

    def update(self, outputs: Mapping[str, Tensor], batch: Mapping[str, Tensor]) -> None:
        ref = batch["depth"] if "depth" in self.tasks else batch["semantic"]
        ref = ref[:, 0] if ref.dim() == 4 else ref
        radius = self._radius(batch, ref.shape)
        gt_d = pred_d = labels = pred_s = None
        valid = torch.ones(ref.shape, dtype=torch.bool)
        if "depth" in self.tasks:
            gt_d = batch["depth"].detach().double().cpu().reshape(ref.shape)
            pred_d = outputs["depth"].detach().double().cpu().reshape(ref.shape)
            valid = gt_d > self.min_depth
        if "semantic" in self.tasks:
            labels = batch["semantic"].detach().cpu().long().reshape(ref.shape)
            s = outputs["semantic"].detach().cpu()
            pred_s = (s.argmax(1) if s.dim() == 4 else s).long().reshape(ref.shape)
            if "depth" not in self.tasks:
                valid = labels != self.ignore_index
        bins = self._bins(radius, valid)
        for i in range(ref.shape[0]):
            for b in range(len(self.edges) - 1):
                m = bins[i] == b
                if not bool(m.any()):
                    continue
                if gt_d is not None:
                    md = m & (gt_d[i] > self.min_depth)
                    self.pixels[b] += int(md.sum())
                    res = depth_errors(pred_d[i][md], gt_d[i][md], self.min_depth, self.max_depth) if md.any() else None
                    if res is not None:
                        for k in DEPTH_METRICS:
                            self._add(k, b, res[k])
                if labels is not None:
                    conf = confusion_matrix(pred_s[i][m], labels[i][m], self.num_classes, self.ignore_index)
                    if gt_d is None:
                        self.pixels[b] += int(conf.sum())
                    if int(conf.sum()) == 0:
                        continue
                    self.confusion[b] += conf
                    sc = scores_from_confusion(conf, self.ignore_index)
                    for k in SEG_METRICS:
                        self._add(k, b, float(sc[k]))

    def table(self) -> list[dict[str, float]]:
        """One row per bin: ``r_lo, r_hi, r_mid, pixels, images`` and ``<metric>_mean``/``<metric>_std``
        (std over images; NaN with fewer than 2 images), plus ``miou_all``/``macc_all``/``pixel_acc_all``."""
        if self.edges is None:
            return []
        rows = []
        for b in range(len(self.edges) - 1):
            row = {"r_lo": self.edges[b], "r_hi": self.edges[b + 1], "r_mid": 0.5 * (self.edges[b] + self.edges[b + 1]),
                   "pixels": float(self.pixels[b])}
            n_img = 0
            for k, per_bin in self.values.items():
                v = np.asarray(per_bin[b], dtype=np.float64)
                n_img = max(n_img, v.size)
                row[f"{k}_mean"] = float(v.mean()) if v.size else math.nan
                row[f"{k}_std"] = float(v.std(ddof=1)) if v.size > 1 else math.nan
            row["images"] = float(n_img)
            if "semantic" in self.tasks:
                sc = scores_from_confusion(self.confusion[b], self.ignore_index)
                for k in SEG_METRICS:
                    row[f"{k}_all"] = float(sc[k]) if int(self.confusion[b].sum()) else math.nan
            rows.append(row)
        return rows

    def compute(self) -> dict[str, float]:
        """Flat ``radial/<metric>_mean/bin<b>`` scalars (for loggers); :meth:`table` is the readable form."""
        out = {}
        for b, row in enumerate(self.table()):
            for k, v in row.items():
                if k.endswith(("_mean", "_all")):
                    out[f"radial/{k}/bin{b}"] = v
        return out


def plot_radial(curves: Mapping[str, Sequence[Mapping[str, float]]], metrics: Sequence[str], path: str | Path,
                title: str = "", xlabel: str = "distance to the principal point (px)",
                styles: Mapping[str, Mapping[str, str]] | None = None) -> Path:
    """Plot ``metric`` mean ± std against the bin centre, one curve per label, one panel per metric.

    ``curves``: label -> :meth:`RadialMetrics.table` rows; ``styles``: optional label -> ``{"color": ...,
    "linestyle": ...}``. Written atomically (PNG by the suffix).
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from omnidl.utils.io import atomic_write
    n = len(metrics)
    cols = min(n, 4)
    nrows = (n + cols - 1) // cols
    # constrained layout sizes the margins to the tick labels, axis labels and titles (nothing is cut off)
    fig, axes = plt.subplots(nrows, cols, figsize=(4 * cols, 3.2 * nrows), squeeze=False, layout="constrained")
    colours = ["tab:red", "tab:blue", "tab:green", "tab:orange", "tab:purple", "tab:brown"]
    for ax, m in zip(axes.ravel(), metrics):
        for c, (label, rows) in enumerate(curves.items()):
            x = np.array([r["r_mid"] for r in rows], dtype=float)
            y = np.array([r.get(f"{m}_mean", math.nan) for r in rows], dtype=float)
            s = np.nan_to_num(np.array([r.get(f"{m}_std", math.nan) for r in rows], dtype=float))
            st = dict((styles or {}).get(label, {}))
            col = st.pop("color", colours[c % len(colours)])
            ax.plot(x, y, marker="o", ms=3, color=col, label=label, **st)
            ax.fill_between(x, y - s, y + s, color=col, alpha=0.15)
        ax.set_title(m)
        ax.set_xlabel(xlabel)
        ax.grid(alpha=0.3)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    axes.ravel()[0].legend(fontsize=8)
    if title:
        fig.suptitle(title)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=100, format=path.suffix.lstrip(".") or "png"))
    plt.close(fig)
    return path
