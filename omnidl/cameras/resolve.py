"""One resolver from a user's camera spec (object, mapping, file, name) to a :class:`Camera`.

Every place that takes a ``camera=`` argument (layers, models, datasets, command lines) goes through
:func:`resolve_camera`, so they all accept the same specs and give the same errors.
"""
from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from .base import Camera
from .registry import build, list_cameras

#: ``configs/camera`` of the source tree (next to the ``omnidl`` package)
CAMERA_CONFIG_DIR = Path(__file__).resolve().parents[2] / "configs" / "camera"
#: suffixes of Kannala–Brandt calibration text files (``cx cy fx fy W H FOV k1 k2 k3 k4``)
CALIB_SUFFIXES = (".txt", ".calib", ".dat")
YAML_SUFFIXES = (".yaml", ".yml")
ACCEPTED = ("a Camera, a config mapping ({'type': ..., ...}, or {'calib_file': ...} for Kannala-Brandt), "
            f"a camera YAML file ({'/'.join(YAML_SUFFIXES)}), a Kannala-Brandt calibration file "
            f"({'/'.join(CALIB_SUFFIXES)}), a configs/camera name or a registered camera type")


class _Required:
    def __repr__(self) -> str:
        return "<required>"


_REQUIRED: Any = _Required()


def config_names() -> list[str]:
    """Names of the ``configs/camera/<name>.yaml`` files (empty outside a source checkout)."""
    return sorted(p.stem for p in CAMERA_CONFIG_DIR.glob("*.yaml"))


def check_image_size(hw: Sequence[int], camera: Camera, what: str = "image", rel_tol: float = 0.02) -> None:
    """Raise ``ValueError`` unless an ``(H, W)`` image can show ``camera`` (same aspect ratio).

    A calibrated camera describes an image of ``camera.width x camera.height`` pixels; a network
    may read it uniformly resized (thesis Eq. 7.3), but not with another aspect ratio.
    """
    h, w = int(hw[0]), int(hw[1])
    ar_img, ar_cam = w / h, camera.width / camera.height
    if abs(ar_img / ar_cam - 1) > rel_tol:
        raise ValueError(f"{what} of size {w}x{h} (W x H) disagrees with the calibration "
                         f"({camera.width}x{camera.height}, aspect {ar_cam:.4f} vs {ar_img:.4f}); resize the image "
                         "to the calibrated aspect ratio or use a calibration of this image size")


def _load_yaml(path: Path) -> dict:
    from omegaconf import OmegaConf
    try:
        cfg = OmegaConf.to_container(OmegaConf.load(path), resolve=True)
    except Exception as exc:  # noqa: BLE001 (YAML/interpolation errors of many kinds)
        raise ValueError(f"camera config {path}: cannot read it as YAML ({exc})") from exc
    if isinstance(cfg, dict) and "type" not in cfg and isinstance(cfg.get("camera"), dict):
        cfg = cfg["camera"]  # a file holding {camera: {...}} (e.g. a saved run config's node)
    if not isinstance(cfg, dict) or "type" not in cfg:
        raise ValueError(f"camera config {path}: expected a mapping with a 'type' field (one of {list_cameras()})")
    return cfg


def _from_mapping(spec: Any, fields: dict[str, Any]) -> Camera:
    cfg = {k: v for k, v in dict(spec).items() if k != "_target_"}
    cfg.update(fields)
    if "type" not in cfg and "calib_file" in cfg:
        cfg["type"] = "kannala_brandt"
    return build(cfg)


