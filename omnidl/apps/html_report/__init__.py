"""``report.html``: one static page for an evaluation run folder (``python evaluate.py ...`` writes it;
``python -m omnidl.apps.html_report RUN_DIR [--overwrite]`` rebuilds it).

The page holds the metrics table (and the rotation sweep), one card per image with its panels
(``images/<stem>.png``) sortable by any per-image metric, an interactive panorama viewer (the network input,
the predicted depth and the predicted semantics, as a perspective view to drag around) and a 3-D view of the
predicted point cloud (``pointclouds/<stem>.ply``, gravity-aligned y-up frame) with the predicted and the
ground-truth room layout as wireframes over it (``postprocess.jsonl``: the layout hooks' ``layout`` per image
and, when the hooks write it, ``layout_gt``; layout frame z up, shown in the same y-up frame as the clouds).

No server and no network: the page's own script and style are inline; the viewers' images and points are
embedded (a page opened from disk may not read pixels of files beside it); the panels are relative links;
three.js (vendored, pinned: ``vendor/README.md``) is copied to ``report_assets/`` beside the page.

Safety. Every string of the run (folder and file names, config values such as the checkpoint path and the
split, metric names, sample names) reaches the page in two ways only: HTML-escaped text (the title) or JSON in a
``<script type="application/json">`` block where ``<``, ``>``, ``&`` and U+2028/U+2029 are ``\\uXXXX`` escapes
(:func:`embed_json`), so no value can close the block or open markup; the page's script puts them into the
document with ``textContent`` and ``setAttribute`` only. A per-image output stem that is not a plain file name
(a path separator, ``..``, a leading dot) is shown but no file is read for it. Nothing is overwritten: an
existing ``report.html`` (or a different ``report_assets/three.min.js``) is kept unless ``overwrite``
(:mod:`omnidl.utils.outputs`).
"""
from __future__ import annotations

import base64
import html
import json
import math
import re
import sys
from pathlib import Path
from typing import Any
from urllib.parse import quote

import cv2
import numpy as np

from omnidl.utils.io import atomic_write_bytes, atomic_write_text
from omnidl.utils.outputs import guard_outputs

HERE = Path(__file__).resolve().parent
THREE = HERE / "vendor" / "three-0.159.0"
#: points per cloud kept in the page (a random, fixed-seed subset of the PLY's)
MAX_POINTS = 20000
#: per-image metrics where smaller is better, in the order the page sorts by default (largest first)
ERROR_KEYS = ("mre", "mae", "rmse", "rmse_log", "ce", "corner_error", "loss")
#: the template's placeholders, each replaced once (a value is never searched for another placeholder)
_SLOT = re.compile(r"__(TITLE|GUARD_JS|CSS|REPORT_JS|DATA)__")
#: characters that could end a <script> block or start markup inside it, and JavaScript's line separators
_JSON_ESCAPES = {"<": "\\u003c", ">": "\\u003e", "&": "\\u0026", "\u2028": "\\u2028", "\u2029": "\\u2029"}
#: layout frame (z up) -> the clouds' gravity-aligned y-up frame: (x, y, z) -> (x, z, -y) (omnidl.viz.ply)
LAYOUT_TO_Y_UP = ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, -1.0, 0.0))


def embed_json(obj: Any) -> str:
    """``obj`` as JSON text safe inside ``<script type="application/json">``: ``json.loads`` gives ``obj`` back,
    and the text holds no ``<``, ``>`` or ``&`` (so neither ``</script>`` nor ``<!--`` can appear) and no raw
    U+2028/U+2029. Non-finite numbers are refused (``ValueError``): :func:`collect` turns them into None."""
    text = json.dumps(obj, allow_nan=False, ensure_ascii=False)
    return re.sub("[<>&\u2028\u2029]", lambda m: _JSON_ESCAPES[m.group(0)], text)


def render_page(data: dict[str, Any], title: str) -> str:
    """The page's HTML: the template with ``title`` HTML-escaped and ``data`` embedded by :func:`embed_json`."""
    parts = {"TITLE": html.escape(title, quote=True), "GUARD_JS": _read("guard.js"), "CSS": _read("report.css"),
             "REPORT_JS": _read("report.js"), "DATA": embed_json(data)}
    return _SLOT.sub(lambda m: parts[m.group(1)], _read("template.html"))


def write_report(run_dir: str | Path, max_points: int = MAX_POINTS, overwrite: bool = False) -> Path:
    """Write ``run_dir/report.html`` (and ``run_dir/report_assets/``) from what evaluation left in ``run_dir``.

    Returns the page's path. Raises ``FileNotFoundError`` naming the folder when it holds no ``metrics.json``,
    and :class:`~omnidl.utils.outputs.OutputExistsError` (a ``FileExistsError``) before writing anything when
    ``report.html`` exists, or ``report_assets/`` holds other files of the same names, and not ``overwrite``.
    """
    run = Path(run_dir)
    if not (run / "metrics.json").is_file():
        raise FileNotFoundError(f"{run} has no metrics.json: give the run folder of `python evaluate.py ...`")
    assets = run / "report_assets"
    copies = [(assets / "three.min.js", THREE / "three.min.js"), (assets / "three.LICENSE", THREE / "LICENSE")]
    copies = [(dst, src) for dst, src in copies if not (dst.is_file() and dst.read_bytes() == src.read_bytes())]
    inputs = [run / n for n in ("metrics.json", "per_image.json", "postprocess.jsonl")]
    guard_outputs([run / "report.html"] + [dst for dst, _ in copies], inputs=inputs, overwrite=overwrite)
    data = collect(run, max_points)
    page = render_page(data, run.name)
    for dst, src in copies:
        atomic_write_bytes(dst, src.read_bytes())
    return atomic_write_text(run / "report.html", page)


