"""A tiny timm-style model registry: ``@register_model`` + :func:`create_model` / :func:`list_models`."""
from __future__ import annotations

from typing import Any, Callable

import torch.nn as nn

_MODELS: dict[str, Callable[..., nn.Module]] = {}
_SMOKE: dict[str, dict[str, Any]] = {}


def register_model(fn: Callable[..., nn.Module] | None = None, *, name: str | None = None,
                   smoke_kwargs: dict[str, Any] | None = None, smoke_size: tuple[int, int] = (64, 128)):
    """Register a model factory under ``name`` (default: the function's name).

    ``smoke_kwargs``/``smoke_size`` give a small configuration and input ``(H, W)`` that the
    registry-wide tests (forward, backward, every parameter gets a gradient) use on CPU.
    """
    def deco(f):
        key = name or f.__name__
        if key in _MODELS and _MODELS[key] is not f:
            raise ValueError(f"model {key!r} is registered twice")
        _MODELS[key] = f
        _SMOKE[key] = {"kwargs": dict(smoke_kwargs or {}), "size": tuple(smoke_size)}
        return f
    return deco(fn) if fn is not None else deco


def smoke_config(name: str) -> dict[str, Any]:
    """``{"kwargs": ..., "size": (H, W)}``: the small test configuration of a registered model."""
    _import_all()
    return _SMOKE[name]


def _import_all() -> None:
    import omnidl.models  # noqa: F401  (its __init__ imports every model module)


def list_models() -> list[str]:
    """Names of every registered model."""
    _import_all()
    return sorted(_MODELS)


def create_model(name: str, **kwargs: Any) -> nn.Module:
    """Build a registered model: ``create_model("fredsnet", width=0.25)``.

    ``kwargs`` go to the model factory; Hydra's ``_target_`` and ``_partial_`` keys are dropped.
    """
    _import_all()
    if name not in _MODELS:
        raise KeyError(f"unknown model {name!r}; registered models: {sorted(_MODELS)}")
    kwargs = {k: v for k, v in kwargs.items() if not k.startswith("_")}
    return _MODELS[name](**kwargs)
