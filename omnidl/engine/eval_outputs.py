"""What evaluation writes per image and per run (see :mod:`omnidl.engine.evaluator` for the file list).

Batches are collated sample dicts (``image (B, 3, H, W)``, targets, ``meta`` a list of dicts); outputs
are the model's named outputs (``depth (B, 1, H, W)`` metres, ``semantic (B, C, H, W)`` logits, ...).
"""
from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from omnidl.utils.io import atomic_imwrite, atomic_write_csv, json_default


def sample_name(batch: dict[str, Any], i: int, fallback: int) -> str:
    """The original name of sample ``i`` of a batch: ``meta`` name, image stem, ``<split>_<index>``, else
    ``fallback`` (5 digits). Not file-name safe: :class:`OutputNames` turns it into an output stem."""
    meta = (batch.get("meta") or [{}] * (i + 1))[i] or {}
    name = meta.get("name") or (Path(meta["image"]).stem if meta.get("image") else None)
    if name is None and "index" in meta:  # e.g. synthetic samples: <split>_<index>
        name = f"{meta['split']}_{int(meta['index']):05d}" if "split" in meta else f"{int(meta['index']):05d}"
    return str(name) if name is not None else f"{fallback:05d}"


def sample_source(batch: dict[str, Any], i: int) -> str | None:
    """The file sample ``i`` was read from (``meta["image"]``), if the dataset says."""
    meta = (batch.get("meta") or [{}] * (i + 1))[i] or {}
    return str(meta["image"]) if meta.get("image") else None


def printable(name: str) -> str:
    """``name`` as text any UTF-8 file can hold: bytes of a non-UTF-8 file name (surrogate escapes) as ``\\xNN``."""
    return name.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


#: smaller images get the configured visualiser's compact strip (the titled figure's key needs the height)
MIN_FIGURE_HEIGHT = 64

#: longest safe stem kept before the hash suffix (file names hold 255 bytes; ``_semantic.png`` and the hash follow)
MAX_STEM = 120


class OutputNames:
    """Unique, file-name-safe output stems for the samples of one evaluation (``images/<stem>.png``,
    ``predictions/<stem>_depth.png``, ``pointclouds/<stem>.ply``).

    A name made only of letters, digits, ``-``, ``_`` and ``.`` (and not starting with ``.``) is its own stem.
    Any other name (spaces, ``?``, ``/``, non-UTF-8 bytes, too long) becomes its safe form plus ``-`` and 8 hex
    digits of a hash of the original, so ``a b``, ``a?b`` and ``a_b`` give three stems, the same ones in every
    run. A stem already taken (compared case-insensitively, for case-insensitive file systems) gets the hash of
    the sample's source file, then ``-2``, ``-3``, ... until it is free.
    """

    def __init__(self) -> None:
        self._taken: set[str] = set()

    def __call__(self, name: str, source: str | None = None) -> str:
        safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in name)
        if safe.startswith("."):
            safe = "_" + safe[1:]
        safe = safe[:MAX_STEM] or "_"
        stem = safe if safe == name else f"{safe}-{_hash8(name)}"
        if stem.lower() in self._taken and source is not None:
            stem = f"{stem}-{_hash8(source)}"
        base, k = stem, 2
        while stem.lower() in self._taken:
            stem, k = f"{base}-{k}", k + 1
        self._taken.add(stem.lower())
        return stem


