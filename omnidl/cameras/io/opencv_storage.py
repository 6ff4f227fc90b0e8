"""OpenCV ``cv::FileStorage`` YAML/XML calibrations (``calibrateCamera``, ``cv2.fisheye``, ``cv2.omnidir``).

Fields, as the OpenCV sample apps write them (``samples/cpp/calibration.cpp``, the camera-calibration
tutorial, ``opencv_contrib/modules/ccalib/samples/omni_calibration.cpp``):

* intrinsic matrix ``K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]``: ``camera_matrix`` (also read:
  ``Camera_Matrix`` as the calibration tutorial's sample output ``out_camera_data.yml`` has it,
  ``cameraMatrix``, ``K``, ``intrinsic_matrix``, ``intrinsics``, ``M``);
* distortion: ``distortion_coefficients`` (also ``Distortion_Coefficients`` (tutorial), ``distCoeffs``,
  ``dist_coeffs``, ``D``, ``distortion``);
* ``xi`` (``cv2.omnidir``), ``fisheye_model`` (the tutorial's flag: ``1`` is ``cv2.fisheye``, ``0`` is
  ``calibrateCamera``), optional ``calibration_model`` (``omnidir``/``fisheye``/``pinhole``);
* image size: ``image_width``/``image_height`` (also the tutorial's ``image_Width``/``image_Height``, and
  ``image_size``/``imageSize`` ``[w, h]``).

Model: ``xi`` present -> ``unified`` (``D = k1, k2, p1, p2``, skew ``s``); ``fisheye_model`` non-zero, or 4
coefficients stored as ``D`` without ``xi`` or ``fisheye_model`` (``cv2.fisheye``'s name) ->
``kannala_brandt`` with ``k0 = 1``;
otherwise ``calibrateCamera``'s ``k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4[, tau_x, tau_y]]]]`` ->
``pinhole`` (all zero) or ``opencv`` (tilt ``tau`` must be 0). ``model=`` overrides the guess.

Pixel convention: OpenCV's first pixel centre is ``(0, 0)``; omnidl's ``cx = cx_file + 0.5`` (same for
``cy``), and writers subtract 0.5 (see :mod:`omnidl.cameras.io._common`).
"""
from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np

from ...utils.io import atomic_write_bytes
from ..base import Camera
from ._common import (OPENCV_SHIFT, family_of, make, positive_int, require_max_fov, safe_yaml, theta_poly_max_fov,
                      unsupported)

FORMAT = "opencv"
K_KEYS = ("camera_matrix", "Camera_Matrix", "cameraMatrix", "K", "intrinsic_matrix", "intrinsics", "M")
D_KEYS = ("distortion_coefficients", "Distortion_Coefficients", "distCoeffs", "dist_coeffs", "D", "distortion")
#: (width key, height key) pairs: ``calibrateCamera`` samples, the calibration tutorial's sample output
SIZE_KEYS = (("image_width", "image_height"), ("image_Width", "image_Height"))
OPENCV_D = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4", "tau_x", "tau_y")
WRITES = ("pinhole", "opencv", "kannala_brandt", "unified")
MODELS = ("pinhole", "fisheye", "omnidir")


# -- FileStorage parsing (YAML 1.0 with !!opencv-matrix, or XML) ------------------------------------------
def _shape(node: dict) -> tuple[int, ...] | None:
    """Shape of an ``opencv-matrix`` (``rows``, ``cols``) or ``opencv-nd-matrix`` (``sizes``) node."""
    if "data" not in node:
        return None
    if "rows" in node and "cols" in node:
        return int(node["rows"]), int(node["cols"])
    if "sizes" in node:
        sizes = node["sizes"]
        return tuple(int(v) for v in (sizes if isinstance(sizes, list) else str(sizes).split()))
    return None


def _array(data: Any, shape: tuple[int, ...]) -> np.ndarray:
    vals = data if isinstance(data, list) else str(data).split()
    return np.asarray([float(v) for v in vals], dtype=np.float64).reshape(shape)


def _matrix(node: Any) -> Any:
    if isinstance(node, dict) and _shape(node) is not None:
        return _array(node["data"], _shape(node))
    if isinstance(node, dict):
        return {k: _matrix(v) for k, v in node.items()}
    return node


def parse_yaml(text: str, where: str) -> dict[str, Any]:
    """A FileStorage YAML (``%YAML:1.0`` header, ``!!opencv-matrix`` tags) or plain YAML -> dict (safe loader)."""
    body = re.sub(r"!!opencv-[a-z-]+|!<tag:yaml\.org,2002:opencv-[a-z-]+>", "", text)
    data = safe_yaml(body, where)
    if not isinstance(data, dict):
        raise ValueError(f"{where}: expected a YAML mapping at the top level, got {type(data).__name__}")
    return {str(k): _matrix(v) for k, v in data.items()}


