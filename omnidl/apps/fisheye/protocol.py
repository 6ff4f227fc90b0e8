"""The calibrated-fisheye protocol of thesis §7.4, end to end, with one command::

    python -m omnidl.apps.fisheye.protocol --config configs/fisheye/small_cpu.yaml [--out DIR] [key=value ...]

Each training stage is a Hydra experiment of ``configs/experiment/`` run by :func:`omnidl.engine.train`
(:mod:`omnidl.apps.fisheye.stages`), on panoramas rendered once and held in memory:

1. train a U-Net with standard convolutions on perspective crops of the training panoramas (*Pers*,
   ``experiment=fisheye_pers``): the baseline (BL);
2. evaluate BL on Pers and on the fisheye test sets (F165, F195), with standard and with calibrated
   convolutions (the same weights; calibrated = the ``fisheye_<cam>_calib`` experiment's model);
3. fine-tune a copy of BL on each fisheye training set, once with standard and once with calibrated
   convolutions (``fisheye_<cam>_{std,calib}``), for ``finetune.steps`` (a fraction of the baseline budget);
4. evaluate the fine-tuned networks (FT); plus the rectification baseline (§7.4.3): rectify ->
   BL (and, with ``rectify.finetune``, a standard copy fine-tuned through the warps) -> un-rectify,
   evaluated in the fisheye domain, with the fraction of the image that cannot be rectified.

Writes to ``out_dir``: ``results.csv`` (one row per stage/dataset/kernel), ``tables.md`` (Tables
7.1–7.4-shaped), ``radial/<dataset>_<run>.csv`` (metrics per radius bin, mean ± std over images),
``radial_<dataset>_{depth,semantic}.png`` (Figs 7.2/7.5) and ``radial_<dataset>_rectified_*.png``
(Figs 7.8/7.9), ``summary.json`` (the Std-vs-Calib comparison at large radii), ``checkpoints/<stage>.pt``
(a re-run skips stages whose checkpoint exists; ``--fresh`` retrains) and ``runs/<stage>/`` (the engine's
run folders). Overrides are OmegaConf dot-list entries (``train.steps=50``) of keys the config has (a typo is
an error); ``+key=value`` adds a new key.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from omnidl.data.fisheye import build_panoramas
from omnidl.engine.build import build_dataset, pick_device
from omnidl.engine.seed import seed_everything
from omnidl.metrics.radial import plot_radial, radial_bin_edges
from omnidl.utils.io import atomic_write_json, atomic_write_text, rows_to_csv

from .banks import PanoramaBank, holding
from .rectified import rectification_report
from .stages import CONFIG_DIR, compose_experiment, evaluate_stage, model_with, train_stage, training_config
from .tables import compare_large_radii, markdown_tables

log = logging.getLogger("omnidl.apps.fisheye")
#: what the numbers of results.csv / summary.json are (tables.md alone prints mIoU/mAcc in %, labelled)
UNITS = ("fractions in [0, 1]: miou, macc, pixel_acc, delta1-3, covered_fraction, coverage; metres: mae, rmse; "
         "relative: mre; rmse_log: log metres")
REQUIRED = ("image", "panoramas", "experiments", "model", "loss", "train", "finetune")
#: thesis colours: standard red, calibrated blue; baseline dashed, fine-tuned solid; rectified green
STYLES = {"BL-Std": {"color": "tab:red", "linestyle": "--"}, "FT-Std": {"color": "tab:red"},
          "BL-Calib": {"color": "tab:blue", "linestyle": "--"}, "FT-Calib": {"color": "tab:blue"},
          "BL-R": {"color": "tab:green", "linestyle": "--"}, "FT-R": {"color": "tab:green"}}


def load_config(path: str | None, overrides: list[str]) -> DictConfig:
    """The protocol YAML (default ``configs/fisheye/small_cpu.yaml``) with dot-list ``overrides``."""
    path = Path(path) if path else CONFIG_DIR / "fisheye" / "small_cpu.yaml"
    if not path.is_file():
        raise FileNotFoundError(f"protocol config {str(path)!r} does not exist")
    try:
        cfg = OmegaConf.load(path)
    except Exception as e:  # noqa: BLE001 - yaml's parser errors
        raise ValueError(f"protocol config {str(path)!r} is not valid YAML: {e}") from e
    if not isinstance(cfg, DictConfig):
        raise ValueError(f"protocol config {str(path)!r} must be a mapping of sections, got a list")
    for o in overrides:
        if "=" not in o or not o.split("=", 1)[0].lstrip("+"):
            raise ValueError(f"bad override {o!r} for {str(path)!r}: expected key=value (e.g. train.steps=50)")
    OmegaConf.set_struct(cfg, True)  # an override of a key the config does not have (a typo) is an error...
    plain = [o for o in overrides if not o.startswith("+")]
    added = [o[1:] for o in overrides if o.startswith("+")]  # ...unless written +key=value (a new key)
    try:
        cfg = OmegaConf.merge(cfg, OmegaConf.from_dotlist(plain))
        OmegaConf.set_struct(cfg, False)
        cfg = OmegaConf.merge(cfg, OmegaConf.from_dotlist(added))
    except Exception as e:  # noqa: BLE001
        raise ValueError(f"bad override in {overrides} for {str(path)!r} (write +key=value to add a key the "
                         f"config does not have): {e}") from e
    for key in REQUIRED:
        if key not in cfg:
            raise KeyError(f"protocol config {str(path)!r} has no '{key}' section")
    return cfg


def run(cfg: DictConfig, out_dir: str | Path, fresh: bool = False, panoramas: dict[str, Any] | None = None
        ) -> dict[str, Any]:
    """Run the whole protocol; returns ``{"rows", "radial", "coverage", "comparison"}``.

    ``panoramas``: optional ``{"train": dataset, "test": dataset}`` of equirectangular sample dicts used
    instead of ``cfg.panoramas`` (e.g. a small stand-in in tests).
    """
    t0 = time.time()
    out = Path(out_dir)
    cfg = cfg.copy()
    cfg.out_dir = str(out)  # ${out_dir} in the config (the panorama cache) follows --out
    seed = int(cfg.get("seed", 0))
    seed_everything(seed, num_threads=int(cfg.get("threads", 0)))
    banks = {split: PanoramaBank(panoramas[split] if panoramas is not None else
                                 build_panoramas(OmegaConf.to_container(cfg.panoramas[split], resolve=True), split),
                                 f"{split} panoramas") for split in ("train", "test")}
    with holding(banks):
        rows, radial, coverage = _stages(cfg, out, fresh)
    order = {"BL": 0, "FT": 1}
    rows.sort(key=lambda r: (order[r["stage"]], r["dataset"] != "Pers", r["dataset"]))
    tasks = list(cfg.model.get("tasks", ["depth", "semantic"]))
    atomic_write_text(out / "results.csv", rows_to_csv(rows))
    atomic_write_text(out / "tables.md", "# Calibrated fisheye protocol (thesis §7.4)\n\n"
                      + markdown_tables(rows, tasks, coverage))
    if cfg.get("plots", True):
        _plots(radial, tasks, out)
    comparison = compare_large_radii(radial, float(cfg.get("large_radius_fraction", 1 / 3)))
    summary = {"units": UNITS, "rows": rows, "coverage": coverage, "comparison": comparison,
               "seconds": time.time() - t0,
               "config": OmegaConf.to_container(cfg, resolve=True)}
    atomic_write_json(out / "summary.json", summary)
    return {"rows": rows, "radial": radial, "coverage": coverage, "comparison": comparison}


def _stages(cfg: DictConfig, out: Path, fresh: bool) -> tuple[list[dict], dict, dict]:
    """Steps 1–4 and the rectification baseline; returns ``(rows, radial tables, coverage)``."""
    ckdir, runs = out / "checkpoints", out / "runs"
    device = pick_device(str(cfg.get("device", "cpu")))
    tasks = list(cfg.model.get("tasks", ["depth", "semantic"]))
    ebs = int(cfg.get("eval", {}).get("batch_size", cfg.train.batch_size))
    rad = cfg.get("radial", {})
    edges = radial_bin_edges(float(rad.get("max_radius", 490.0)), int(rad.get("num_bins", 10)))
    exps = cfg.experiments
    pers_over = [f"data.fov_deg={float(cfg.get('pers', {}).get('fov_deg', 90.0))}"]
    pers_cfg = compose_experiment(str(exps.baseline), cfg, pers_over)
    fish = {name: {kind: compose_experiment(str(e[kind]), cfg) for kind in ("std", "calib")}
            for name, e in exps.fisheye.items()}
    rows: list[dict] = []
    radial: dict[str, dict[str, list[dict]]] = {}

    def record(stage: str, dataset: str, kernel: str, model, ds, run_name: str, use_edges: bool = True) -> None:
        scal, table, extra = evaluate_stage(model, ds, tasks, ebs, device, edges if use_edges else None)
        rows.append({"stage": stage, "dataset": dataset, "kernel": kernel, **scal, **extra})
        if table:
            radial.setdefault(dataset.removesuffix("-R"), {})[run_name] = table
            atomic_write_text(out / "radial" / f"{dataset}_{run_name}.csv", rows_to_csv(table))
        log.info("%s %s %s: %s", stage, dataset, kernel, {k: round(v, 4) for k, v in scal.items()})

    # 1. baseline on Pers
    bl_path = ckdir / "pers_bl.pt"
    bl = train_stage("pers_bl", training_config(pers_cfg, runs / "pers_bl", int(cfg.train.steps),
                                                float(cfg.train.lr)), ckdir, fresh)
    # 2. BL evaluation, Std and Calib
    pers_test = build_dataset(pers_cfg, "test")
    record("BL", "Pers", "Std", model_with(pers_cfg, bl), pers_test, "BL-Std", use_edges=False)
    if cfg.get("pers", {}).get("calib", True):
        record("BL", "Pers", "Calib", model_with(pers_cfg, bl).calibrate(pers_test.camera), pers_test, "BL-Calib",
               use_edges=False)
    tests = {name: build_dataset(c["std"], "test") for name, c in fish.items()}
    for name, c in fish.items():
        record("BL", name, "Std", model_with(c["std"], bl), tests[name], "BL-Std")
        record("BL", name, "Calib", model_with(c["calib"], bl), tests[name], "BL-Calib")
    # 3.-4. fine-tune Std and Calib, evaluate
    ft_steps, ft_lr = int(cfg.finetune.steps), float(cfg.finetune.lr)
    for name, c in fish.items():
        for kind, kernel in (("std", "Std"), ("calib", "Calib")):
            stage = f"{name}_ft_{kind}"
            ft = train_stage(stage, training_config(c[kind], runs / stage, ft_steps, ft_lr, bl_path), ckdir, fresh)
            record("FT", name, kernel, model_with(c[kind], ft), tests[name], f"FT-{kernel}")
    # §7.4.3 rectification baseline
    coverage: dict[str, dict] = {}
    rcfg = cfg.get("rectify", {})
    if rcfg.get("enabled", True):
        fov = float(rcfg.get("fov_deg", 150.0))
        for name in rcfg.get("cameras", list(fish)):
            std = fish[name]["std"]
            coverage[name] = rectification_report(tests[name].camera, fov_deg=fov)
            bl_rect = {f"model.{k}": v for k, v in bl.items()}
            record("BL", f"{name}-R", "Std", model_with(std, bl_rect, rectify_fov=fov), tests[name], "BL-R")
            if rcfg.get("finetune", False):
                stage = f"{name}_ft_rect"
                ft = train_stage(stage, training_config(std, runs / stage, ft_steps, ft_lr, bl_path, rectify_fov=fov),
                                 ckdir, fresh)
                record("FT", f"{name}-R", "Std", model_with(std, ft, rectify_fov=fov), tests[name], "FT-R")
    return rows, radial, coverage


def _plots(radial: dict[str, dict[str, list[dict]]], tasks: list[str], out: Path) -> None:
    """Radius plots: Std vs Calib per dataset, and the fisheye vs rectified standard runs."""
    depth_plot = [k for k in ("mre", "mae", "rmse", "delta1") if "depth" in tasks]
    seg_plot = [k for k in ("miou", "macc", "pixel_acc") if "semantic" in tasks]
    for ds, runs in radial.items():
        main = {k: v for k, v in runs.items() if not k.endswith("-R")}
        for task, keys in (("depth", depth_plot), ("semantic", seg_plot)):
            if not keys:
                continue
            plot_radial(main, keys, out / f"radial_{ds}_{task}.png", f"{ds}: Std vs Calib", styles=STYLES)
            rr = {k: v for k, v in runs.items() if k in ("BL-Std", "FT-Std", "BL-R", "FT-R")}
            if any(k.endswith("-R") for k in rr):
                plot_radial(rr, keys, out / f"radial_{ds}_rectified_{task}.png", f"{ds} vs {ds}-R (Std)",
                            styles=STYLES)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m omnidl.apps.fisheye.protocol", description=__doc__.split("\n\n")[0],
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
