"""One resolver from a user's camera spec (object, mapping, file, name) to a :class:`Camera`.

Every place that takes a ``camera=`` argument (layers, models, datasets, command lines) goes through
:func:`resolve_camera`, so they all accept the same specs and give the same errors.
"""
from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from importlib import resources
from pathlib import Path
from typing import Any

from .base import Camera
from .registry import build, list_cameras
from .validate import check_size

#: ``configs/camera`` of the Hydra config tree shipped inside the package (``omnidl/configs/camera``, found with
#: ``importlib.resources``: the installed package's in a wheel install, the checkout's in an editable one)
CAMERA_CONFIG_DIR = Path(str(resources.files("omnidl").joinpath("configs", "camera")))
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
    """Names of the ``configs/camera/<name>.yaml`` presets shipped with the package (e.g. ``kb_f195``)."""
    return sorted(p.stem for p in CAMERA_CONFIG_DIR.glob("*.yaml"))


#: what to do when an image's size is not the calibrated image's size (nor that image uniformly resized)
SIZE_POLICIES = ("error", "pad", "crop", "scale")


def is_uniform_resize(width: int, height: int, camera: Camera) -> bool:
    """True when a ``width x height`` image is the calibrated image uniformly resized.

    A downscale may round each side to a neighbouring integer (``floor``/``ceil`` of ``s W_c``, ``s H_c``);
    an upscale must be exact; a side of the calibrated length needs the other side unchanged too
    (so a 1088x960 image is not a 1080x960 calibration resized).
    """
    wc, hc = camera.width, camera.height
    if (width, height) == (wc, hc):
        return True
    if width == wc or height == hc:
        return False
    for a, ac, b, bc in ((height, hc, width, wc), (width, wc, height, hc)):
        s = a / ac
        target = s * bc
        if s <= 1:
            if b in (math.floor(target + 1e-9), math.ceil(target - 1e-9)):
                return True
        elif abs(target - b) < 1e-9:
            return True
    return False


def _check_policy(size_policy: str) -> str:
    if size_policy not in SIZE_POLICIES:
        raise ValueError(f"size_policy must be one of {list(SIZE_POLICIES)}, got {size_policy!r}")
    return size_policy


def _mismatch(w: int, h: int, camera: Camera, what: str, source: str | None) -> str:
    of = f" of {source!r}" if source else ""
    return (f"{what} of size {w}x{h} (W x H) disagrees with the calibration{of} ({camera.width}x{camera.height})")


def check_image_size(hw: Sequence[int], camera: Camera, what: str = "image", rel_tol: float = 0.02,
                     size_policy: str = "error", source: str | None = None) -> None:
    """Raise ``ValueError`` unless an ``(H, W)`` image can show ``camera`` under ``size_policy``.

    A calibrated camera describes an image of ``camera.width x camera.height`` pixels; a network may
    read that image uniformly resized (thesis Eq. 7.3, :func:`is_uniform_resize`). Any other size needs
    a policy: ``"error"`` (default) raises naming ``source`` (the calibration file) and both sizes;
    ``"pad"``/``"crop"`` accept any size (the calibrated image padded / cropped on the right and bottom,
    see :func:`fit_camera_to_image`); ``"scale"`` stretches to the size if the aspect ratios agree to
    ``rel_tol``.
    """
    _check_policy(size_policy)
    w, h = check_size(f"{what} size (H, W) = {tuple(hw)!r}", hw[1], hw[0])
    if size_policy in ("pad", "crop") or is_uniform_resize(w, h, camera):
        return
    msg = _mismatch(w, h, camera, what, source)
    if size_policy == "error":
        raise ValueError(f"{msg}: it is not the calibrated image uniformly resized. Use a calibration of this "
                         "image size or state a size policy (size_policy=): 'pad' (the image is the calibrated "
                         "one padded on the right/bottom, Eq. 7.3), 'crop' (cropped on the right/bottom) or "
                         "'scale' (stretched; aspect ratios within 2 %)")
    ar_img, ar_cam = w / h, camera.width / camera.height
    if abs(ar_img / ar_cam - 1) > rel_tol:
        raise ValueError(f"{msg}, aspect {ar_cam:.4f} vs {ar_img:.4f} (size_policy='scale' stretches by at most "
                         f"{100 * rel_tol:g} %); resize the image to the calibrated aspect ratio, use a calibration "
                         "of this image size or state size_policy='pad' or 'crop'")


def fit_camera_to_image(camera: Camera, width: int, height: int, size_policy: str = "error",
                        source: str | None = None, what: str = "image") -> Camera:
    """``camera`` on a ``width x height`` image, following ``size_policy`` (see :func:`check_image_size`).

    * the same size: ``camera``; a uniform resize (:func:`is_uniform_resize`): ``camera.resized``;
    * ``"pad"``: the calibrated image scaled by ``s = min(W / W_c, H / H_c)`` fills the top-left of the
      image and the rest is padding (thesis Eq. 7.3; the calibration is unchanged, padded pixels are
      invalid); at ``s = 1`` a 1080x960 calibration on a 1088x960 image keeps every pixel where it was;
    * ``"crop"``: the image is the top-left part of the calibrated image scaled by ``s = max(W / W_c,
      H / H_c)`` (the right/bottom are cut off);
    * ``"scale"``: stretched to the size (``camera.resized(W, H)``), aspect ratios within 2 %;
    * ``"error"``: ``ValueError`` naming ``source`` and both sizes.
    """
    w, h = check_size(f"{what} size {width!r}x{height!r} (W x H)", width, height)
    if (camera.width, camera.height) == (w, h):
        return camera
    check_image_size((h, w), camera, what, size_policy=size_policy, source=source)
    if size_policy in ("error", "scale") or is_uniform_resize(w, h, camera):
        return camera.resized(w, h)
    s = (min if size_policy == "pad" else max)(w / camera.width, h / camera.height)
    return camera.resized(w, h, pad_right=w / s - camera.width, pad_bottom=h / s - camera.height)


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
    cfg.pop("size_policy", None)  # read by resolve_camera (_stated_policy), not a model field
    return cfg