def _xml_value(el: ET.Element) -> Any:
    kids = list(el)
    if kids:
        d = {k.tag: _xml_value(k) for k in kids}
        shape = _shape(d)
        return d if shape is None else _array(d["data"], shape)
    text = (el.text or "").strip()
    for conv in (int, float):
        try:
            return conv(text)
        except ValueError:
            pass
    toks = text.split()
    if len(toks) > 1:
        try:
            return [float(t) for t in toks]
        except ValueError:
            pass
    return text.strip('"')


def parse_xml(text: str, where: str) -> dict[str, Any]:
    try:
        root = ET.fromstring(text.lstrip())
    except ET.ParseError as e:
        raise ValueError(f"{where}: cannot parse it as XML ({e})") from None
    return {child.tag: _xml_value(child) for child in root}


def parse(path: str | Path) -> dict[str, Any]:
    """The top-level nodes of a FileStorage file (YAML or XML by content)."""
    path = Path(path)
    text = path.read_text()
    where = f"OpenCV FileStorage file {str(path)!r}"
    return parse_xml(text, where) if text.lstrip().startswith("<") else parse_yaml(text, where)


# -- reading -----------------------------------------------------------------------------------------------
def _first(data: dict[str, Any], keys: tuple[str, ...]) -> tuple[str | None, Any]:
    for k in keys:
        if k in data:
            return k, data[k]
    return None, None


def _size(data: dict[str, Any], where: str, image_size: tuple[int, int] | None) -> tuple[int, int]:
    for wk, hk in SIZE_KEYS:
        if wk in data and hk in data:
            return positive_int(data[wk], where, wk), positive_int(data[hk], where, hk)
    _, sz = _first(data, ("image_size", "imageSize", "image_resolution", "resolution"))
    if sz is not None:
        wh = np.asarray(sz, dtype=np.float64).ravel()
        if wh.size == 2:
            return positive_int(wh[0], where, "image width"), positive_int(wh[1], where, "image height")
    if image_size is not None:
        return int(image_size[0]), int(image_size[1])
    raise ValueError(f"{where}: no image size (image_width/image_height or image_size); pass image_size=(W, H)")


def _flag(value: Any, where: str) -> bool:
    """The tutorial's ``fisheye_model`` flag (``0``/``1``; absent: ``False``)."""
    if value is None:
        return False
    if isinstance(value, (bool, int, float)) and float(value) in (0.0, 1.0):
        return bool(value)
    raise ValueError(f"{where}: fisheye_model must be 0 or 1 (the calibration tutorial's flag), got {value!r}")


def from_nodes(data: dict[str, Any], where: str, image_size: tuple[int, int] | None = None,
               model: str | None = None) -> Camera:
    """The camera of parsed FileStorage nodes (see the module doc)."""
    kname, K = _first(data, K_KEYS)
    if K is None:
        raise ValueError(f"{where}: no intrinsic matrix (looked for {', '.join(K_KEYS)})")
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
        raise ValueError(f"{where}: {kname} must be a 3x3 matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got "
                         f"{K.tolist()}")
    dname, D = _first(data, D_KEYS)
    D = np.zeros(0) if D is None else np.asarray(D, dtype=np.float64).ravel()
    width, height = _size(data, where, image_size)
    fx, s, cx, fy, cy = K[0, 0], K[0, 1], K[0, 2] + OPENCV_SHIFT, K[1, 1], K[1, 2] + OPENCV_SHIFT
    if model is None:
        cm = str(data.get("calibration_model", "")).lower()
        if "xi" in data or cm == "omnidir":
            model = "omnidir"
        elif cm == "fisheye" or _flag(data.get("fisheye_model"), where) or (
                "fisheye_model" not in data and dname == "D" and D.size == 4):
            model = "fisheye"
        else:
            model = "pinhole"
    if model not in MODELS:
        raise ValueError(f"{where}: model must be one of {MODELS}, got {model!r}")
    base = dict(width=width, height=height, fx=fx, fy=fy, cx=cx, cy=cy)
    if model == "omnidir":
        if D.size not in (0, 4):
            raise ValueError(f"{where}: cv2.omnidir needs 4 distortion coefficients (k1, k2, p1, p2) in {dname}, "
                             f"got {D.size}")
        xi = float(np.asarray(data.get("xi", np.nan), dtype=np.float64).ravel()[0])
        k = list(D) if D.size else [0.0] * 4
        return make("unified", where, **base, s=s, xi=xi, k1=k[0], k2=k[1], p1=k[2], p2=k[3])
    if s != 0:
        raise ValueError(f"{where}: skew {kname}[0][1] = {s} is not supported by the {model} models (only "
                         "cv2.omnidir has a skew)")
    if model == "fisheye":
        if D.size != 4:
            raise ValueError(f"{where}: cv2.fisheye needs 4 distortion coefficients (k1..k4) in {dname}, got {D.size}")
        k = [float(v) for v in D]
        return make("kannala_brandt", where, **base, k0=1.0, k1=k[0], k2=k[1], k3=k[2], k4=k[3],
                    max_fov=theta_poly_max_fov({1: 1.0, 3: k[0], 5: k[1], 7: k[2], 9: k[3]}))
    if D.size not in (0, 4, 5, 8, 12, 14):
        raise ValueError(f"{where}: {dname} must hold 4, 5, 8, 12 or 14 coefficients ({', '.join(OPENCV_D)}), "
                         f"got {D.size}")
    d = dict(zip(OPENCV_D, (float(v) for v in D)))
    tau = (d.pop("tau_x", 0.0), d.pop("tau_y", 0.0))
    if any(tau):
        raise ValueError(f"{where}: the tilted-sensor terms (tau_x, tau_y) = {tau} are not supported (must be 0)")
    if not any(d.values()):
        return make("pinhole", where, **base)
    return make("opencv", where, **base, **d)