def _from_text(spec: str | os.PathLike, width: int | None, height: int | None,
               fields: dict[str, Any]) -> tuple[Camera, bool]:
    """``(camera, sized)``: ``sized`` when a registered type was built at ``width x height`` directly."""
    text = os.fspath(spec)
    path = Path(text)
    suffix = path.suffix.lower()
    if suffix in CALIB_SUFFIXES or suffix in YAML_SUFFIXES:
        if not path.is_file():
            raise FileNotFoundError(f"camera file {text!r} does not exist")
        if suffix in CALIB_SUFFIXES:
            return _from_mapping({"calib_file": text}, fields), False
        return build(_load_yaml(path), **fields), False
    named = CAMERA_CONFIG_DIR / f"{text}.yaml"
    if path.name == text and named.is_file():
        return build(_load_yaml(named), **fields), False
    if text in list_cameras():
        if width is None or height is None:
            raise ValueError(f"camera type {text!r} needs width and height (or use a configured camera: "
                             f"{config_names()})")
        return build({"type": text, "width": int(width), "height": int(height), **fields}), True
    raise ValueError(f"unknown camera {text!r}: not a camera file ({'/'.join(YAML_SUFFIXES + CALIB_SUFFIXES)}), "
                     f"not a config name in {CAMERA_CONFIG_DIR} ({config_names()}) and not a registered camera "
                     f"type ({list_cameras()})")


def resolve_camera(spec: Any, width: int | None = None, height: int | None = None, *, default: Any = _REQUIRED,
                   check_aspect: bool = False, allow_files: bool = True, **fields: Any) -> Camera | None:
    """A :class:`Camera` from any camera spec.

    Args:
        spec: one of
            - a :class:`Camera` (returned as is, or resized);
            - a config mapping or omegaconf ``DictConfig`` (``{"type": ..., **fields}``; a ``_target_`` key
              is ignored; ``{"calib_file": path, ...}`` without ``type`` is a Kannala–Brandt camera);
            - a path to a camera YAML file (``.yaml``/``.yml``; a top-level ``camera:`` node is unwrapped) or
              to a Kannala–Brandt calibration text file (``.txt``/``.calib``/``.dat``:
              ``cx cy fx fy W H FOV k1 k2 k3 k4``);
            - a name of ``configs/camera/<name>.yaml`` (:data:`CAMERA_CONFIG_DIR`), e.g. ``"kb_f195"``;
            - a registered camera type (:func:`list_cameras`), built at ``width x height`` with ``fields``;
            - ``None``: returns ``default`` (resized like any camera); without ``default`` it is an error.
        width, height: image size the camera is used at; a camera of another size is resized to it
            (same optics, :meth:`Camera.resized`, thesis Eq. 7.3). Give both or neither.
        default: the camera (or ``None``) that stands in for ``spec=None``.
        check_aspect: with a size to resize to, raise ``ValueError`` if its aspect ratio disagrees
            with the camera's (:func:`check_image_size`).
        allow_files: ``False`` accepts in-memory specs only (``Camera``, mapping, ``None``) and raises
            ``TypeError`` for a name or path: layers never read files (resolve those first).
        **fields: model fields that override a config's (or a calibration file's); not for a ``Camera``.

    Raises:
        TypeError: ``spec`` is none of the kinds above (or ``None`` without ``default``).
        FileNotFoundError: a camera file path that does not exist.
        ValueError: an unknown name (lists the config names and registered types), a bad config or
            file, a registered type without a size, or a size with another aspect ratio.
    """
    if (width is None) != (height is None):
        raise ValueError(f"camera size: give both width and height or neither, got width={width}, height={height}")
    if spec is None:
        if default is _REQUIRED:
            raise TypeError(f"no camera given (None); expected {ACCEPTED}")
        if default is None:
            return None
        spec = default
    sized = False
    if isinstance(spec, Camera):
        if fields:
            raise ValueError(f"camera fields {sorted(fields)} apply to a camera config or name, not to a "
                             f"{type(spec).__name__} object")
        cam = spec
    elif isinstance(spec, Mapping) or hasattr(spec, "items"):
        cam = _from_mapping(spec, fields)
    elif isinstance(spec, (str, os.PathLike)):
        if not allow_files:
            raise TypeError(f"camera must be an omnidl Camera, a camera config mapping or None, got "
                            f"{type(spec).__name__} {str(spec)!r}; resolve names and files with "
                            "omnidl.cameras.resolve_camera first")
        cam, sized = _from_text(spec, width, height, fields)
    else:
        raise TypeError(f"camera spec of type {type(spec).__name__} ({spec!r}); expected {ACCEPTED}")
    if not sized and width is not None and (cam.width, cam.height) != (int(width), int(height)):
        if check_aspect:
            check_image_size((int(height), int(width)), cam, "requested image")
        cam = cam.resized(int(width), int(height))
    return cam
