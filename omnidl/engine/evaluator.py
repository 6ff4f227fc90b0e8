"""Evaluation: :func:`evaluate` (``python evaluate.py model=... checkpoint=...``).

Writes into ``<output_dir>``:

* ``metrics.json`` — mean metrics over the dataset (as the metrics object accumulates them), the number of
  images, the checkpoint, and with ``eval.rotation_deg`` the metrics per rotation angle;
* ``per_image.csv`` / ``per_image.json`` — one record per image (metrics of that image alone, hook scalars);
* ``images/<stem>.png`` — full-resolution titled panels ``input | depth | depth GT | semantics | semantics GT``
  with a depth colour bar (m) and a class legend; ``inputs/<stem>.jpg`` — the network input;
* ``predictions/<stem>_depth.png`` (16-bit, millimetres) and ``<stem>_semantic.png`` (class ids);
* ``pointclouds/<stem>.ply`` — coloured points from the predicted depth through the camera's ``unproject``,
  gravity-aligned y-up frame;
* ``rotation.csv`` and ``rotation.png`` — metrics against the rotation angle (with ``eval.rotation_deg``);
* ``postprocess.jsonl`` — the non-scalar results of the ``postprocess`` hooks per batch.

``<stem>`` is the sample's name made file-name safe and unique (:class:`~omnidl.engine.eval_outputs.OutputNames`);
``per_image.csv`` has both (``name``, ``output``). ``evaluate.py`` then adds ``report.html``
(:mod:`omnidl.apps.html_report`).

The configured ``postprocess`` hooks run on every batch before the metrics see it, and their results are
merged into the outputs (:mod:`omnidl.engine.hooks`; validation during training does the same).
Datasets without labels (``data=folder``) only get predictions, pictures and point clouds.
"""
from __future__ import annotations

import copy
import inspect
import logging
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf, open_dict
from torch.utils.data import DataLoader

from omnidl.data.collate import collate_samples
from omnidl.data.robust import SkipCorrupt
from omnidl.utils.io import atomic_write_csv, atomic_write_json
from omnidl.utils.outputs import OutputClaims, RunLock, is_within

from .build import build_camera, build_dataset, build_metrics, build_model, build_viz, output_dir, pick_device
from .checkpoint import load_checkpoint, load_model_weights
from .config import check_finite_config
from .eval_outputs import (OutputNames, append_hook_results, printable, sample_name, sample_source, save_pictures,
                           scalars, slice_sample, write_rotation)
from .forward import forward, to_device
from .hooks import ConfiguredHooks
from .run_dir import check_evaluation_dir, evaluation_dir, overwrite_of
from .seed import seed_everything

log = logging.getLogger("omnidl.engine")


@torch.no_grad()
def evaluate(cfg: DictConfig) -> dict[str, Any]:
    """Evaluate ``cfg.checkpoint`` (or, with a warning, the untrained model) on ``cfg.data[cfg.eval.split]``.

    Returns the dict written to ``metrics.json``: ``{"metrics": {...}, "num_images", "checkpoint",
    "rotation": {angle: {...}} (when asked), "output_dir", "wall_time_s"}``.
    """
    t0 = time.time()
    check_finite_config(cfg)
    out_dir = evaluation_dir(cfg, output_dir(cfg))  # a training run's folder (even a running one): eval_<ckpt>_<split>/
    with RunLock(out_dir, "evaluation"):
        check_evaluation_dir(cfg, out_dir)          # (under the lock: a concurrent evaluation has finished or failed)
        return _evaluate(cfg, out_dir, t0)


