"""The protocol's tables: Tables 7.1–7.4-shaped markdown and the Std-vs-Calib comparison at large radii.

Rows are the protocol's ``results.csv`` rows: ``stage`` (``BL``/``FT``), ``dataset`` (``Pers``, a fisheye
name, or ``<name>-R`` for the rectification baseline), ``kernel`` (``Std``/``Calib``) and the metrics.

Units: every value in the rows (``results.csv``, ``summary.json``) is a fraction, as everywhere in omnidl;
only these printed thesis-style tables show the segmentation scores in percent, in columns labelled (%).
"""
from __future__ import annotations

import math
from typing import Any

#: segmentation scores reported in the tables (fractions in the rows, percent in the printed tables)
SEG_KEYS = ("miou", "macc")


def _fmt(v: Any, nd: int = 4) -> str:
    return "—" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{nd}f}"


def _pct(v: Any, nd: int = 2) -> str:
    """A fraction printed as a percentage (without the sign: the column header says (%))."""
    return _fmt(None if v is None else 100.0 * float(v), nd)


def markdown_tables(rows: list[dict], tasks, coverage: dict[str, dict]) -> str:
    """Tables 7.1/7.2 (Std vs Calib, BL/FT) and 7.3/7.4 (fisheye vs rectified) as markdown."""
    out = []
    main = [r for r in rows if not r["dataset"].endswith("-R")]
    rect = [r for r in rows if r["dataset"].endswith("-R") or (r["kernel"] == "Std" and
                                                                 r["dataset"] + "-R" in {x["dataset"] for x in rows})]
    if "depth" in tasks:
        head = "| | Dataset | Kernel | " + " | ".join(["MRE ↓", "MAE ↓", "RMSE ↓", "RMSE_log ↓", "δ1 ↑", "δ2 ↑",
                                                       "δ3 ↑"]) + " |"
        keys = ["mre", "mae", "rmse", "rmse_log", "delta1", "delta2", "delta3"]
        out += ["### Depth (Table 7.1 shape)", "", head, "|" + "---|" * (3 + len(keys))]
        out += [f"| {r['stage']} | {r['dataset']} | {r['kernel']} | " + " | ".join(_fmt(r.get(k)) for k in keys)
                + " |" for r in main]
        out.append("")
    if "semantic" in tasks:
        out += ["### Semantic segmentation (Table 7.2 shape)", "", "| | Dataset | Kernel | mIoU (%) ↑ | mAcc (%) ↑ |",
                "|---|---|---|---|---|"]
        out += [f"| {r['stage']} | {r['dataset']} | {r['kernel']} | {_pct(r.get('miou'))} | "
                f"{_pct(r.get('macc'))} |" for r in main]
        out.append("")
    if any(r["dataset"].endswith("-R") for r in rows):
        out += ["### Rectification baseline (Tables 7.3/7.4 shape, standard convolutions)", "",
                "| | Input | " + ("MRE ↓ | MAE ↓ | RMSE ↓ | δ1 ↑ | " if "depth" in tasks else "")
                + ("mIoU (%) ↑ | mAcc (%) ↑ | " if "semantic" in tasks else "")
                + "pixels with a prediction (fraction) |",
                "|---|---|" + "---|" * ((4 if "depth" in tasks else 0) + (2 if "semantic" in tasks else 0) + 1)]
        for r in rect:
            cells = []
            if "depth" in tasks:
                cells += [_fmt(r.get(k)) for k in ("mre", "mae", "rmse", "delta1")]
            if "semantic" in tasks:
                cells += [_pct(r.get(k)) for k in SEG_KEYS]
            cells.append(_fmt(r.get("covered_fraction", 1.0 if not r["dataset"].endswith("-R") else None), 3))
            out.append(f"| {r['stage']} | {r['dataset']} | " + " | ".join(cells) + " |")
        out.append("")
    if coverage:
        out += ["### Rectification coverage (fractions of the valid fisheye pixels)", "",
                "| Camera | rectifiable (z > 0) | cannot be rectified | covered by the pinhole | pinhole FOV (°) |",
                "|---|---|---|---|---|"]
        out += [f"| {k} | {_fmt(c['rectifiable'])} | {_fmt(c['unrectifiable'])} | {_fmt(c['covered'])} | "
                f"{_fmt(c['pinhole_fov_deg'], 1)} |" for k, c in coverage.items()]
        out.append("")
    return "\n".join(out)


def compare_large_radii(radial: dict[str, dict[str, list[dict]]], fraction: float = 1 / 3) -> dict[str, Any]:
    """Per fisheye dataset: FT Calib vs FT Std averaged over the outer ``fraction`` of the radius bins
    that hold pixels (lower is better for depth errors; higher for deltas and segmentation scores)."""
    better_high = {"delta1", "delta2", "delta3", "miou", "macc", "pixel_acc", "miou_all", "macc_all",
                   "pixel_acc_all"}
    res: dict[str, Any] = {}
    for ds, runs in radial.items():
        std, cal = runs.get("FT-Std"), runs.get("FT-Calib")
        if not std or not cal:
            continue
        used = [i for i, r in enumerate(std) if r["pixels"] > 0]
        outer = used[-max(1, round(len(used) * fraction)):]
        per: dict[str, Any] = {"r_from": std[outer[0]]["r_lo"], "r_to": std[outer[-1]]["r_hi"], "metrics": {}}
        wins = 0
        n = 0
        # per-image means (``<m>_mean``) and dataset-wide per-bin segmentation scores (``<m>_all``)
        for col in [k for k in std[0] if k.endswith(("_mean", "_all"))]:
            key = col[:-5] if col.endswith("_mean") else col
            a = [std[i][col] for i in outer]
            b = [cal[i][col] for i in outer]
            if any(math.isnan(x) for x in a + b):
                continue
            sa, sb = sum(a) / len(a), sum(b) / len(b)
            calib_better = sb > sa if key in better_high else sb < sa
            per["metrics"][key] = {"std": sa, "calib": sb, "calib_better": calib_better}
            wins += calib_better
            n += 1
        per["calib_better_count"] = f"{wins}/{n}"
        res[ds] = per
    return res
