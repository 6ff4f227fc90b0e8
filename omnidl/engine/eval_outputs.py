"""What evaluation writes per image and per run (see :mod:`omnidl.engine.evaluator` for the file list).

Batches are collated sample dicts (``image (B, 3, H, W)``, targets, ``meta`` a list of dicts); outputs
are the model's named outputs (``depth (B, 1, H, W)`` metres, ``semantic (B, C, H, W)`` logits, ...).
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from omnidl.utils.io import atomic_imwrite, atomic_write_csv, json_default


def sample_name(batch: dict[str, Any], i: int, fallback: int) -> str:
    """A file-name-safe name for sample ``i`` of a batch: ``meta`` name, image stem, ``<split>_<index>``,
    else ``fallback`` (5 digits)."""
    meta = (batch.get("meta") or [{}] * (i + 1))[i] or {}
    name = meta.get("name") or (Path(meta["image"]).stem if meta.get("image") else None)
    if name is None and "index" in meta:  # e.g. synthetic samples: <split>_<index>
        name = f"{meta['split']}_{int(meta['index']):05d}" if "split" in meta else f"{int(meta['index']):05d}"
    name = str(name) if name is not None else f"{fallback:05d}"
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)


def slice_sample(d: dict[str, Any], i: int) -> dict[str, Any]:
    """Sample ``i`` of a batch (or outputs) dict as a batch of one: tensors with a batch dim and lists are sliced."""
    out = {}
    for k, v in d.items():
        if isinstance(v, torch.Tensor) and v.dim() > 0:
            out[k] = v[i:i + 1]
        elif isinstance(v, list):
            out[k] = v[i:i + 1]
        else:
            out[k] = v
    return out


def scalars(d: dict[str, Any]) -> dict[str, float]:
    """The plain numbers of a dict (ints, floats, numpy scalars, one-element tensors; not bools) as floats."""
    out = {}
    for k, v in d.items():
        if isinstance(v, (int, float, np.floating, np.integer)) and not isinstance(v, bool):
            out[k] = float(v)
        elif isinstance(v, torch.Tensor) and v.numel() == 1:
            out[k] = float(v)
    return out


def append_hook_results(path: Path, names: list[str], results: dict[str, Any]) -> None:
    """Append the non-scalar hook results of one batch (with its sample names) as a JSON line to ``path``."""
    rest = {k: v for k, v in results.items() if k not in scalars(results)}
    if rest:
        with open(path, "a") as f:
            f.write(json.dumps({"names": names, **rest}, default=json_default) + "\n")


def save_pictures(out_dir: Path, name: str, outputs: dict, batch: dict, i: int, viz,
                  camera_fn: Callable[[int, int], Any], save_image: bool, save_ply: bool) -> None:
    """Pictures of sample ``i``: the visualiser's panel ``images/<name>.png``, ``predictions/<name>_depth.png``
    (uint16 millimetres) and ``<name>_semantic.png`` (class ids) with ``save_image``; with ``save_ply`` the
    predicted depth as a coloured point cloud ``pointclouds/<name>.ply`` through ``camera_fn(w, h).unproject``."""
    from omnidl.viz import depth_to_points, to_uint8_bgr, write_ply
    if save_image and viz is not None:
        pic = viz(slice_sample(outputs, i), slice_sample(batch, i))
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
        pts, cols = depth_to_points(depth, camera_fn(depth.shape[-1], depth.shape[-2]), image)
        write_ply(out_dir / "pointclouds" / f"{name}.ply", pts, cols)


def write_rotation(out_dir: Path, rotation: dict[str, dict[str, float]]) -> None:
    """``rotation.csv`` (one row per angle) and ``rotation.png`` (each metric against the angle)."""
    angles = sorted(rotation, key=float)
    keys = sorted({k for r in rotation.values() for k in r})
    atomic_write_csv(out_dir / "rotation.csv", [{"angle_deg": float(a), **rotation[a]} for a in angles])
    if keys:
        from omnidl.viz import plot_curves
        plot_curves(out_dir / "rotation.png", [float(a) for a in angles],
                    {k: [rotation[a].get(k, math.nan) for a in angles] for k in keys},
                    xlabel="rotation about a horizontal axis (deg)", ylabel="metric",
                    title="evaluation under rotation")