def read(path: str | Path, image_size: tuple[int, int] | None = None, model: str | None = None) -> Camera:
    """The camera of an OpenCV FileStorage calibration (``image_size=(W, H)`` if the file has none)."""
    return from_nodes(parse(path), f"OpenCV FileStorage file {str(path)!r}", image_size, model)


# -- writing -----------------------------------------------------------------------------------------------
def to_nodes(camera: Camera) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """``(K, D, extra scalar nodes)`` of ``camera`` in OpenCV's convention."""
    fam, c = family_of(camera), camera
    if fam not in WRITES:
        raise unsupported(FORMAT, c, WRITES)
    skew = c.s if fam == "unified" else 0.0
    K = np.array([[c.fx, skew, c.cx - OPENCV_SHIFT], [0.0, c.fy, c.cy - OPENCV_SHIFT], [0.0, 0.0, 1.0]])
    extra: dict[str, Any] = {}
    if fam == "pinhole":
        D = np.zeros(5)
    elif fam == "opencv":
        vals = [getattr(c, n) for n in OPENCV_D[:12]]
        n = 12 if any(vals[8:]) else 8 if any(vals[5:8]) else 5
        D = np.array(vals[:n])
    elif fam == "kannala_brandt":
        if c.k0 != 1:
            raise unsupported(FORMAT, c, WRITES, f"cv2.fisheye has k0 = 1, got k0 = {c.k0}")
        require_max_fov(c, {1: 1.0, 3: c.k1, 5: c.k2, 7: c.k3, 9: c.k4}, FORMAT, WRITES, "cv2.fisheye")
        D, extra = np.array([c.k1, c.k2, c.k3, c.k4]), {"fisheye_model": 1}
    else:
        D, extra = np.array([c.k1, c.k2, c.p1, c.p2]), {"calibration_model": "omnidir", "xi": float(c.xi)}
    return K, D.reshape(1, -1), extra


def _fmt(v: float) -> str:
    r = repr(float(v))
    return r if ("." in r or "e" in r or "n" in r) else r + "."


def _scalar(v: Any) -> str:
    if isinstance(v, float):
        return _fmt(v)
    return f'"{v}"' if isinstance(v, str) else str(v)


def dumps(camera: Camera, path: str | Path) -> bytes:
    """The bytes :func:`write` writes (``path`` only picks the layout by its suffix)."""
    path = Path(path)
    K, D, extra = to_nodes(camera)
    scalars: list[tuple[str, Any]] = [("image_width", int(camera.width)), ("image_height", int(camera.height))]
    scalars += list(extra.items())
    mats = [("camera_matrix", K), ("distortion_coefficients", D)]
    if path.suffix.lower() == ".xml":
        out = ['<?xml version="1.0"?>', "<opencv_storage>"]
        for k, v in scalars:
            out.append(f"<{k}>{_scalar(v)}</{k}>")
        for k, m in mats:
            out.append(f'<{k} type_id="opencv-matrix">\n  <rows>{m.shape[0]}</rows>\n  <cols>{m.shape[1]}</cols>\n'
                       f"  <dt>d</dt>\n  <data>\n    {' '.join(_fmt(v) for v in m.ravel())}</data></{k}>")
        out.append("</opencv_storage>")
    else:
        out = ["%YAML:1.0", "---"]
        for k, v in scalars:
            out.append(f"{k}: {_scalar(v)}")
        for k, m in mats:
            out.append(f"{k}: !!opencv-matrix\n   rows: {m.shape[0]}\n   cols: {m.shape[1]}\n   dt: d\n"
                       f"   data: [ {', '.join(_fmt(v) for v in m.ravel())} ]")
    return ("\n".join(out) + "\n").encode()


def write(camera: Camera, path: str | Path) -> None:
    """Write ``camera`` as FileStorage YAML (``.xml`` suffix: XML) that ``cv2.FileStorage`` reads."""
    atomic_write_bytes(path, dumps(camera, path))



def looks_like(data: dict[str, Any]) -> bool:
    return any(k in data for k in K_KEYS)

