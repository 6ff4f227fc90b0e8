"""Evaluation: :func:`evaluate` (``python evaluate.py model=... checkpoint=...``).

Writes into ``<output_dir>``:

* ``metrics.json`` — mean metrics over the dataset (as the metrics object accumulates them), the number of
  images, the checkpoint, and with ``eval.rotation_deg`` the metrics per rotation angle;
* ``per_image.csv`` / ``per_image.json`` — one record per image (metrics of that image alone, hook scalars);
* ``images/<name>.png`` — ``RGB | depth pred | depth GT | semantic pred | semantic GT`` panels;
* ``predictions/<name>_depth.png`` (16-bit, millimetres) and ``<name>_semantic.png`` (class ids);
* ``pointclouds/<name>.ply`` — coloured points from the predicted depth through the camera's ``unproject``;
* ``rotation.csv`` and ``rotation.png`` — metrics against the rotation angle (with ``eval.rotation_deg``);
* ``postprocess.jsonl`` — the non-scalar results of the ``postprocess`` hooks per batch.

Datasets without labels (``data=folder``) only get predictions, pictures and point clouds.
"""
from __future__ import annotations

import copy
import csv
import io
import json
import logging
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf, open_dict
from torch.utils.data import DataLoader

from omnidl.data.collate import collate_samples
from omnidl.data.robust import SkipCorrupt
from omnidl.utils.io import atomic_imwrite, atomic_write_json, atomic_write_text

from .build import build_camera, build_dataset, build_metrics, build_model, build_viz, output_dir, pick_device
from .checkpoint import load_checkpoint, load_model_weights
from .seed import seed_everything
from .trainer import autocast_context, to_device

log = logging.getLogger("omnidl.engine")


def _sample_name(batch: dict[str, Any], i: int, fallback: int) -> str:
    meta = (batch.get("meta") or [{}] * (i + 1))[i] or {}
    name = meta.get("name") or (Path(meta["image"]).stem if meta.get("image") else None)
    if name is None and "index" in meta:  # e.g. synthetic samples: <split>_<index>
        name = f"{meta['split']}_{int(meta['index']):05d}" if "split" in meta else f"{int(meta['index']):05d}"
    name = str(name) if name is not None else f"{fallback:05d}"
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)


def _slice(d: dict[str, Any], i: int) -> dict[str, Any]:
    out = {}
    for k, v in d.items():
        if isinstance(v, torch.Tensor) and v.dim() > 0:
            out[k] = v[i:i + 1]
        elif isinstance(v, list):
            out[k] = v[i:i + 1]
        else:
            out[k] = v
    return out


def _scalars(d: dict[str, Any]) -> dict[str, float]:
    out = {}
    for k, v in d.items():
        if isinstance(v, (int, float, np.floating, np.integer)) and not isinstance(v, bool):
            out[k] = float(v)
        elif isinstance(v, torch.Tensor) and v.numel() == 1:
            out[k] = float(v)
    return out


def _clamp_depth(outputs: dict, batch: dict, depth_max: float | None) -> None:
    if depth_max is None:
        return
    if isinstance(outputs.get("depth"), torch.Tensor):
        outputs["depth"] = outputs["depth"].clamp(0, depth_max)
    if isinstance(batch.get("depth"), torch.Tensor):
        d = batch["depth"]
        batch["depth"] = torch.where(d > depth_max, torch.zeros_like(d), d)


def _write_csv(path: Path, records: list[dict[str, Any]]) -> None:
    keys: list[str] = []
    for r in records:
        keys += [k for k in r if k not in keys]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=keys)
    w.writeheader()
    for r in records:
        w.writerow(r)
    atomic_write_text(path, buf.getvalue())


def _save_pictures(out_dir: Path, name: str, outputs: dict, batch: dict, i: int, viz, camera_fn, save_image: bool,
                   save_ply: bool) -> None:
    from omnidl.viz import depth_to_points, to_uint8_bgr, write_ply
    if save_image and viz is not None:
        pic = viz(_slice(outputs, i), _slice(batch, i))
        atomic_imwrite(out_dir / "images" / f"{name}.png", to_uint8_bgr(pic))
    if save_image:
        if isinstance(outputs.get("depth"), torch.Tensor):
            mm = (outputs["depth"][i, 0].float().cpu().clamp(0, 65.535) * 1000).round().numpy().astype(np.uint16)
            atomic_imwrite(out_dir / "predictions" / f"{name}_depth.png", mm)
        if isinstance(outputs.get("semantic"), torch.Tensor):
            lab = outputs["semantic"][i].argmax(0).cpu().numpy().astype(np.uint8)
            atomic_imwrite(out_dir / "predictions" / f"{name}_semantic.png", lab)
    if save_ply and isinstance(outputs.get("depth"), torch.Tensor):
        depth = outputs["depth"][i].float().cpu()
        image = batch["image"][i].float().cpu()
        cam = camera_fn(depth.shape[-1], depth.shape[-2])
        pts, cols = depth_to_points(depth, cam, image)
        write_ply(out_dir / "pointclouds" / f"{name}.ply", pts, cols)


