"""Collect a sweep into a results table: ``python -m omnidl.apps.report multirun/<dir> [--out DIR]``.

Every job folder below ``<dir>`` that holds a ``metrics.json`` becomes one row. The row is named by the
job's experiment code (``name`` in its ``.hydra/config.yaml``, set by the experiment configs, e.g. ``F-Std-CE-B``), else by its
Hydra overrides. Columns are the scalar metrics, in the order of Tables 4.1–4.6 when present
(MRE, MAE, RMSE, RMSElog, δ¹, δ², δ³, mIoU, mAcc) and alphabetically after that.
Writes ``results.md`` and ``results.csv``; when jobs report metrics per rotation angle
(a ``rotation`` mapping ``angle -> metrics`` in ``metrics.json``), also ``rotation.png`` — as Fig. 4.5, one
panel per unit (metres, fractions, ...), one curve per job and metric, the legend beside the panels.

Units: omnidl's metrics are fractions (mIoU 0.42, not 42; layout IoU and CEN too); ``results.csv`` keeps them
so. Only the printed thesis-style table (``results.md`` and the terminal) shows mIoU, mAcc, the layout IoUs and
CEN in percent, in columns labelled (%). A fraction metric outside [0, 1] (a job that wrote percent) is reported
on stderr. Per-group keys such as ``iou_3d@4`` (a layout protocol's corner-count groups) have their base key's unit.

Names in ``results.md`` (job names from the configs, metric keys) are Markdown-escaped: ``|`` cannot split a cell,
a line break cannot end a row, and ``<``, ``>``, ``&`` are HTML entities, so a Markdown renderer shows them as text
and never as markup. Nothing is overwritten: existing ``results.md``/``results.csv``/``rotation.png`` are replaced
only with ``--overwrite`` (:mod:`omnidl.utils.outputs`; the check runs before anything is written).
"""
from __future__ import annotations

import argparse
import csv
import io
import json
import math
import re
import sys
from pathlib import Path
from typing import Any

from omnidl.utils.io import atomic_write, atomic_write_text
from omnidl.utils.outputs import guard_outputs

PREFERRED = ["mre", "mae", "rmse", "rmse_log", "rmselog", "delta1", "delta2", "delta3", "miou", "macc",
             "ce", "cen", "iou_3d", "iou_2d", "iou3d", "iou2d"]
PRETTY = {"mre": "MRE", "mae": "MAE", "rmse": "RMSE", "rmse_log": "RMSElog", "rmselog": "RMSElog", "delta1": "δ¹",
          "delta2": "δ²", "delta3": "δ³", "miou": "mIoU", "macc": "mAcc", "ce": "CE", "cen": "CEN",
          "iou_3d": "3D IoU", "iou_2d": "2D IoU", "iou3d": "3D IoU", "iou2d": "2D IoU"}
LOWER_IS_BETTER = {"mre", "mae", "rmse", "rmse_log", "rmselog", "ce", "cen", "loss"}
#: layout IoU/CEN keys: LayoutMetrics / LayoutProtocolMetrics names and the layout hooks' ``layout_`` scores
_LAYOUT_PERCENT = {f"{p}{k}" for p in ("", "layout_") for k in ("cen", "iou_3d", "iou_3d_u2s", "iou_2d")}
#: fraction metrics the printed table shows in percent (as the thesis' tables do)
PERCENT = {"miou", "macc", "iou3d", "iou2d", "corner_error", "pixel_error"} | _LAYOUT_PERCENT
#: metrics whose values are fractions in [0, 1]
FRACTIONS = ({"delta1", "delta2", "delta3", "miou", "macc", "pixel_acc", "layout_fail_rate", "covered_fraction",
              "layout_ok", "gt_skipped", "depth_delta1", "horizon_no_line", "horizon_success",
              "upright_baseline_success", "rotation_success"} | PERCENT
             | {f"{m}_{k}" for m in ("edge", "corner") for k in ("precision", "recall", "accuracy", "iou")})
#: the unit of each metric (the rotation plot draws one panel per unit)
UNITS = {"mae": "metres", "rmse": "metres", "ce": "metres", "layout_ce": "metres", "depth_rmse": "metres",
         "rmse_log": "log metres", "rmselog": "log metres", "mre": "relative error",
         **{k: "fraction" for k in FRACTIONS}}


def metric_unit(key: str) -> str:
    """``"metres"``, ``"fraction"``, ``"degrees"``, ... for a metric key (its last ``/`` part)."""
    s = _base(key)
    if s in UNITS:
        return UNITS[s]
    if s.endswith("_deg") or s.endswith("_err_deg"):
        return "degrees"
    if s.endswith("_m"):
        return "metres"
    return s  # unknown unit: a panel of its own


def flatten(d: dict, prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}} -> {"a/b": 1}``."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten(v, key + "/"))
        else:
            out[key] = v
    return out


def _short(key: str) -> str:
    return key.rsplit("/", 1)[-1].lower().replace("δ", "delta")


