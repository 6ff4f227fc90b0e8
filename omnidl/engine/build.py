"""Turn config nodes into objects: model, datasets, loss, metrics, visualiser, camera, device."""
from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Any

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, ListConfig, OmegaConf

log = logging.getLogger("omnidl.engine")

#: dataset entries a data config may define; ``train`` is required for training, ``test`` (or ``val``) for evaluation
SPLITS = ("train", "val", "test", "predict")


def _is_empty(node: Any) -> bool:
    return node is None or (isinstance(node, (DictConfig, Mapping)) and len(node) == 0)


def output_dir(cfg: DictConfig) -> str:
    """``cfg.paths.output_dir`` resolved (the Hydra run dir by default), with a clear error outside Hydra."""
    try:
        out = cfg.paths.output_dir
    except Exception as e:
        raise ValueError("paths.output_dir could not be resolved (it defaults to the Hydra run dir, which only "
                         "exists under @hydra.main); set paths.output_dir=<folder> when composing configs "
                         f"yourself ({e})") from e
    if not out:
        raise ValueError("paths.output_dir is empty; set paths.output_dir=<folder>")
    return str(out)


def pick_device(name: str, local_rank: int = 0) -> torch.device:
    """``auto`` -> ``cuda:<local_rank>`` when CUDA is available, else ``cpu``."""
    if name == "auto":
        return torch.device(f"cuda:{local_rank}") if torch.cuda.is_available() else torch.device("cpu")
    dev = torch.device(name)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"trainer.device={name!r} but CUDA is not available; use trainer.device=cpu or auto")
    if dev.type == "cuda" and dev.index is None:
        dev = torch.device(f"cuda:{local_rank}")
    return dev


def build_model(cfg: DictConfig) -> torch.nn.Module:
    """Instantiate ``cfg.model`` (``_target_: omnidl.models.create_model`` + ``name`` + kwargs)."""
    if _is_empty(cfg.get("model")):
        try:
            from omnidl.models import list_models
            names = list_models()
        except Exception:  # pragma: no cover
            names = []
        raise ValueError(f"no model selected: run with model=<name> (configs/model/<name>.yaml; registered models: "
                         f"{names})")
    model = instantiate(cfg.model, _convert_="all")
    if not isinstance(model, torch.nn.Module):
        raise TypeError(f"config 'model' built a {type(model).__name__}, expected a torch.nn.Module")
    return model


def build_dataset(cfg: DictConfig, split: str, required: bool = True):
    """Instantiate ``cfg.data.<split>`` (a ``_target_`` node giving a map-style dataset of sample dicts)."""
    data = cfg.get("data")
    if _is_empty(data):
        raise ValueError("no dataset selected: choose data=<name> (configs/data/) or a model config that sets it")
    node = data.get(split)
    if _is_empty(node):
        if required:
            raise ValueError(f"data config has no '{split}' dataset; it defines {[s for s in SPLITS if s in data]}")
        return None
    ds = instantiate(node, _convert_="all")
    if not hasattr(ds, "__len__") or not hasattr(ds, "__getitem__"):
        raise TypeError(f"data.{split} built a {type(ds).__name__}, expected a map-style dataset")
    if len(ds) == 0:
        raise ValueError(f"data.{split} ({type(ds).__name__}) is empty")
    return ds


def build_loss(cfg: DictConfig):
    """Instantiate ``cfg.loss``: ``loss(outputs, batch) -> (total, terms)``; None when not configured."""
    if _is_empty(cfg.get("loss")):
        return None
    return instantiate(cfg.loss, _convert_="all")


class MetricCollection:
    """Several metric objects behind the one metrics interface; their result dicts are merged."""

    def __init__(self, metrics: Mapping[str, Any]):
        self.metrics = dict(metrics)

    def reset(self) -> None:
        for m in self.metrics.values():
            m.reset()

    def update(self, outputs, batch) -> None:
        for m in self.metrics.values():
            m.update(outputs, batch)

    def compute(self) -> dict[str, float]:
        out: dict[str, float] = {}
        for m in self.metrics.values():
            out.update(m.compute())
        return out


def build_metrics(cfg: DictConfig):
    """``cfg.metrics`` is one ``_target_`` node or a mapping name -> ``_target_`` node; None when not set."""
    node = cfg.get("metrics")
    if _is_empty(node):
        return None
    if "_target_" in node:
        return instantiate(node, _convert_="all")
    return MetricCollection({k: instantiate(v, _convert_="all") for k, v in node.items() if not _is_empty(v)})


def build_viz(cfg: DictConfig):
    """``cfg.viz``: ``viz(outputs, batch) -> (3, h, w)`` image in [0, 1]; None when ``_target_`` is null."""
    node = cfg.get("viz")
    if _is_empty(node) or node.get("_target_") is None:
        return None
    return instantiate(node, _convert_="all")


def build_camera(cfg: DictConfig, width: int | None = None, height: int | None = None):
    """The configured camera (:func:`omnidl.cameras.resolve_camera`, resized to ``width x height``), else a full
    equirectangular camera of the image size."""
    from omnidl.cameras import Equirectangular, resolve_camera
    node = cfg.get("camera")
    if not _is_empty(node):
        return resolve_camera(node, width, height)
    if width is None:
        raise ValueError("no camera configured and no image size to default to")
    return Equirectangular(width=width, height=height)


def to_plain(node: Any) -> Any:
    if isinstance(node, (DictConfig, ListConfig)):
        return OmegaConf.to_container(node, resolve=True)
    return node
