"""Checkpoints: one dict with everything needed for exact resume, written atomically.

Layout of a checkpoint (``torch.save`` dict):
``model`` (state dict of the unwrapped model), ``optimizer``, ``scheduler``, ``scaler`` (or None),
``rng`` (:func:`omnidl.engine.seed.rng_state`), ``step`` (optimiser steps done), ``epoch`` (current epoch),
``batch_in_epoch`` (batches of ``epoch`` already consumed: the sampler position), ``best`` (monitored value),
``bad_validations`` (early-stopping counter), ``config`` (the resolved config as a plain dict), ``version``.
``best.pt`` is weights-only by default: ``model`` and the position/best entries, without ``optimizer``,
``scheduler``, ``scaler`` and ``rng`` (``trainer.save_optimizer=true`` keeps them).

Checkpoints are read with ``torch.load(weights_only=True)``: a ``.pt`` file can hold only tensors, numbers,
strings and containers of them (plus the NumPy RNG arrays of older omnidl checkpoints), never code, so a
checkpoint downloaded from the internet cannot run anything when loaded.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from omnidl.utils.io import atomic_torch_save, safe_torch_load

CHECKPOINT_VERSION = 1


def save_checkpoint(path: str | Path, state: dict[str, Any]) -> Path:
    """Write ``state`` atomically (temp file + rename): a kill never leaves a half-written file."""
    state = dict(state, version=CHECKPOINT_VERSION)
    return atomic_torch_save(path, state)


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Read a checkpoint written by :func:`save_checkpoint` (or a bare state dict, returned as ``{"model": sd}``)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    obj = safe_torch_load(path, map_location)
    if not isinstance(obj, dict):
        raise RuntimeError(f"checkpoint {path}: expected a dict, got {type(obj).__name__}")
    if not obj:
        raise RuntimeError(f"checkpoint {path}: an empty dict, expected a 'model' state dict")
    if "model" not in obj:
        if "state_dict" in obj and isinstance(obj["state_dict"], dict):
            return {"model": obj["state_dict"]}
        if all(isinstance(v, torch.Tensor) for v in obj.values()):
            return {"model": obj}
        raise RuntimeError(f"checkpoint {path}: no 'model' entry (keys found: {_keys(obj)}); expected a checkpoint of "
                           "train.py ({'model': state dict, ...}), {'state_dict': state dict} or a bare state dict")
    if "optimizer" in obj:
        missing = [k for k in RESUME_LAYOUT if k not in obj]
        if missing:
            raise RuntimeError(f"checkpoint {path}: has an 'optimizer' but not the rest of an omnidl resume state "
                               f"(missing {missing}; keys found: {_keys(obj)}); it is another program's checkpoint. "
                               "Keep only its weights ({'model': state dict}) to start from them")
    return obj


#: what a checkpoint with an optimiser state must also hold to be resumed (:func:`save_checkpoint`'s layout)
RESUME_LAYOUT = ("model", "scheduler", "step", "epoch", "batch_in_epoch")


def _keys(obj: dict) -> list:
    keys = sorted(map(str, obj))
    return keys[:12] + ([f"... {len(keys) - 12} more"] if len(keys) > 12 else [])


def model_config(ckpt: dict[str, Any], label: str, hint: str, default_name: str | None = None):
    """``(name, kwargs, config)`` of the model a ``train.py`` checkpoint was trained with: the registered model
    name, the ``create_model`` keyword arguments of ``config.model`` (``_target_`` dropped; ``pretrained`` and
    ``official_checkpoint`` set to ``None``, since the weights come from the checkpoint itself and those paths
    may not exist here) and the whole run config (an ``OmegaConf`` object). ``label`` names the file in errors
    (e.g. ``"--checkpoint ck.pt"``), ``hint`` says where such a checkpoint comes from."""
    from omegaconf import OmegaConf

    cfg = ckpt.get("config")
    if not cfg or "model" not in cfg:
        raise ValueError(f"{label}: no 'config' with a 'model' entry; {hint}")
    conf = OmegaConf.create(cfg)
    kwargs = OmegaConf.to_container(conf.model, resolve=True)
    kwargs.pop("_target_", None)
    name = kwargs.pop("name", default_name)
    if name is None:
        raise ValueError(f"{label}: config.model has no 'name' (a registered model name)")
    for k in ("pretrained", "official_checkpoint"):
        if k in kwargs:
            kwargs[k] = None
    return name, kwargs, conf


def load_model_weights(model: torch.nn.Module, ckpt: dict[str, Any], path: str | Path = "<checkpoint>",
                       strict: bool = True) -> None:
    """Load ``ckpt["model"]`` into ``model`` with an error that lists missing/unexpected keys."""
    if "model" not in ckpt:
        raise ValueError(f"checkpoint {path}: no 'model' entry (the network's weights); it holds "
                       f"{sorted(map(str, ckpt))}. A checkpoint of `python train.py` has 'model', 'config', 'step'")
    sd = ckpt["model"]
    if not isinstance(sd, dict) or not all(isinstance(k, str) for k in sd):
        raise RuntimeError(f"checkpoint {path}: 'model' is a {type(sd).__name__}, expected a state dict "
                           "(parameter name -> tensor)")
    if any(k.startswith("module.") for k in sd):
        sd = {k.removeprefix("module."): v for k, v in sd.items()}
    try:
        missing, unexpected = model.load_state_dict(sd, strict=False)
    except RuntimeError as e:  # shape mismatches
        raise RuntimeError(f"checkpoint {path} does not fit the model ({type(model).__name__}): {e}; was it trained "
                           "with another model config?") from e
    if strict and (missing or unexpected):
        raise RuntimeError(f"checkpoint {path} does not fit the model ({type(model).__name__}): "
                           f"missing keys {missing[:8]}{'...' if len(missing) > 8 else ''}, "
                           f"unexpected keys {unexpected[:8]}{'...' if len(unexpected) > 8 else ''}; "
                           "was it trained with another model config?")