def _from_mapping(spec: Any, fields: dict[str, Any]) -> Camera:
    cfg = {k: v for k, v in dict(spec).items() if k not in ("_target_", "size_policy")}
    cfg.update(fields)
    if "type" not in cfg and "calib_file" in cfg:
        cfg["type"] = "kannala_brandt"
    return build(cfg)


#: suffixes of other tools' calibration files, read by :func:`omnidl.cameras.io.load`
IO_SUFFIXES = (".bin", ".xml", ".json")


def _io_format(path: Path) -> str | None:
    """The :mod:`omnidl.cameras.io` format of a calibration file, ``None`` if not recognised."""
    from .io import detect_format
    try:
        return detect_format(path)
    except ValueError:
        return None


def _from_text(spec: str | os.PathLike, width: int | None, height: int | None,
               fields: dict[str, Any]) -> tuple[Camera, bool]:
    """``(camera, sized)``: ``sized`` when a registered type was built at ``width x height`` directly."""
    text = os.fspath(spec)
    path = Path(text)
    suffix = path.suffix.lower()
    if suffix in CALIB_SUFFIXES or suffix in YAML_SUFFIXES or suffix in IO_SUFFIXES:
        if not path.is_file():
            raise FileNotFoundError(f"camera file {text!r} does not exist")
        fmt = _io_format(path)
        if fmt not in (None, "omnidl", "kb_txt") or suffix in IO_SUFFIXES:
            from .io import load  # other tools' calibrations (COLMAP, Kalibr, OpenCV, ORB-SLAM3, OCamCalib)
            cam = load(path, format=fmt)
            return (build({**cam.to_config(), **fields}) if fields else cam), False
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


def _stated_policy(spec: Any) -> tuple[str | None, str | None]:
    """``(size_policy, source)`` stated by a spec: the ``size_policy`` key of a mapping or camera YAML, and the
    file the calibration comes from (for error messages)."""
    if isinstance(spec, Camera) or spec is None:
        return None, None
    if isinstance(spec, Mapping) or hasattr(spec, "items"):
        src = spec.get("calib_file", None) if hasattr(spec, "get") else None
        return (spec.get("size_policy", None) if hasattr(spec, "get") else None), (None if src is None else str(src))
    if not isinstance(spec, (str, os.PathLike)):
        return None, None
    text = os.fspath(spec)
    path = Path(text)
    if path.suffix.lower() not in YAML_SUFFIXES:
        path = CAMERA_CONFIG_DIR / f"{text}.yaml"
        if Path(text).name != text or not path.is_file():
            return None, text
    try:
        from omegaconf import OmegaConf
        cfg = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
    except Exception:  # noqa: BLE001 (reported by _load_yaml with the file name)
        return None, str(path)
    if isinstance(cfg, dict) and "type" not in cfg and isinstance(cfg.get("camera"), dict):
        cfg = cfg["camera"]
    src = cfg.get("calib_file") if isinstance(cfg, dict) else None
    return (cfg.get("size_policy") if isinstance(cfg, dict) else None), str(src or path)


def resolve_camera(spec: Any, width: int | None = None, height: int | None = None, *, default: Any = _REQUIRED,
                   check_aspect: bool = False, size_policy: str | None = None, allow_files: bool = True,
                   **fields: Any) -> Camera | None:
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
        check_aspect: with a size to resize to, raise ``ValueError`` unless it is the calibrated image
            uniformly resized (the default ``size_policy`` becomes ``"error"``).
        size_policy: what a size that is not the calibrated image uniformly resized means (see
            :func:`fit_camera_to_image`): ``"error"`` (a ``ValueError`` naming the calibration file and both
            sizes), ``"pad"`` (right/bottom padding, Eq. 7.3; the calibration is unchanged), ``"crop"``
            (right/bottom cropped) or ``"scale"`` (stretched, aspect ratios within 2 %). Default: the
            spec's ``size_policy`` key (config mapping or camera YAML), else ``"error"`` with
            ``check_aspect`` and an unchecked ``camera.resized(width, height)`` without.
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
    if not sized and width is not None:
        width, height = check_size(f"requested image size {width!r}x{height!r} (W x H)", width, height)
    if not sized and width is not None and (cam.width, cam.height) != (width, height):
        stated, source = _stated_policy(spec)
        policy = size_policy or stated or ("error" if check_aspect else None)
        if policy is None:
            return cam.resized(width, height)
        cam = fit_camera_to_image(cam, width, height, _check_policy(str(policy)), source, "requested image")
    elif size_policy is not None:
        _check_policy(size_policy)
    return cam