def _hash8(text: str) -> str:
    return hashlib.sha1(text.encode("utf-8", "surrogateescape")).hexdigest()[:8]


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
                  camera_fn: Callable[[int, int], Any], save_image: bool, save_ply: bool,
                  depth_max: float | None = None, claim: Callable[[Path], Path] = lambda p: p) -> None:
    """Pictures of sample ``i`` under the output stem ``name``. With ``save_image``: ``images/<name>.png`` (the
    full-resolution titled figure ``input | depth | depth GT | semantics | semantics GT`` with a depth colour bar
    in metres and a class legend, :func:`omnidl.viz.prediction_figure`; models without depth/semantic outputs and
    images under ``MIN_FIGURE_HEIGHT`` rows get the configured visualiser's panel), ``inputs/<name>.jpg`` (the network input), ``predictions/<name>_depth.png``
    (uint16 millimetres) and ``<name>_semantic.png`` (class ids). With ``save_ply``: the predicted depth as a
    coloured point cloud ``pointclouds/<name>.ply`` through ``camera_fn(w, h).unproject``, in the gravity-aligned
    y-up frame (:mod:`omnidl.viz.ply`; tilted synthetic samples are levelled with their ``rotation``).
    ``claim(path)``: called with every path before it is written (the evaluation's
    :class:`~omnidl.utils.outputs.OutputClaims`: raises for an input, an older result or a second write)."""
    from omnidl.viz import depth_to_points, prediction_figure, to_uint8_bgr, write_ply
    depth, sem = outputs.get("depth"), outputs.get("semantic")
    depth = depth if isinstance(depth, torch.Tensor) else None
    sem = sem if isinstance(sem, torch.Tensor) else None
    if save_image:
        image = batch["image"][i].float().cpu()
        if (depth is not None or sem is not None) and image.shape[-2] >= MIN_FIGURE_HEIGHT:
            gt_d, gt_s = batch.get("depth"), batch.get("semantic")
            pic = prediction_figure(image, None if depth is None else depth[i], None if sem is None else sem[i],
                                    gt_d[i] if isinstance(gt_d, torch.Tensor) else None,
                                    gt_s[i] if isinstance(gt_s, torch.Tensor) else None, depth_max=depth_max)
        else:
            pic = viz(slice_sample(outputs, i), slice_sample(batch, i)) if viz is not None else None
        if pic is not None:
            atomic_imwrite(claim(out_dir / "images" / f"{name}.png"), to_uint8_bgr(pic))
        atomic_imwrite(claim(out_dir / "inputs" / f"{name}.jpg"), to_uint8_bgr(image))
        if depth is not None:
            mm = (depth[i, 0].float().cpu().clamp(0, 65.535) * 1000).round().numpy().astype(np.uint16)
            atomic_imwrite(claim(out_dir / "predictions" / f"{name}_depth.png"), mm)
        if sem is not None:
            lab = sem[i].argmax(0).cpu().numpy().astype(np.uint8)
            atomic_imwrite(claim(out_dir / "predictions" / f"{name}_semantic.png"), lab)
    if save_ply and depth is not None:
        d = depth[i].float().cpu()
        rot = batch.get("rotation")
        R = rot[i].double().cpu() if isinstance(rot, torch.Tensor) and rot.shape[-2:] == (3, 3) else None
        pts, cols = depth_to_points(d, camera_fn(d.shape[-1], d.shape[-2]), batch["image"][i].float().cpu(),
                                    frame="gravity_y_up", R_up_cam=R)
        write_ply(claim(out_dir / "pointclouds" / f"{name}.ply"), pts, cols, frame="gravity_y_up")


#: metrics in metres (one panel); the others are fractions or unitless ratios (another panel)
METRE_METRICS = ("mae", "rmse", "ce", "corner_error", "height_error", "rmse_m")


def write_rotation(out_dir: Path, rotation: dict[str, dict[str, float]]) -> None:
    """``rotation.csv`` (one row per angle) and ``rotation.png`` (each metric against the angle, one panel per
    unit: metres, then fractions / unitless ratios; legends beside the axes, not over the data)."""
    angles = sorted(rotation, key=float)
    keys = sorted({k for r in rotation.values() for k in r})
    atomic_write_csv(out_dir / "rotation.csv", [{"angle_deg": float(a), **rotation[a]} for a in angles])
    if not keys:
        return
    groups = [(f"{unit}", [k for k in keys if (k in METRE_METRICS) == metres])
              for unit, metres in (("metres", True), ("fraction / ratio", False))]
    groups = [(u, ks) for u, ks in groups if ks]
    import matplotlib
    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    from omnidl.utils.io import atomic_write
    x = [float(a) for a in angles]
    fig, axes = plt.subplots(len(groups), 1, figsize=(7.5, 3.2 * len(groups)), dpi=100, squeeze=False)
    try:
        for ax, (unit, ks) in zip(axes[:, 0], groups):
            for k in ks:
                ax.plot(x, [rotation[a].get(k, math.nan) for a in angles], marker="o", label=k)
            ax.set_ylabel(unit)
            ax.grid(True, alpha=0.3)
            ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
        axes[-1, 0].set_xlabel("rotation about a horizontal axis (deg)")
        axes[0, 0].set_title("evaluation under rotation")
        fig.tight_layout()
        atomic_write(out_dir / "rotation.png", lambda tmp: fig.savefig(tmp, format="png"))
    finally:
        plt.close(fig)