def _evaluate(cfg: DictConfig, out_dir: Path, t0: float) -> dict[str, Any]:
    """:func:`evaluate` once its folder is chosen and locked."""
    ec, tc = cfg.eval, cfg.trainer
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "postprocess.jsonl").unlink(missing_ok=True)  # appended per batch below (old: trainer.overwrite)
    seed_everything(int(tc.seed), tc.num_threads, False)  # trainer.num_threads: auto | 0 | N, as in training
    device = pick_device(str(tc.device))
    cfg, model, ckpt_path = _model_from_checkpoint(cfg, device)
    run = _Evaluation(cfg, out_dir, device, model, _loader(cfg), build_metrics(cfg), build_viz(cfg),
                      ConfiguredHooks.from_config(cfg), claims=_claims(cfg, out_dir, ckpt_path))
    angles = [float(a) for a in ec.rotation_deg] or [None]
    if 0.0 not in angles and angles != [None]:
        angles = [None] + angles  # pictures/per-image records always come from the unrotated images
    rotation: dict[str, dict[str, float]] = {}
    mean: dict[str, float] = {}
    for angle in angles:
        base = angle is None or (angle == 0.0 and None not in angles)
        result = run.one_pass(angle, base)
        if base:
            mean = result
        if angle is not None:
            rotation[f"{angle:g}"] = result
    summary: dict[str, Any] = {"metrics": mean, "num_images": len(run.records), "checkpoint": ckpt_path,
                               "split": str(ec.split), "output_dir": str(out_dir)}
    if rotation:
        summary["rotation"] = rotation
        write_rotation(out_dir, rotation)
    summary["wall_time_s"] = time.time() - t0
    if run.records:
        atomic_write_csv(out_dir / "per_image.csv", run.records)
        atomic_write_json(out_dir / "per_image.json", run.records)
    atomic_write_json(out_dir / "metrics.json", summary)
    text = "\n".join(f"  {k:>12s}: {v:.4f}" for k, v in mean.items()) or "  (no labels: predictions only)"
    print(f"evaluated {len(run.records)} images ({ckpt_path or 'untrained model'}):\n{text}\noutputs in {out_dir}")
    return summary


@dataclass
class _Evaluation:
    """The state of one evaluation: model, loader, metrics (dataset and per-image), hooks, records so far."""

    cfg: DictConfig
    out_dir: Path
    device: torch.device
    model: torch.nn.Module
    loader: DataLoader
    metrics: Any
    viz: Any
    hooks: ConfiguredHooks
    records: list[dict[str, Any]] = field(default_factory=list)
    cameras: dict[tuple[int, int], Any] = field(default_factory=dict)
    stems: OutputNames = field(default_factory=OutputNames)
    claims: OutputClaims = field(default_factory=OutputClaims)   # no picture replaces an input or older result

    def __post_init__(self):
        self.has_labels = self.metrics is not None
        self.per_image_metrics = copy.deepcopy(self.metrics) if self.metrics is not None else None

    def camera(self, w: int, h: int):
        """The configured camera at a ``w x h`` output size (cached). A size that is not the calibrated image
        uniformly resized (nor covered by a ``size_policy`` the camera config states) is a ``ValueError``
        naming both sizes: point clouds are never made through a stretched camera."""
        if (w, h) not in self.cameras:
            from omnidl.cameras import check_image_size
            cam = build_camera(self.cfg, w, h)
            base = getattr(cam, "base", None)
            node = self.cfg.get("camera")
            if base is not None and not (node.get("size_policy") if hasattr(node, "get") else None):
                check_image_size((h, w), base, "evaluated output")
            self.cameras[(w, h)] = cam
        return self.cameras[(w, h)]

    def one_pass(self, angle: float | None, base: bool) -> dict[str, float]:
        """Metrics over the dataset rotated by ``angle`` degrees (None/0: as is); the ``base`` pass also
        writes per-image records, pictures and hook results."""
        ec, tc = self.cfg.eval, self.cfg.trainer
        R = None
        if angle is not None and angle != 0.0:
            from omnidl.data.transforms import horizontal_rotation
            R = horizontal_rotation(angle, str(ec.rotation_axis))
        if self.metrics is not None:
            self.metrics.reset()
        seen = 0
        from tqdm.auto import tqdm
        desc = "evaluate" if angle is None else f"evaluate @ {angle:g} deg"
        for batch in tqdm(self.loader, desc=desc, disable=not bool(tc.progress), dynamic_ncols=True):
            if batch is None:
                continue
            if R is not None:
                batch = _rotate_batch(batch, R)
            batch = to_device(batch, self.device)
            outputs = forward(self.model, batch, self.device, bool(tc.amp))
            _clamp_depth(outputs, batch, ec.depth_max)
            merged, hook_res = outputs, {}
            if self.hooks and (base or self.has_labels):
                merged, hook_res = self.hooks.run(outputs, batch, exports=base)
            if self.has_labels:
                try:
                    self.metrics.update(merged, batch)
                except KeyError as e:
                    log.info("the dataset has no labels for the metrics (%s): writing predictions only", e)
                    self.has_labels = False
            if base:
                self._per_image(batch, outputs, merged, hook_res, seen)
            seen += batch["image"].shape[0]
        return {k: float(v) for k, v in self.metrics.compute().items()} if self.has_labels else {}

    def _per_image(self, batch: dict, outputs: dict, merged: dict, hook_res: dict, seen: int) -> None:
        """Records (per-image metrics + hook scalars), hook results and pictures of one batch."""
        ec = self.cfg.eval
        n = batch["image"].shape[0]
        names = [printable(sample_name(batch, i, seen + i)) for i in range(n)]
        stems = [self.stems(sample_name(batch, i, seen + i), sample_source(batch, i)) for i in range(n)]
        if self.hooks:
            append_hook_results(self.out_dir / "postprocess.jsonl", stems, hook_res)
        n_img, n_ply = int(ec.save_images), int(ec.save_pointclouds)
        for i in range(n):
            idx = seen + i
            rec: dict[str, Any] = {"index": idx, "name": names[i], "output": stems[i]}
            if self.has_labels:
                self.per_image_metrics.reset()
                self.per_image_metrics.update(slice_sample(merged, i), slice_sample(batch, i))
                rec.update(scalars(self.per_image_metrics.compute()))
            rec.update(scalars(hook_res))
            self.records.append(rec)
            save_img = n_img < 0 or idx < n_img
            save_ply = n_ply < 0 or idx < n_ply
            if save_img or save_ply:
                save_pictures(self.out_dir, stems[i], outputs, batch, i, self.viz, self.camera, save_img, save_ply,
                              ec.depth_max, claim=self.claims.claim)