@torch.no_grad()
def evaluate(cfg: DictConfig) -> dict[str, Any]:
    """Evaluate ``cfg.checkpoint`` (or, with a warning, the untrained model) on ``cfg.data[cfg.eval.split]``.

    Returns the dict written to ``metrics.json``: ``{"metrics": {...}, "num_images", "checkpoint",
    "rotation": {angle: {...}} (when asked), "output_dir", "wall_time_s"}``.
    """
    t0 = time.time()
    ec = cfg.eval
    tc = cfg.trainer
    out_dir = Path(output_dir(cfg))
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "postprocess.jsonl").unlink(missing_ok=True)  # appended per batch below
    seed_everything(int(tc.seed), int(tc.num_threads), False)
    device = pick_device(str(tc.device))
    ckpt_path = cfg.get("checkpoint")
    ckpt = load_checkpoint(ckpt_path, map_location=device) if ckpt_path else None
    if ckpt is not None:
        cfg = _fill_from_checkpoint(cfg, ckpt)
    model = build_model(cfg).to(device).eval()
    if ckpt is not None:
        load_model_weights(model, ckpt, ckpt_path)
        log.info("loaded %s", ckpt_path)
    else:
        log.warning("no checkpoint given (checkpoint=PATH): evaluating the randomly initialised model")
    dataset = SkipCorrupt(build_dataset(cfg, str(ec.split)))
    n_total = len(dataset) if ec.max_images is None else min(len(dataset), int(ec.max_images))
    if n_total < len(dataset):
        dataset = torch.utils.data.Subset(dataset, range(n_total))
    loader = DataLoader(dataset, batch_size=int(ec.batch_size), shuffle=False, num_workers=int(tc.num_workers),
                        collate_fn=collate_samples)
    metrics = build_metrics(cfg)
    per_image_metrics = copy.deepcopy(metrics) if metrics is not None else None
    viz = build_viz(cfg)
    hooks = cfg.get("postprocess") or []
    hooks = [h.strip() for h in hooks.split(",") if h.strip()] if isinstance(hooks, str) else list(hooks)
    hook_opts = cfg.get("postprocess_options")
    hook_opts = OmegaConf.to_container(hook_opts, resolve=True) if hook_opts else {}
    cams: dict[tuple[int, int], Any] = {}

    def camera_fn(w: int, h: int):
        if (w, h) not in cams:
            cams[(w, h)] = build_camera(cfg, w, h)
        return cams[(w, h)]

    angles = [float(a) for a in ec.rotation_deg] or [None]
    if 0.0 not in angles and angles != [None]:
        angles = [None] + angles  # pictures/per-image records always come from the unrotated images
    has_labels = metrics is not None
    records: list[dict[str, Any]] = []
    rotation: dict[str, dict[str, float]] = {}
    mean: dict[str, float] = {}
    n_save_img = int(ec.save_images)
    n_save_ply = int(ec.save_pointclouds)
    from tqdm.auto import tqdm
    for angle in angles:
        R = None
        if angle is not None and angle != 0.0:
            from omnidl.data.transforms import horizontal_rotation
            R = horizontal_rotation(angle, str(ec.rotation_axis))
        base = angle is None or (angle == 0.0 and None not in angles)
        if metrics is not None:
            metrics.reset()
        seen = 0
        desc = "evaluate" if angle is None else f"evaluate @ {angle:g} deg"
        for batch in tqdm(loader, desc=desc, disable=not bool(tc.progress), dynamic_ncols=True):
            if batch is None:
                continue
            if R is not None:
                batch = _rotate_batch(batch, R)
            batch = to_device(batch, device)
            with autocast_context(device, bool(tc.amp)):
                outputs = model(batch["image"])
            outputs = {k: (v.float() if isinstance(v, torch.Tensor) and v.is_floating_point() else v)
                       for k, v in outputs.items()}
            _clamp_depth(outputs, batch, ec.depth_max)
            if has_labels:
                try:
                    metrics.update(outputs, batch)
                except KeyError as e:
                    log.info("the dataset has no labels for the metrics (%s): writing predictions only", e)
                    has_labels = False
            if not base:
                continue
            hook_res = {}
            if hooks:
                from omnidl.postprocess.registry import run_hooks
                hook_res = run_hooks(hooks, outputs, batch, hook_opts)
                rest = {k: v for k, v in hook_res.items() if k not in _scalars(hook_res)}
                if rest:
                    with open(out_dir / "postprocess.jsonl", "a") as f:
                        f.write(json.dumps({"names": [_sample_name(batch, i, seen + i)
                                                      for i in range(batch["image"].shape[0])], **rest},
                                           default=_json_default) + "\n")
            for i in range(batch["image"].shape[0]):
                idx = seen + i
                name = _sample_name(batch, i, idx)
                rec: dict[str, Any] = {"index": idx, "name": name}
                if has_labels:
                    per_image_metrics.reset()
                    per_image_metrics.update(_slice(outputs, i), _slice(batch, i))
                    rec.update(_scalars(per_image_metrics.compute()))
                rec.update(_scalars(hook_res))
                records.append(rec)
                save_img = n_save_img < 0 or idx < n_save_img
                save_ply = n_save_ply < 0 or idx < n_save_ply
                if save_img or save_ply:
                    _save_pictures(out_dir, name, outputs, batch, i, viz, camera_fn, save_img, save_ply)
            seen += batch["image"].shape[0]
        result = {k: float(v) for k, v in metrics.compute().items()} if has_labels else {}
        if base:
            mean = result
        if angle is not None:
            rotation[f"{angle:g}"] = result
    summary: dict[str, Any] = {"metrics": mean, "num_images": len(records), "checkpoint": ckpt_path,
                               "split": str(ec.split), "output_dir": str(out_dir)}
    if rotation:
        summary["rotation"] = rotation
        _write_rotation(out_dir, rotation)
    summary["wall_time_s"] = time.time() - t0
    if records:
        _write_csv(out_dir / "per_image.csv", records)
        atomic_write_json(out_dir / "per_image.json", records)
    atomic_write_json(out_dir / "metrics.json", summary)
    text = "\n".join(f"  {k:>12s}: {v:.4f}" for k, v in mean.items()) or "  (no labels: predictions only)"
    print(f"evaluated {len(records)} images ({ckpt_path or 'untrained model'}):\n{text}\noutputs in {out_dir}")
    return summary