def collect(run: Path, max_points: int = MAX_POINTS) -> dict[str, Any]:
    """The page's data: ``{"metrics", "rotation", "images": [{index, name, output, values, panel, layers,
    cloud, layout}], ...}`` (JSON-safe: non-finite numbers become None)."""
    summary = json.loads((run / "metrics.json").read_text(encoding="utf-8"))
    if not isinstance(summary, dict):
        raise ValueError(f"{run / 'metrics.json'}: expected a JSON object, got {type(summary).__name__}")
    records = []
    if (run / "per_image.json").is_file():
        records = json.loads((run / "per_image.json").read_text(encoding="utf-8"))
        if not isinstance(records, list):
            raise ValueError(f"{run / 'per_image.json'}: expected a JSON list of records, got "
                             f"{type(records).__name__}")
    layouts = read_layouts(run / "postprocess.jsonl")
    images = []
    for rec in records:
        if not isinstance(rec, dict):
            continue
        stem = str(rec.get("output", rec.get("name", rec.get("index"))))
        values = {str(k): _num(v) for k, v in rec.items() if k not in ("index", "name", "output")
                  and isinstance(v, (int, float)) and not isinstance(v, bool)}
        safe = _plain_name(stem)
        if not safe:
            print(f"report: {run / 'per_image.json'}: output {stem!r} is not a plain file name; its pictures, "
                  "panorama and point cloud are not read", file=sys.stderr)
        panel = run / "images" / f"{stem}.png"
        index = rec.get("index", len(images))
        images.append({"index": int(index) if isinstance(index, (int, float)) and math.isfinite(index)
                       else len(images), "name": str(rec.get("name", stem)), "output": stem, "values": values,
                       "panel": f"images/{quote(stem)}.png" if safe and panel.is_file() else None,
                       "layers": _layers(run, stem) if safe else {},
                       "cloud": _cloud(run / "pointclouds" / f"{stem}.ply", max_points) if safe else None,
                       "layout": layouts.get(stem)})
    keys = [k for k in ERROR_KEYS if any(k in im["values"] for im in images)]
    return {"run_dir": str(run), "run_name": run.name, "split": str(summary.get("split", "")),
            "checkpoint": None if summary.get("checkpoint") is None else str(summary.get("checkpoint")),
            "metrics": _clean(summary.get("metrics", {})),
            "rotation": _clean(summary.get("rotation", {})), "images": images,
            "default_sort": keys[0] if keys else None, "default_desc": True}


def _plain_name(stem: str) -> bool:
    """A stem that names a file inside the run's folders (no separator, no ``..``, no leading dot, no NUL)."""
    return bool(stem) and not any(c in stem for c in "/\\\0") and not stem.startswith(".")


def layout_segments(layout: Any) -> list[float] | None:
    """Wireframe of a layout as flat ``[x0, y0, z0, x1, y1, z1, ...]`` segment end points in the clouds' y-up
    frame: the ceiling and floor outlines and one vertical edge per corner. ``layout``: a ``Layout.to_dict()``
    (``ok``, ``floor_corners``, ``ceiling_corners``; layout frame, z up, metres) or any mapping with the two corner
    lists. None when it is not a usable layout (failed, missing or non-finite corners)."""
    if not isinstance(layout, dict) or layout.get("ok") is False:
        return None
    try:
        fl = np.asarray(layout["floor_corners"], float)
        ce = np.asarray(layout["ceiling_corners"], float)
    except (KeyError, TypeError, ValueError):
        return None
    if fl.ndim != 2 or fl.shape[1:] != (3,) or fl.shape != ce.shape or len(fl) < 3 \
            or not (np.isfinite(fl).all() and np.isfinite(ce).all()):
        return None
    M = np.asarray(LAYOUT_TO_Y_UP)
    fl, ce = fl @ M.T, ce @ M.T
    segs = [np.stack([p, np.roll(p, -1, 0)], 1) for p in (ce, fl)] + [np.stack([fl, ce], 1)]
    return [round(float(v), 4) for v in np.concatenate(segs).reshape(-1)]


def read_layouts(path: Path) -> dict[str, dict[str, list[float]]]:
    """``stem -> {"pred": segments, "gt": segments}`` (:func:`layout_segments`) from an evaluation's
    ``postprocess.jsonl`` (one JSON object per batch: ``names`` and the hooks' per-image lists ``layout`` and
    ``layout_gt``). Unreadable lines are reported on stderr and skipped."""
    out: dict[str, dict[str, list[float]]] = {}
    if not path.is_file():
        return out
    for i, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
        if not line.strip():
            continue
        try:
            batch = json.loads(line)
        except json.JSONDecodeError as e:
            print(f"report: {path}:{i}: skipped, not JSON ({e})", file=sys.stderr)
            continue
        names = batch.get("names") if isinstance(batch, dict) else None
        if not isinstance(names, list):
            continue
        for key, kind in (("layout", "pred"), ("layout_gt", "gt")):
            items = batch.get(key)
            if not isinstance(items, list):
                continue
            for name, lay in zip(names, items):
                seg = layout_segments(lay)
                if seg is not None:
                    out.setdefault(str(name), {})[kind] = seg
    return out


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
