"""Checkpoints: one dict with everything needed for exact resume, written atomically.

Layout of a checkpoint (``torch.save`` dict):
``model`` (state dict of the unwrapped model), ``optimizer``, ``scheduler``, ``scaler`` (or None),
``rng`` (:func:`omnidl.engine.seed.rng_state`), ``step`` (optimiser steps done), ``epoch`` (current epoch),
``batch_in_epoch`` (batches of ``epoch`` already consumed: the sampler position), ``best`` (monitored value),
``bad_validations`` (early-stopping counter), ``config`` (the resolved config as a plain dict), ``version``.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from omnidl.utils.io import atomic_torch_save

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
    try:
        obj = torch.load(path, map_location=map_location, weights_only=False)
    except Exception as e:  # truncated or not a torch file
        raise RuntimeError(f"could not read checkpoint {path}: {e}") from e
    if not isinstance(obj, dict):
        raise RuntimeError(f"checkpoint {path}: expected a dict, got {type(obj).__name__}")
    if "model" not in obj:
        if "state_dict" in obj and isinstance(obj["state_dict"], dict):
            return {"model": obj["state_dict"]}
        if all(isinstance(v, torch.Tensor) for v in obj.values()):
            return {"model": obj}
        raise RuntimeError(f"checkpoint {path}: no 'model' entry (keys: {sorted(obj)[:10]})")
    return obj


def load_model_weights(model: torch.nn.Module, ckpt: dict[str, Any], path: str | Path = "<checkpoint>",
                       strict: bool = True) -> None:
    """Load ``ckpt["model"]`` into ``model`` with an error that lists missing/unexpected keys."""
    sd = ckpt["model"]
    if any(k.startswith("module.") for k in sd):
        sd = {k.removeprefix("module."): v for k, v in sd.items()}
    missing, unexpected = model.load_state_dict(sd, strict=False)
    if strict and (missing or unexpected):
        raise RuntimeError(f"checkpoint {path} does not fit the model ({type(model).__name__}): "
                           f"missing keys {missing[:8]}{'...' if len(missing) > 8 else ''}, "
                           f"unexpected keys {unexpected[:8]}{'...' if len(unexpected) > 8 else ''}; "
                           "was it trained with another model config?")