def _model_from_checkpoint(cfg: DictConfig, device: torch.device) -> tuple[DictConfig, torch.nn.Module, str | None]:
    """``(cfg, model in eval mode with the checkpoint's weights, checkpoint path)``; the config is completed
    from the checkpoint's training config when no model was chosen."""
    ckpt_path = cfg.get("checkpoint")
    ckpt = load_checkpoint(ckpt_path, map_location=device) if ckpt_path else None
    if ckpt is not None:
        cfg = _fill_from_checkpoint(cfg, ckpt)
        cfg = _size_from_checkpoint(cfg, ckpt)
        with _quiet_initialisation():  # "random initialisation" is about to be overwritten by the checkpoint
            model = build_model(cfg).to(device).eval()
        load_model_weights(model, ckpt, ckpt_path)
        log.info("weights: %s", describe_checkpoint(ckpt_path, ckpt))
    else:
        model = build_model(cfg).to(device).eval()
        log.warning("no checkpoint given (checkpoint=PATH): evaluating the randomly initialised model")
    return cfg, _through_views(cfg, model), ckpt_path


def _through_views(cfg: DictConfig, model: torch.nn.Module) -> torch.nn.Module:
    """``model`` as it is, or, when the data config has ``through_views: {layout, size, fov, align, assumed_range,
    ...}`` (the options of :class:`omnidl.geometry.views.ThroughViews`, plus ``split``: the split of whole images,
    default ``test``) and that split is evaluated, ``model`` (its weights loaded) wrapped in ``ThroughViews`` on the
    configured camera (``camera=...``, resized to the images): a perspective depth network trained on views, run on
    whole images through the view chain. Training never wraps (validation stays on the views)."""
    data = cfg.get("data")
    node = data.get("through_views") if isinstance(data, DictConfig) else None
    if node is None:
        return model
    from omnidl.geometry.views import ThroughViews
    opts = OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig) else node
    allowed = [k for k in inspect.signature(ThroughViews).parameters if k not in ("net", "camera")] + ["split"]
    if not isinstance(opts, dict) or set(opts) - set(allowed):
        bad = sorted(set(opts) - set(allowed)) if isinstance(opts, dict) else opts
        raise ValueError(f"data.through_views: expected null or a mapping with some of the keys {allowed}, got "
                         f"{'the unknown key(s) ' if isinstance(opts, dict) else ''}{bad!r}")
    split = str(opts.pop("split", "test"))
    if str(cfg.eval.split) != split:
        log.info("data.through_views is for the %s split: evaluating the %s split with the model as it is", split,
                 cfg.eval.split)
        return model
    node = cfg.get("camera")
    if node is None or (isinstance(node, DictConfig) and len(node) == 0):
        raise ValueError("data.through_views needs the camera of the whole images: choose camera=<name>")
    wrapped = ThroughViews(model, build_camera(cfg), **opts).eval()
    log.info("data.through_views: evaluating the %s split's whole images through the view chain (%s camera, %d %s "
             "views of %d px, align %s; omnidl.geometry.views.ThroughViews)", split, type(wrapped.camera).__name__,
             len(wrapped.views), wrapped.layout, wrapped.size, wrapped.align)
    return wrapped


