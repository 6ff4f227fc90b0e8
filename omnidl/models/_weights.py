"""Load a model's weights from a local file (``model.pretrained=PATH`` options of the models).

Accepted files (``torch.load``; nothing is downloaded): an omnidl training checkpoint
(``{"model": state_dict, ...}``, :mod:`omnidl.engine.checkpoint`), ``{"state_dict": state_dict}`` or a
bare state dict. ``module.`` prefixes (DistributedDataParallel) are stripped. Files are read with
``weights_only=True`` (:func:`omnidl.utils.io.safe_torch_load`): a file holding pickled code is refused, never run.
"""
from __future__ import annotations

import os
from collections.abc import Mapping

from torch import Tensor, nn


def read_state_dict(path: str | os.PathLike) -> dict[str, Tensor]:
    """The model state dict stored in ``path`` (see the module docstring), with clear errors naming the file."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"weights file {path!r} does not exist")
    from omnidl.utils.io import safe_torch_load
    obj = safe_torch_load(path)           # RuntimeError naming the file: truncated, not torch, or pickled code
    if isinstance(obj, dict) and isinstance(obj.get("model"), dict):
        sd = obj["model"]
    elif isinstance(obj, dict) and isinstance(obj.get("state_dict"), dict):
        sd = obj["state_dict"]
    elif isinstance(obj, dict) and obj and all(isinstance(v, Tensor) for v in obj.values()):
        sd = obj
    else:
        raise RuntimeError(f"weights file {path!r}: expected a checkpoint with 'model' or 'state_dict', or a bare "
                           f"state dict; got {type(obj).__name__}")
    return {k.removeprefix("module."): v for k, v in sd.items()}


def load_strict(module: nn.Module, sd: Mapping[str, Tensor], what: str) -> None:
    """``module.load_state_dict(sd, strict=True)`` after a check whose ``ValueError`` names ``what``, the missing
    and unexpected keys and the tensors of the wrong shape (a few of each)."""
    own = module.state_dict()
    missing = [k for k in own if k not in sd]
    unexpected = [k for k in sd if k not in own]
    wrong = [f"{k}: {tuple(sd[k].shape)} vs {tuple(v.shape)}" for k, v in own.items()
             if k in sd and tuple(sd[k].shape) != tuple(v.shape)]
    if missing or unexpected or wrong:
        raise ValueError(f"{what} does not fit {type(module).__name__}: "
                         f"missing {missing[:8]}{'...' if len(missing) > 8 else ''}, "
                         f"unexpected {unexpected[:8]}{'...' if len(unexpected) > 8 else ''}, "
                         f"wrong shapes {wrong[:4]}{'...' if len(wrong) > 4 else ''}")
    module.load_state_dict(dict(sd), strict=True)


def load_weights(model: nn.Module, path: str | os.PathLike, strict: bool = True) -> None:
    """Load the weights of ``path`` into ``model``; with ``strict`` an error lists missing/unexpected keys
    (a shape mismatch is ``load_state_dict``'s own ``size mismatch`` error)."""
    missing, unexpected = model.load_state_dict(read_state_dict(path), strict=False)
    if strict and (missing or unexpected):
        raise RuntimeError(f"weights {os.fspath(path)!r} do not fit the model ({type(model).__name__}): "
                           f"missing keys {missing[:8]}{'...' if len(missing) > 8 else ''}, "
                           f"unexpected keys {unexpected[:8]}{'...' if len(unexpected) > 8 else ''}; "
                           "were they trained with another model config?")
