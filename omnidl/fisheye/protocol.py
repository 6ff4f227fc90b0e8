"""The calibrated-fisheye protocol of thesis §7.4, end to end, with one command::

    python -m omnidl.fisheye.protocol --config configs/fisheye/small_cpu.yaml [--out DIR] [key=value ...]

1. train a U-Net with standard convolutions on perspective crops of the training panoramas (*Pers*):
   the baseline (BL);
2. evaluate BL on Pers and on the fisheye test sets (F165, F195), with standard and with calibrated
   convolutions (the same weights; calibrated = :func:`omnidl.nn.convert_conv2d` with the camera);
3. fine-tune a copy of BL on each fisheye training set, once with standard and once with calibrated
   convolutions, for ``finetune.steps`` (a fraction of the baseline budget);
4. evaluate the fine-tuned networks (FT); plus the rectification baseline (§7.4.3): rectify ->
   BL (and, with ``rectify.finetune``, a standard copy fine-tuned through the warps) -> un-rectify,
   evaluated in the fisheye domain, with the fraction of the image that cannot be rectified.

Writes to ``out_dir``: ``results.csv`` (one row per stage/dataset/kernel), ``tables.md`` (Tables
7.1–7.4-shaped), ``radial/<dataset>_<run>.csv`` (metrics per radius bin, mean ± std over images),
``radial_<dataset>_{depth,semantic}.png`` (Figs 7.2/7.5) and ``radial_<dataset>_rectified_*.png``
(Figs 7.8/7.9), ``summary.json`` (the Std-vs-Calib comparison at large radii), ``checkpoints/``
(a re-run skips stages whose checkpoint exists; ``--fresh`` retrains). Overrides are OmegaConf
dot-list entries (``train.steps=50``).
"""
from __future__ import annotations

import argparse
import copy
import json
import logging
import math
import sys
import time
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from torch.utils.data import DataLoader
from tqdm import tqdm

from omnidl.data.collate import collate_samples
from omnidl.data.fisheye import PerspectiveFromPanoramas, ViewsFromPanoramas, build_panoramas, load_camera
from omnidl.engine.checkpoint import load_checkpoint, save_checkpoint
from omnidl.engine.seed import seed_everything
from omnidl.metrics.depth import DEPTH_METRICS, DepthMetrics
from omnidl.metrics.radial import RadialMetrics, plot_radial, radial_bin_edges, rows_to_csv
from omnidl.metrics.segmentation import SegmentationMetrics
from omnidl.models.unet import UNet
from omnidl.utils.io import atomic_write_json, atomic_write_text

from .rectified import RectifiedModel, rectification_report

log = logging.getLogger("omnidl.fisheye")
SEG_KEYS = ("miou", "macc")


class PanoramaBank:
    """Panoramas rendered/loaded once and kept in memory (image, depth, semantic only), shared by the
    Pers and fisheye datasets of one split."""

    def __init__(self, source, desc: str = "panoramas") -> None:
        self.items = []
        for i in tqdm(range(len(source)), desc=desc, leave=False):
            s = source[i]
            self.items.append({"image": s["image"].float(), "depth": s["depth"].float(),
                               "semantic": s["semantic"].to(torch.int16)})

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> dict:
        return self.items[i]


def _loader(ds, batch_size: int, shuffle: bool, seed: int) -> DataLoader:
    g = torch.Generator().manual_seed(seed)
    return DataLoader(ds, batch_size=batch_size, shuffle=shuffle, num_workers=0, collate_fn=collate_samples,
                      generator=g, drop_last=shuffle and len(ds) >= batch_size)


def _batch(b: dict, device: torch.device) -> dict:
    return {k: (v.to(device) if isinstance(v, torch.Tensor) else v) for k, v in b.items()}


def train_steps(model: torch.nn.Module, dataset, loss_fn, steps: int, lr: float, batch_size: int, seed: int,
                device: torch.device, desc: str, weight_decay: float = 0.0) -> list[float]:
    """Adam for ``steps`` optimiser steps over a shuffled, repeated ``dataset``; returns the losses."""
    model.train().to(device)
    opt = torch.optim.Adam(model.parameters(), lr=lr, weight_decay=weight_decay)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(1, steps))
    losses: list[float] = []
    epoch = 0
    bar = tqdm(total=steps, desc=desc, leave=False)
    while len(losses) < steps:
        for batch in _loader(dataset, batch_size, True, seed + epoch):
            if len(losses) >= steps:
                break
            batch = _batch(batch, device)
            out = model(batch["image"])
            loss, _ = loss_fn(out, batch)
            if not torch.isfinite(loss):
                log.warning("%s: non-finite loss at step %d skipped", desc, len(losses))
                continue
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            losses.append(float(loss.detach()))
            bar.update(1)
            bar.set_postfix(loss=f"{losses[-1]:.3f}")
        epoch += 1
    bar.close()
    return losses