def _claims(cfg: DictConfig, out_dir: Path, ckpt_path: str | None) -> OutputClaims:
    """The per-file output check of the pictures: never the checkpoint or a file already in the data folder
    (``data.root``), never an existing file without ``trainer.overwrite=true``."""
    data = cfg.get("data") or {}
    root = data.get("root") if hasattr(data, "get") else None
    if root and out_dir != Path(root) and is_within(out_dir, root):
        root = None   # an evaluation folder inside the data folder: the files in it are its own, not data
    inputs = [p for p in (ckpt_path, root) if p]
    return OutputClaims(inputs, overwrite_of(cfg), option="trainer.overwrite=true")


def _loader(cfg: DictConfig) -> DataLoader:
    """The evaluation split (at most ``eval.max_images`` images), in order."""
    ec = cfg.eval
    dataset = SkipCorrupt(build_dataset(cfg, str(ec.split)))
    n_total = len(dataset) if ec.max_images is None else min(len(dataset), int(ec.max_images))
    if n_total < len(dataset):
        dataset = torch.utils.data.Subset(dataset, range(n_total))
    return DataLoader(dataset, batch_size=int(ec.batch_size), shuffle=False, num_workers=int(cfg.trainer.num_workers),
                      collate_fn=collate_samples)


def _clamp_depth(outputs: dict, batch: dict, depth_max: float | None) -> None:
    """Clamp predicted depth to ``[0, depth_max]`` and drop ground truth beyond it (in place)."""
    if depth_max is None:
        return
    if isinstance(outputs.get("depth"), torch.Tensor):
        outputs["depth"] = outputs["depth"].clamp(0, depth_max)
    if isinstance(batch.get("depth"), torch.Tensor):
        d = batch["depth"]
        batch["depth"] = torch.where(d > depth_max, torch.zeros_like(d), d)


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


def describe_checkpoint(path: str, ckpt: dict[str, Any]) -> str:
    """One line saying which weights were loaded: the file, its training step and monitored best, the model."""
    saved = ckpt.get("config") if isinstance(ckpt.get("config"), dict) else {}
    model = (saved.get("model") or {}).get("name") if isinstance(saved.get("model"), dict) else None
    parts = [f"step {int(ckpt['step'])}" if isinstance(ckpt.get("step"), int) else "a bare state dict",
             f"model {model}" if model else None,
             f"best {float(ckpt['best']):.4g}" if isinstance(ckpt.get("best"), (int, float)) else None]
    n = sum(int(v.numel()) for v in ckpt["model"].values() if isinstance(v, torch.Tensor))
    return f"loaded all weights from {path} ({', '.join(p for p in parts if p)}; {n:,} values)"


class _DropInitialisationNotes(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return "random initialisation" not in record.getMessage()


@contextmanager
def _quiet_initialisation():
    """Drop the models' "random initialisation" notes while building a model a checkpoint then fills."""
    filt, logger = _DropInitialisationNotes(), logging.getLogger("omnidl.models._backbone")
    logger.addFilter(filt)
    try:
        yield
    finally:
        logger.removeFilter(filt)


def _size_from_checkpoint(cfg: DictConfig, ckpt: dict[str, Any]) -> DictConfig:
    """A data config that leaves its size open (``data=folder``: ``height``/``width`` null) gets the size the
    checkpoint was trained at (its stored ``data.height``/``data.width``)."""
    data, saved = cfg.get("data"), ckpt.get("config")
    if data is None or not isinstance(saved, dict) or not isinstance(saved.get("data"), dict):
        return cfg
    keys = [k for k in ("height", "width") if k in data and data.get(k) is None and saved["data"].get(k)]
    if not keys:
        return cfg
    cfg = copy.deepcopy(cfg)
    with open_dict(cfg):
        for k in keys:
            cfg.data[k] = int(saved["data"][k])
    log.info("input size %sx%s: the checkpoint's training size (set data.height/data.width to change it)",
             cfg.data.get("width"), cfg.data.get("height"))
    return cfg


def _rotate_batch(batch: dict[str, Any], R: torch.Tensor) -> dict[str, Any]:
    from omnidl.data.transforms import rotate_tensors
    return rotate_tensors(batch, R, batched=True, drop_unknown=True)