def _base(key: str) -> str:
    """:func:`_short` without a group suffix (``iou_3d@4`` -> ``iou_3d``): the name that fixes the unit."""
    return _short(key).split("@", 1)[0]


def _order(keys: list[str]) -> list[str]:
    def rank(k: str):
        s = _short(k)
        return (PREFERRED.index(s) if s in PREFERRED else len(PREFERRED), k)
    return sorted(keys, key=rank)


def _job_name(job: Path, root: Path) -> str:
    cfg = job / ".hydra" / "config.yaml"
    if cfg.exists():
        try:
            from omegaconf import OmegaConf
            c = OmegaConf.load(cfg)
            code = OmegaConf.select(c, "experiment_code", default=None) or OmegaConf.select(c, "name", default=None)
            if code and code != "run":
                return str(code)
        except Exception:
            pass
    ov = job / ".hydra" / "overrides.yaml"
    if ov.exists():
        try:
            import yaml
            items = yaml.safe_load(ov.read_text()) or []
            if items:
                return ",".join(str(i) for i in items)
        except Exception:
            pass
    return str(job.relative_to(root)) if job != root else job.name


def collect(root: str | Path) -> list[dict[str, Any]]:
    """One record per job folder: ``{"name", "path", "metrics" (flat scalars), "rotation" (angle -> metrics)}``."""
    root = Path(root)
    if not root.exists():
        raise FileNotFoundError(f"report: no such folder {root}")
    jobs = sorted({p.parent for p in root.rglob("metrics.json") if "trial_" not in p.parent.name},
                  key=lambda p: [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", str(p))])
    records = []
    for job in jobs:
        try:
            raw = json.loads((job / "metrics.json").read_text())
        except (OSError, json.JSONDecodeError) as exc:
            print(f"report: skipping {job / 'metrics.json'}: {exc}", file=sys.stderr)
            continue
        if not isinstance(raw, dict):
            print(f"report: skipping {job / 'metrics.json'}: expected a JSON object of metrics, got "
                  f"{type(raw).__name__}", file=sys.stderr)
            continue
        rotation = raw.pop("rotation", None)
        flat = {k: v for k, v in flatten(raw).items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
        records.append({"name": _job_name(job, root), "path": str(job), "metrics": flat,
                        "rotation": rotation if isinstance(rotation, dict) else None})
    if not records:
        raise FileNotFoundError(f"report: no metrics.json found below {root} (each job writes one)")
    return records


def check_fractions(records: list[dict[str, Any]]) -> list[str]:
    """Messages for fraction metrics outside [0, 1] (e.g. a job that wrote mIoU in percent); printed on stderr."""
    out = []
    for r in records:
        for k, v in r["metrics"].items():
            if _base(k) in FRACTIONS and isinstance(v, (int, float)) and math.isfinite(v) and not 0 <= v <= 1:
                out.append(f"report: warning: {r['path']}: {k} = {v} is outside [0, 1]; omnidl writes fractions "
                           "(was it written in percent?)")
    return out


def table(records: list[dict[str, Any]], columns: list[str] | None = None,
          all_metrics: bool = False, percent: bool = False) -> tuple[list[str], list[list[str]]]:
    """Header and rows. By default only the thesis' table metrics (MRE ... mAcc, layout CE/IoU) are columns,
    taken from the final validation (``final/``) or evaluation (``metrics/``) results; ``all_metrics`` keeps
    every scalar. ``percent``: the :data:`PERCENT` fractions (mIoU, mAcc, layout IoUs, CEN) as percentages (the
    printed table; the header then says (%))."""
    keys = columns or _order(sorted({k for r in records for k in r["metrics"]}))
    if not columns and not all_metrics:
        chosen: dict[str, str] = {}
        for k in keys:  # one column per metric name, preferring evaluation over final validation results
            s = _short(k)
            if s in PREFERRED and (s not in chosen or k.startswith("metrics/")):
                chosen[s] = k
        keys = [chosen[s] for s in PREFERRED if s in chosen] or keys
    header = ["network"] + keys
    rows = []
    for r in records:
        row = [r["name"]]
        for k in keys:
            v = r["metrics"].get(k)
            if v is None or (isinstance(v, float) and math.isnan(v)):
                row.append("-")
            elif percent and _base(k) in PERCENT:
                row.append(f"{100 * v:.2f}")
            else:
                row.append(f"{v:.4f}")
        rows.append(row)
    return header, rows


_MD_ESCAPES = {"&": "&amp;", "<": "&lt;", ">": "&gt;", "|": "\\|", "\\": "\\\\", "\n": " ", "\r": " "}


def markdown_cell(text: str) -> str:
    """``text`` as the content of one Markdown table cell shown literally (see the module docstring)."""
    return re.sub(r"[&<>|\\\n\r]", lambda m: _MD_ESCAPES[m.group(0)], str(text))


def to_markdown(header: list[str], rows: list[list[str]], percent: bool = True) -> str:
    """The printed table; with ``percent`` (rows made by ``table(..., percent=True)``) the :data:`PERCENT` columns
    say (%)."""
    def label(h: str) -> str:
        s = _short(h)
        unit = " (%)" if percent and _base(h) in PERCENT else ""
        return PRETTY.get(s, h) + unit + (" ↓" if s in LOWER_IS_BETTER else " ↑" if s in PREFERRED else "")
    arrows = [label(h) for h in header]
    arrows[0] = header[0]
    lines = ["| " + " | ".join(markdown_cell(a) for a in arrows) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(markdown_cell(c) for c in r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def _angle(a: Any) -> float:
    try:
        return float(a)
    except (TypeError, ValueError):
        return math.nan


def rotation_panels(records: list[dict[str, Any]]) -> dict[str, list[str]]:
    """``unit -> metric keys`` of the jobs' rotation results: one panel of the rotation plot per unit."""
    names = _order(sorted({k for r in records if r["rotation"] for m in r["rotation"].values() if isinstance(m, dict)
                           for k, v in flatten(m).items() if isinstance(v, (int, float)) and not isinstance(v, bool)}))
    groups: dict[str, list[str]] = {}
    for m in names:
        groups.setdefault(metric_unit(m), []).append(m)
    return groups


def plot_rotation(records: list[dict[str, Any]], path: Path) -> bool:
    """Metric vs rotation angle, one line per job (Fig. 4.5). Returns False if no job has rotation results."""
    rot = [r for r in records if r["rotation"]]
    if not rot:
        return False
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    groups = rotation_panels(rot)
    n = len(groups)
    cols = min(3, n)
    nrows = math.ceil(n / cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(5.2 * cols, 4.8 * nrows), squeeze=False)
    styles = ["-", "--", ":", "-."]
    markers = "osD^v<>px*"
    for ax, (unit, names) in zip(axes.flat, groups.items()):
        for j, r in enumerate(rot):
            for i, m in enumerate(names):
                pts = sorted((_angle(a), flatten(v).get(m)) for a, v in r["rotation"].items() if isinstance(v, dict))
                pts = [(a, v) for a, v in pts if math.isfinite(a) and isinstance(v, (int, float))]
                if pts:
                    label = PRETTY.get(_short(m), m) + (f" ({r['name']})" if len(rot) > 1 else "")
                    ax.plot(*zip(*pts), marker=markers[i % len(markers)], linestyle=styles[j % len(styles)],
                            color=f"C{i % 10}", label=label)
        ax.set_title(unit)
        ax.set_ylabel(unit)
        ax.set_xlabel("rotation (deg)")
        ax.grid(alpha=0.3)
        # the legend goes below each panel, off the curves
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2, frameon=False, handlelength=3.5)
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    fig.tight_layout()
    atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=100, bbox_inches="tight"))
    plt.close(fig)
    return True


def write_report(root: str | Path, out: str | Path | None = None, all_metrics: bool = False,
                 overwrite: bool = False) -> dict[str, Path]:
    """Collect ``root`` and write ``results.md``, ``results.csv`` (and ``rotation.png``) into ``out`` (default root).

    Raises :class:`~omnidl.utils.outputs.OutputExistsError` (a ``FileExistsError``) before writing anything when
    one of them exists and not ``overwrite``, or ``out`` is an existing file."""
    records = collect(root)
    out = Path(out or root)
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"report: --out {out} is an existing file; give a folder")
    planned = [out / "results.md", out / "results.csv"] + ([out / "rotation.png"] if any(r["rotation"] for r in records)
                                                           else [])
    guard_outputs(planned, inputs=[Path(r["path"]) / "metrics.json" for r in records], overwrite=overwrite)
    for msg in check_fractions(records):
        print(msg, file=sys.stderr)
    header, rows = table(records, all_metrics=all_metrics, percent=True)
    written = {"markdown": atomic_write_text(out / "results.md", to_markdown(header, rows))}
    header, rows = table(records, all_metrics=all_metrics)  # results.csv: fractions, as omnidl writes them
    buf = io.StringIO()
    csv.writer(buf).writerows([header] + rows)
    written["csv"] = atomic_write_text(out / "results.csv", buf.getvalue())
    if plot_rotation(records, out / "rotation.png"):
        written["rotation"] = out / "rotation.png"
    return written


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m omnidl.apps.report", description=__doc__.split("\n\n")[0])
    ap.add_argument("sweep", help="a multirun folder (or any folder with job sub-folders holding metrics.json)")
    ap.add_argument("--out", help="where to write results.md/results.csv (default: the sweep folder)")
    ap.add_argument("--all", action="store_true", help="a column for every scalar metric, not only the table ones")
    ap.add_argument("--overwrite", action="store_true", help="replace existing results.md/results.csv/rotation.png")
    args = ap.parse_args(argv)
    try:
        written = write_report(args.sweep, args.out, all_metrics=args.all, overwrite=args.overwrite)
    except (FileNotFoundError, FileExistsError) as exc:
        print(exc, file=sys.stderr)
        return 2
    print(Path(written["markdown"]).read_text())
    for k, p in written.items():
        print(f"{k}: {p}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