@torch.no_grad()
def evaluate_model(model: torch.nn.Module, dataset, tasks, batch_size: int, device: torch.device,
                   edges: list[float] | None, desc: str) -> tuple[dict[str, float], list[dict], dict[str, float]]:
    """``(scalars, radial rows, extra)``: depth and segmentation metrics, the per-radius table, and for
    rectified models the covered fraction."""
    model.eval().to(device)
    dm = DepthMetrics() if "depth" in tasks else None
    sm = SegmentationMetrics(num_classes=14) if "semantic" in tasks else None
    rm = RadialMetrics(edges=edges, tasks=tasks) if edges is not None else None
    covered, total = 0.0, 0.0
    for batch in tqdm(_loader(dataset, batch_size, False, 0), desc=desc, leave=False):
        batch = _batch(batch, device)
        out = model(batch["image"])
        for m in (dm, sm, rm):
            if m is not None:
                m.update(out, batch)
        if "rectified" in out:
            v = batch["valid"]
            covered += float((out["rectified"][:, 0] & v).sum())
            total += float(v.sum())
    scalars: dict[str, float] = {}
    if dm is not None:
        scalars.update({k: v for k, v in dm.compute().items() if k in DEPTH_METRICS})
    if sm is not None:
        scalars.update({k: 100 * v for k, v in sm.compute().items() if k in SEG_KEYS})
    extra = {"covered_fraction": covered / total} if total else {}
    return scalars, (rm.table() if rm is not None else []), extra


def _fmt(v: Any, nd: int = 4) -> str:
    return "—" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{nd}f}"


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
        out += ["### Semantic segmentation (Table 7.2 shape)", "", "| | Dataset | Kernel | mIoU | mAcc |",
                "|---|---|---|---|---|"]
        out += [f"| {r['stage']} | {r['dataset']} | {r['kernel']} | {_fmt(r.get('miou'), 2)} | "
                f"{_fmt(r.get('macc'), 2)} |" for r in main]
        out.append("")
    if any(r["dataset"].endswith("-R") for r in rows):
        out += ["### Rectification baseline (Tables 7.3/7.4 shape, standard convolutions)", "",
                "| | Input | " + ("MRE ↓ | MAE ↓ | RMSE ↓ | δ1 ↑ | " if "depth" in tasks else "")
                + ("mIoU | mAcc | " if "semantic" in tasks else "") + "pixels with a prediction |",
                "|---|---|" + "---|" * ((4 if "depth" in tasks else 0) + (2 if "semantic" in tasks else 0) + 1)]
        for r in rect:
            cells = []
            if "depth" in tasks:
                cells += [_fmt(r.get(k)) for k in ("mre", "mae", "rmse", "delta1")]
            if "semantic" in tasks:
                cells += [_fmt(r.get(k), 2) for k in SEG_KEYS]
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


def load_config(path: str | None, overrides: list[str]) -> DictConfig:
    default = Path(__file__).resolve().parents[2] / "configs" / "fisheye" / "small_cpu.yaml"
    path = Path(path) if path else default
    if not path.is_file():
        raise FileNotFoundError(f"protocol config {str(path)!r} does not exist")
    cfg = OmegaConf.load(path)
    try:
        cfg = OmegaConf.merge(cfg, OmegaConf.from_dotlist(overrides))
    except Exception as e:  # noqa: BLE001
        raise ValueError(f"bad override in {overrides}: {e}") from e
    for key in ("image", "panoramas", "cameras", "model", "loss", "train", "finetune"):
        if key not in cfg:
            raise KeyError(f"protocol config {str(path)!r} has no '{key}' section")
    return cfg