def _fill_from_checkpoint(cfg: DictConfig, ckpt: dict[str, Any]) -> DictConfig:
    """``python evaluate.py checkpoint=PATH`` without ``model=...``: take the model (and the camera, metrics and
    data when those are not chosen either) from the training config stored in the checkpoint."""
    saved = ckpt.get("config")
    if not isinstance(saved, dict) or cfg.get("model") is not None:
        return cfg
    cfg = copy.deepcopy(cfg)
    taken = []
    with open_dict(cfg):
        for key in ("model", "camera", "metrics", "data"):
            if cfg.get(key) is None and saved.get(key) is not None:
                cfg[key] = OmegaConf.create(saved[key])
                taken.append(key)
    log.info("no model=... given: using %s from the checkpoint's training config", ", ".join(taken))
    return cfg


def _rotate_batch(batch: dict[str, Any], R: torch.Tensor) -> dict[str, Any]:
    from omnidl.data.transforms import rotate_tensors
    return rotate_tensors(batch, R, batched=True, drop_unknown=True)


def _write_rotation(out_dir: Path, rotation: dict[str, dict[str, float]]) -> None:
    angles = sorted(rotation, key=float)
    keys = sorted({k for r in rotation.values() for k in r})
    _write_csv(out_dir / "rotation.csv", [{"angle_deg": float(a), **rotation[a]} for a in angles])
    if keys:
        from omnidl.viz import plot_curves
        plot_curves(out_dir / "rotation.png", [float(a) for a in angles],
                    {k: [rotation[a].get(k, math.nan) for a in angles] for k in keys},
                    xlabel="rotation about a horizontal axis (deg)", ylabel="metric",
                    title="evaluation under rotation")


def _json_default(o):
    if isinstance(o, torch.Tensor):
        return o.detach().cpu().tolist()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    return str(o)
