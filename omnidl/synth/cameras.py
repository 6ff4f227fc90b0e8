"""Turn a camera spec (object, config mapping, registry/config name, yaml path) into a ``Camera``."""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import omnidl
from omnidl.cameras import Camera, build, list_cameras

#: ``configs/camera`` of the source tree (next to the package)
CAMERA_CONFIG_DIR = Path(omnidl.__file__).resolve().parents[1] / "configs" / "camera"


def _load_yaml(path: Path) -> dict:
    from omegaconf import OmegaConf
    try:
        cfg = OmegaConf.to_container(OmegaConf.load(path), resolve=True)
    except Exception as exc:  # noqa: BLE001
        raise ValueError(f"camera config {path}: cannot read it as YAML ({exc})") from exc
    if not isinstance(cfg, dict) or "type" not in cfg:
        raise ValueError(f"camera config {path}: expected a mapping with a 'type' field (one of {list_cameras()})")
    return cfg


def resolve_camera(spec: Any, width: int | None = None, height: int | None = None, **fields: Any) -> Camera:
    """A :class:`Camera` from ``spec``.

    ``spec`` may be a ``Camera``, a config mapping (``{"type": ..., ...}``), a path to a YAML file, a
    name of ``configs/camera/<name>.yaml`` or a registered camera type (then ``width``/``height`` and
    ``fields`` give its parameters). With ``width``/``height`` a configured camera is resized to that
    image size (same optics, :meth:`Camera.resized`).
    """
    if isinstance(spec, Camera):
        cam = spec
    elif isinstance(spec, Mapping) or hasattr(spec, "items"):
        cam = build(dict(spec), **fields)
    elif isinstance(spec, (str, Path)):
        text = str(spec)
        path = Path(text)
        if path.suffix in (".yaml", ".yml") and path.exists():
            cam = build(_load_yaml(path), **fields)
        elif (CAMERA_CONFIG_DIR / f"{text}.yaml").exists():
            cam = build(_load_yaml(CAMERA_CONFIG_DIR / f"{text}.yaml"), **fields)
        elif text in list_cameras():
            if width is None or height is None:
                raise ValueError(f"camera type {text!r} needs width and height")
            return build({"type": text, "width": int(width), "height": int(height), **fields})
        else:
            raise ValueError(f"unknown camera {text!r}: not a YAML file, not in {CAMERA_CONFIG_DIR} and not a "
                             f"registered type ({list_cameras()})")
    else:
        raise TypeError(f"camera must be a Camera, a mapping or a name/path, got {type(spec).__name__}")
    if width is not None and height is not None and (cam.width, cam.height) != (int(width), int(height)):
        cam = cam.resized(int(width), int(height))
    return cam