def run(cfg: DictConfig, out_dir: str | Path, fresh: bool = False, panoramas: dict[str, Any] | None = None
        ) -> dict[str, Any]:
    """Run the whole protocol; returns ``{"rows", "radial", "coverage", "comparison"}``.

    ``panoramas``: optional ``{"train": dataset, "test": dataset}`` of equirectangular sample dicts used
    instead of ``cfg.panoramas`` (e.g. a small stand-in in tests).
    """
    from hydra.utils import instantiate
    t0 = time.time()
    out = Path(out_dir)
    ckdir = out / "checkpoints"
    seed = int(cfg.get("seed", 0))
    seed_everything(seed, num_threads=int(cfg.get("threads", 0)))
    device = torch.device(cfg.get("device", "cpu") if cfg.get("device", "cpu") != "auto" else
                          ("cuda" if torch.cuda.is_available() else "cpu"))
    W, H = int(cfg.image.width), int(cfg.image.height)
    tasks = list(cfg.model.get("tasks", ["depth", "semantic"]))
    loss_fn = instantiate(cfg.loss, _convert_="all")
    bs, ebs = int(cfg.train.batch_size), int(cfg.get("eval", {}).get("batch_size", cfg.train.batch_size))
    views = int(cfg.get("views_per_panorama", 1))
    angles = dict(cfg.get("orientation", {}))

    banks = {}
    for split in ("train", "test"):
        src = (panoramas[split] if panoramas is not None else
               build_panoramas(OmegaConf.to_container(cfg.panoramas[split], resolve=True), split))
        banks[split] = PanoramaBank(src, f"{split} panoramas")
    pers = {s: PerspectiveFromPanoramas(width=W, height=H, fov_deg=float(cfg.get("pers", {}).get("fov_deg", 90.0)),
                                        panoramas=banks[s], split=s, views_per_panorama=views, seed=seed, **angles)
            for s in banks}
    cams = {name: load_camera(spec, W, H) for name, spec in cfg.cameras.items()}
    fish = {name: {s: ViewsFromPanoramas(cam, panoramas=banks[s], split=s, views_per_panorama=views, seed=seed,
                                         **angles) for s in banks} for name, cam in cams.items()}
    rad = cfg.get("radial", {})
    edges = radial_bin_edges(float(rad.get("max_radius", 490.0)), int(rad.get("num_bins", 10)))
    mkw = {k: v for k, v in OmegaConf.to_container(cfg.model, resolve=True).items()}

    def model_std() -> UNet:
        return UNet(**mkw)

    def trained(name: str, make, dataset, steps: int, lr: float, init: dict | None) -> torch.nn.Module:
        path = ckdir / f"{name}.pt"
        model = make()
        if path.is_file() and not fresh:
            model.load_state_dict(load_checkpoint(path)["model"])
            log.info("%s: loaded %s (delete it or pass --fresh to retrain)", name, path)
            return model
        if init is not None:
            model.load_state_dict(init)
        torch.manual_seed(seed)
        t = time.time()
        losses = train_steps(model, dataset, loss_fn, steps, lr, bs, seed, device, name)
        save_checkpoint(path, {"model": model.state_dict(), "losses": losses, "seconds": time.time() - t})
        log.info("%s: %d steps in %.0f s, loss %.3f -> %.3f", name, steps, time.time() - t,
                 losses[0] if losses else math.nan, losses[-1] if losses else math.nan)
        return model

    rows: list[dict] = []
    radial: dict[str, dict[str, list[dict]]] = {}

    def record(stage: str, dataset: str, kernel: str, model, ds, run_name: str, use_edges=True) -> None:
        scal, table, extra = evaluate_model(model, ds, tasks, ebs, device, edges if use_edges else None,
                                            f"eval {stage} {dataset} {kernel}")
        rows.append({"stage": stage, "dataset": dataset, "kernel": kernel, **scal, **extra})
        if table:
            radial.setdefault(dataset.removesuffix("-R"), {})[run_name] = table
            atomic_write_text(out / "radial" / f"{dataset}_{run_name}.csv", rows_to_csv(table))
        log.info("%s %s %s: %s", stage, dataset, kernel, {k: round(v, 4) for k, v in scal.items()})

    # 1. baseline on Pers
    bl = trained("pers_bl", model_std, pers["train"], int(cfg.train.steps), float(cfg.train.lr), None)
    bl_state = copy.deepcopy(bl.state_dict())
    # 2. BL evaluation, Std and Calib
    record("BL", "Pers", "Std", bl, pers["test"], "BL-Std", use_edges=False)
    if cfg.get("pers", {}).get("calib", True):
        m = model_std(); m.load_state_dict(bl_state); m.calibrate(pers["test"].camera)
        record("BL", "Pers", "Calib", m, pers["test"], "BL-Calib", use_edges=False)
    for name, cam in cams.items():
        m = model_std(); m.load_state_dict(bl_state)
        record("BL", name, "Std", m, fish[name]["test"], "BL-Std")
        m.calibrate(cam)
        record("BL", name, "Calib", m, fish[name]["test"], "BL-Calib")
    # 3.-4. fine-tune Std and Calib, evaluate
    ft_steps, ft_lr = int(cfg.finetune.steps), float(cfg.finetune.lr)
    for name, cam in cams.items():
        ft = trained(f"{name}_ft_std", model_std, fish[name]["train"], ft_steps, ft_lr, bl_state)
        record("FT", name, "Std", ft, fish[name]["test"], "FT-Std")
        ftc = trained(f"{name}_ft_calib", lambda: model_std().calibrate(cam), fish[name]["train"], ft_steps, ft_lr,
                      bl_state)
        record("FT", name, "Calib", ftc, fish[name]["test"], "FT-Calib")
    # §7.4.3 rectification baseline
    coverage: dict[str, dict] = {}
    rcfg = cfg.get("rectify", {})
    if rcfg.get("enabled", True):
        fov = rcfg.get("fov_deg", 150.0)
        for name in rcfg.get("cameras", list(cams)):
            cam = cams[name]
            coverage[name] = rectification_report(cam, fov_deg=fov)
            m = model_std(); m.load_state_dict(bl_state)
            record("BL", f"{name}-R", "Std", RectifiedModel(m, cam, fov_deg=fov), fish[name]["test"], "BL-R")
            if rcfg.get("finetune", False):
                r = trained(f"{name}_ft_rect", lambda: RectifiedModel(model_std(), cam, fov_deg=fov),
                            fish[name]["train"], ft_steps, ft_lr,
                            {f"model.{k}": v for k, v in bl_state.items()})
                record("FT", f"{name}-R", "Std", r, fish[name]["test"], "FT-R")
    # outputs
    order = {"BL": 0, "FT": 1}
    rows.sort(key=lambda r: (order[r["stage"]], r["dataset"] != "Pers", r["dataset"]))
    atomic_write_text(out / "results.csv", rows_to_csv(rows))
    atomic_write_text(out / "tables.md", "# Calibrated fisheye protocol (thesis §7.4)\n\n"
                      + markdown_tables(rows, tasks, coverage))
    depth_plot = [k for k in ("mre", "mae", "rmse", "delta1") if "depth" in tasks]
    seg_plot = [k for k in ("miou", "macc", "pixel_acc") if "semantic" in tasks]
    # thesis colours: standard red, calibrated blue; baseline dashed, fine-tuned solid; rectified green
    styles = {"BL-Std": {"color": "tab:red", "linestyle": "--"}, "FT-Std": {"color": "tab:red"},
              "BL-Calib": {"color": "tab:blue", "linestyle": "--"}, "FT-Calib": {"color": "tab:blue"},
              "BL-R": {"color": "tab:green", "linestyle": "--"}, "FT-R": {"color": "tab:green"}}
    for ds, runs in (radial.items() if cfg.get("plots", True) else ()):
        main = {k: v for k, v in runs.items() if not k.endswith("-R")}
        for task, keys in (("depth", depth_plot), ("semantic", seg_plot)):
            if keys:
                plot_radial(main, keys, out / f"radial_{ds}_{task}.png", f"{ds}: Std vs Calib", styles=styles)
                rr = {k: v for k, v in runs.items() if k in ("BL-Std", "FT-Std", "BL-R", "FT-R")}
                if any(k.endswith("-R") for k in rr):
                    plot_radial(rr, keys, out / f"radial_{ds}_rectified_{task}.png", f"{ds} vs {ds}-R (Std)",
                                styles=styles)
    comparison = compare_large_radii(radial, float(cfg.get("large_radius_fraction", 1 / 3)))
    summary = {"rows": rows, "coverage": coverage, "comparison": comparison, "seconds": time.time() - t0,
               "config": OmegaConf.to_container(cfg, resolve=True)}
    atomic_write_json(out / "summary.json", summary)
    return {"rows": rows, "radial": radial, "coverage": coverage, "comparison": comparison}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m omnidl.fisheye.protocol", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default=None, help="protocol YAML (default configs/fisheye/small_cpu.yaml)")
    p.add_argument("--out", default=None, help="output folder (default: out_dir of the config)")
    p.add_argument("--fresh", action="store_true", help="retrain stages whose checkpoint exists")
    p.add_argument("overrides", nargs="*", help="OmegaConf dot-list overrides, e.g. train.steps=50")
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    try:
        cfg = load_config(a.config, a.overrides)
    except (FileNotFoundError, KeyError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    out = a.out or cfg.get("out_dir", "outputs/fisheye_protocol")
    res = run(cfg, out, fresh=a.fresh)
    print((Path(out) / "tables.md").read_text())
    print("Calib vs Std after fine-tuning at large radii:")
    print(json.dumps(res["comparison"], indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
