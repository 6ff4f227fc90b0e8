"""Name -> camera class registry and :func:`build`."""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

_CAMERAS: dict[str, type] = {}


def register_camera(name: str, cls: type) -> type:
    """Register ``cls`` (a :class:`~omnidl.cameras.base.Camera` subclass) under ``name``."""
    if name in _CAMERAS and _CAMERAS[name] is not cls:
        raise ValueError(f"camera model {name!r} is registered twice")
    cls.name = name
    _CAMERAS[name] = cls
    return cls


def list_cameras() -> list[str]:
    """Names of every registered camera model."""
    import omnidl.cameras  # noqa: F401  (imports every model module)
    return sorted(_CAMERAS)


def get_camera_class(name: str) -> type:
    import omnidl.cameras  # noqa: F401
    if name not in _CAMERAS:
        raise KeyError(f"unknown camera type {name!r}; known: {sorted(_CAMERAS)}")
    return _CAMERAS[name]


def build(cfg: Mapping[str, Any] | None = None, **kwargs: Any):
    """Build a camera from a config mapping (or keyword arguments).

    The mapping needs ``type`` (a registered name, see :func:`list_cameras`) and the
    model's fields (``width``, ``height``, ...). A model may also accept
    ``calib_file`` (see the model's ``from_config``). Hydra's ``_target_`` key, if
    present, is ignored, so ``hydra.utils.instantiate`` and ``build`` take the same
    YAML. Unknown fields raise a ``ValueError`` naming them.
    """
    params: dict[str, Any] = {}
    if cfg is not None:
        try:
            from omegaconf import DictConfig, OmegaConf
            if isinstance(cfg, DictConfig):
                cfg = OmegaConf.to_container(cfg, resolve=True)
        except ImportError:  # pragma: no cover
            pass
        params.update(cfg)
    params.update(kwargs)
    params.pop("_target_", None)
    params = {k: _plain(v) for k, v in params.items()}
    if "type" not in params:
        raise ValueError(f"camera config needs a 'type' field (one of {list_cameras()}); got keys {sorted(params)}")
    cls = get_camera_class(params.pop("type"))
    if hasattr(cls, "from_config"):
        return cls.from_config(params)
    return construct(cls, params)


def _plain(value: Any) -> Any:
    """OmegaConf containers (e.g. lists passed by ``hydra.utils.instantiate``) -> plain Python objects."""
    try:
        from omegaconf import OmegaConf
        if OmegaConf.is_config(value):
            return OmegaConf.to_container(value, resolve=True)
    except ImportError:  # pragma: no cover
        pass
    return value


def construct(cls: type, params: Mapping[str, Any]):
    """``cls(**params)`` with lists turned into tuples and a clear error on unknown fields."""
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(params) - names)
    if unknown:
        raise ValueError(f"camera type {cls.name!r}: unknown field(s) {unknown}; expected some of {sorted(names)}")
    clean = {k: tuple(v) if isinstance(v, list) else v for k, v in params.items()}
    return cls(**clean)
