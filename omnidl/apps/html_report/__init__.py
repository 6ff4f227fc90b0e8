"""``report.html``: one static page for an evaluation run folder (``python evaluate.py ...`` writes it;
``python -m omnidl.apps.html_report RUN_DIR`` rebuilds it).

The page holds the metrics table (and the rotation sweep), one card per image with its panels
(``images/<stem>.png``) sortable by any per-image metric, an interactive panorama viewer (the network input,
the predicted depth and the predicted semantics, as a perspective view to drag around) and a 3-D view of the
predicted point cloud (``pointclouds/<stem>.ply``, gravity-aligned y-up frame).

No server and no network: the page's own script and style are inline; the viewers' images and points are
embedded (a page opened from disk may not read pixels of files beside it); the panels are relative links;
three.js (vendored, pinned: ``vendor/README.md``) is copied to ``report_assets/`` beside the page.
"""
from __future__ import annotations

import base64
import html
import json
import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from omnidl.utils.io import atomic_write_bytes, atomic_write_text

HERE = Path(__file__).resolve().parent
THREE = HERE / "vendor" / "three-0.159.0"
#: points per cloud kept in the page (a random, fixed-seed subset of the PLY's)
MAX_POINTS = 20000
#: per-image metrics where smaller is better, in the order the page sorts by default (largest first)
ERROR_KEYS = ("mre", "mae", "rmse", "rmse_log", "ce", "corner_error", "loss")


def write_report(run_dir: str | Path, max_points: int = MAX_POINTS) -> Path:
    """Write ``run_dir/report.html`` (and ``run_dir/report_assets/``) from what evaluation left in ``run_dir``.

    Returns the page's path. Raises ``FileNotFoundError`` naming the folder when it holds no ``metrics.json``.
    """
    run = Path(run_dir)
    if not (run / "metrics.json").is_file():
        raise FileNotFoundError(f"{run} has no metrics.json: give the run folder of `python evaluate.py ...`")
    data = collect(run, max_points)
    page = (_read("template.html")
            .replace("__TITLE__", html.escape(run.name))
            .replace("__GUARD_JS__", _read("guard.js"))
            .replace("__CSS__", _read("report.css"))
            .replace("__REPORT_JS__", _read("report.js"))
            .replace("__DATA__", json.dumps(data, allow_nan=False).replace("</", "<\\/")))
    assets = run / "report_assets"
    atomic_write_bytes(assets / "three.min.js", (THREE / "three.min.js").read_bytes())
    atomic_write_bytes(assets / "three.LICENSE", (THREE / "LICENSE").read_bytes())
    return atomic_write_text(run / "report.html", page)


def collect(run: Path, max_points: int = MAX_POINTS) -> dict[str, Any]:
    """The page's data: ``{"metrics", "rotation", "images": [{index, name, output, values, panel, layers,
    cloud}], ...}`` (JSON-safe: non-finite numbers become None)."""
    summary = json.loads((run / "metrics.json").read_text(encoding="utf-8"))
    records = []
    if (run / "per_image.json").is_file():
        records = json.loads((run / "per_image.json").read_text(encoding="utf-8"))
    images = []
    for rec in records:
        stem = str(rec.get("output", rec.get("name", rec.get("index"))))
        values = {k: _num(v) for k, v in rec.items() if k not in ("index", "name", "output")
                  and isinstance(v, (int, float))}
        panel = run / "images" / f"{stem}.png"
        images.append({"index": int(rec.get("index", len(images))), "name": str(rec.get("name", stem)),
                       "output": stem, "values": values,
                       "panel": f"images/{stem}.png" if panel.is_file() else None,
                       "layers": _layers(run, stem), "cloud": _cloud(run / "pointclouds" / f"{stem}.ply", max_points)})
    keys = [k for k in ERROR_KEYS if any(k in im["values"] for im in images)]
    return {"run_dir": str(run), "run_name": run.name, "split": summary.get("split", ""),
            "checkpoint": summary.get("checkpoint"), "metrics": _clean(summary.get("metrics", {})),
            "rotation": _clean(summary.get("rotation", {})), "images": images,
            "default_sort": keys[0] if keys else None, "default_desc": True}


def _read(name: str) -> str:
    return (HERE / name).read_text(encoding="utf-8")


def _num(v: float) -> float | None:
    return float(v) if math.isfinite(float(v)) else None


def _clean(d: Any) -> Any:
    if isinstance(d, dict):
        return {str(k): _clean(v) for k, v in d.items()}
    return _num(d) if isinstance(d, (int, float)) and not isinstance(d, bool) else d


def _data_url(img_bgr: np.ndarray, quality: int = 88) -> str:
    ok, buf = cv2.imencode(".jpg", img_bgr, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("could not encode a viewer image as JPEG")
    return "data:image/jpeg;base64," + base64.b64encode(buf.tobytes()).decode("ascii")


def _layers(run: Path, stem: str) -> dict[str, str]:
    """The panorama viewer's images of one sample as data URLs: input, predicted depth and semantics."""
    import torch

    from omnidl.viz import depth_to_color, semantic_to_color

    out: dict[str, str] = {}
    src = run / "inputs" / f"{stem}.jpg"
    if src.is_file():
        out["input"] = _data_url(cv2.imread(str(src), cv2.IMREAD_COLOR))
    depth = run / "predictions" / f"{stem}_depth.png"
    if depth.is_file():
        d = torch.from_numpy(cv2.imread(str(depth), cv2.IMREAD_UNCHANGED).astype(np.float32) / 1000.0)
        valid = d[d > 0]
        vmax = float(torch.quantile(valid, 0.99)) if valid.numel() else 1.0
        rgb = depth_to_color(d, vmax=max(vmax, 1e-3))
        out["predicted depth"] = _data_url(_to_bgr(rgb))
    sem = run / "predictions" / f"{stem}_semantic.png"
    if sem.is_file():
        lab = torch.from_numpy(cv2.imread(str(sem), cv2.IMREAD_UNCHANGED).astype(np.int64))
        out["predicted semantics"] = _data_url(_to_bgr(semantic_to_color(lab)))
    return out


def _to_bgr(rgb) -> np.ndarray:
    return (rgb.clamp(0, 1).permute(1, 2, 0).numpy()[..., ::-1] * 255).round().astype(np.uint8)


def _cloud(path: Path, max_points: int) -> dict[str, Any] | None:
    """A point cloud for the 3-D view: ``xyz`` float32 and ``rgb`` uint8 (base64), at most ``max_points``."""
    if not path.is_file():
        return None
    from omnidl.viz import read_ply
    pts, cols = read_ply(path)
    total = len(pts)
    keep = np.isfinite(pts).all(1)
    pts = pts[keep]
    cols = cols[keep] if cols is not None else np.full((len(pts), 3), 200, np.uint8)
    if len(pts) > max_points:
        idx = np.sort(np.random.default_rng(0).choice(len(pts), max_points, replace=False))
        pts, cols = pts[idx], cols[idx]
    cols = np.asarray(cols)
    if cols.dtype != np.uint8:
        cols = (np.clip(cols, 0, 1) * 255).round().astype(np.uint8)
    return {"n": int(len(pts)), "total": int(total),
            "xyz": base64.b64encode(np.ascontiguousarray(pts, "<f4").tobytes()).decode("ascii"),
            "rgb": base64.b64encode(np.ascontiguousarray(cols).tobytes()).decode("ascii")}
