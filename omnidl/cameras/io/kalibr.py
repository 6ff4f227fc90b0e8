"""Kalibr ``camchain.yaml`` (reader and writer), following Kalibr's own reader.

The truth is ``aslam_offline_calibration/kalibr/python/kalibr_common/ConfigReader.py`` (``CameraParameters``
and ``AslamCamera``). Each camera is a top-level node ``camN`` with ``camera_model``, ``intrinsics``,
``distortion_model``, ``distortion_coeffs`` and ``resolution: [W, H]`` (other keys such as ``T_cn_cnm1``,
``T_cam_imu``, ``rostopic``, ``cam_overlaps`` are ignored):

=============  ==========================  ==================  ====================  ======================
camera_model   intrinsics                  distortion_model    distortion_coeffs     omnidl family
=============  ==========================  ==================  ====================  ======================
pinhole        fu, fv, pu, pv              none / radtan       [] / k1, k2, r1, r2   pinhole / opencv
pinhole        fu, fv, pu, pv              equidistant         k1, k2, k3, k4        kannala_brandt (k0=1)
pinhole        fu, fv, pu, pv              fov                 w                     fov (omega = w)
omni           xi, fu, fv, pu, pv          none / radtan       [] / k1, k2, r1, r2   unified
ds             xi, alpha, fu, fv, pu, pv   none                []                    double_sphere
eucm           alpha, beta, fu, fv, pu, pv none                []                    eucm
=============  ==========================  ==================  ====================  ======================

These are exactly the combinations Kalibr's ``AslamCamera`` builds (``omni`` + ``equidistant`` raises there,
and here). ``equidistant`` is Kalibr's name; older omnidl wrote ``equi``, which is still read but never
written. radtan's ``r1, r2`` are OpenCV's ``p1, p2``. Files that start with OpenCV's ``%YAML:1.0`` directive
(as some VIO datasets ship their camchains) are read; every YAML load is safe (see
:func:`~omnidl.cameras.io._common.safe_yaml`).

Writing: the file is what Kalibr's ``checkIntrinsics``/``checkDistortion``/``checkResolution`` accept
(float intrinsics, focal lengths and principal point >= 0, ``omni`` xi >= 0, ``ds``/``eucm`` 0 <= alpha < 1,
``eucm`` beta >= 0, integer resolution); a camera outside that, or one Kalibr cannot hold (an equidistant
camera whose ``max_fov`` is not what the file implies: Kalibr projects only points in front of the camera,
``theta < 90 deg``), raises :class:`UnsupportedModelError`.

Pixel convention: Kalibr follows OpenCV (first pixel centre at ``(0, 0)``): omnidl's ``cx = pu + 0.5``,
``cy = pv + 0.5``; the writer subtracts 0.5.
"""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from ...utils.io import atomic_write_bytes
from ..base import Camera
from ._common import (OPENCV_SHIFT, family_of, make, positive_int, require_zero, safe_yaml, select,
                      require_max_fov, theta_poly_max_fov, unsupported)

FORMAT = "kalibr"
INTRINSICS = {"pinhole": ("fu", "fv", "pu", "pv"), "omni": ("xi", "fu", "fv", "pu", "pv"),
              "ds": ("xi", "alpha", "fu", "fv", "pu", "pv"), "eucm": ("alpha", "beta", "fu", "fv", "pu", "pv")}
DISTORTION = {"none": (), "radtan": ("k1", "k2", "r1", "r2"), "equidistant": ("k1", "k2", "k3", "k4"),
              "fov": ("w",)}
#: names read as another (omnidl before issue 49 wrote ``equi``, which Kalibr's reader refuses)
ALIASES = {"equi": "equidistant"}
#: (camera_model, distortion_model) pairs Kalibr's AslamCamera builds
COMBOS = {("pinhole", "none"), ("pinhole", "radtan"), ("pinhole", "equidistant"), ("pinhole", "fov"),
          ("omni", "none"), ("omni", "radtan"), ("ds", "none"), ("eucm", "none")}
WRITES = ("pinhole", "opencv", "kannala_brandt", "fov", "unified", "double_sphere", "eucm")


def to_camera(node: Mapping[str, Any], where: str) -> Camera:
    """The omnidl camera of one ``camN`` node."""
    for key in ("camera_model", "intrinsics", "resolution"):
        if key not in node:
            raise ValueError(f"{where}: missing field {key!r}")
    model, dist = str(node["camera_model"]), str(node.get("distortion_model", "none"))
    dist = ALIASES.get(dist, dist)
    if model not in INTRINSICS:
        raise ValueError(f"{where}: camera_model {model!r} is not one of Kalibr's {sorted(INTRINSICS)}")
    if dist not in DISTORTION:
        raise ValueError(f"{where}: distortion_model {dist!r} is not one of Kalibr's {sorted(DISTORTION)}")
    if (model, dist) not in COMBOS:
        raise ValueError(f"{where}: the combination camera_model {model!r} with distortion_model {dist!r} is not "
                         "one Kalibr builds (pinhole-none/radtan/equidistant/fov, omni-none/radtan, ds-none, "
                         "eucm-none)")
    names, dnames = INTRINSICS[model], DISTORTION[dist]
    intr, coeffs = node["intrinsics"], node.get("distortion_coeffs") or []
    if not isinstance(intr, list) or not isinstance(coeffs, list):
        raise ValueError(f"{where}: intrinsics and distortion_coeffs must be lists, got {intr!r} and {coeffs!r}")
    if len(intr) != len(names):
        raise ValueError(f"{where}: {model} intrinsics are [{', '.join(names)}], got {len(intr)} values {intr}")
    if len(coeffs) != len(dnames):
        raise ValueError(f"{where}: {dist} distortion_coeffs are [{', '.join(dnames)}], got {len(coeffs)} values")
    res = node["resolution"]
    if not isinstance(res, list) or len(res) != 2:
        raise ValueError(f"{where}: resolution must be [width, height], got {res}")
    try:
        p = dict(zip(names, (float(v) for v in intr)))
        d = dict(zip(dnames, (float(v) for v in coeffs)))
    except (TypeError, ValueError):
        raise ValueError(f"{where}: intrinsics {intr} and distortion_coeffs {coeffs} must be numbers") from None
    base = dict(width=positive_int(res[0], where, "resolution[0]"), height=positive_int(res[1], where, "resolution[1]"),
                fx=p["fu"], fy=p["fv"], cx=p["pu"] + OPENCV_SHIFT, cy=p["pv"] + OPENCV_SHIFT)
    combo = f"{model}-{dist}"
    if combo in ("pinhole-none", "pinhole-radtan"):
        if not any(d.values()):
            return make("pinhole", where, **base)
        return make("opencv", where, **base, k1=d["k1"], k2=d["k2"], p1=d["r1"], p2=d["r2"])
    if combo == "pinhole-equidistant":
        return make("kannala_brandt", where, **base, k0=1.0, **d, max_fov=theta_poly_max_fov(
            {1: 1.0, 3: d["k1"], 5: d["k2"], 7: d["k3"], 9: d["k4"]}))
    if combo == "pinhole-fov":
        return make("fov", where, **base, omega=d["w"])
    if combo in ("omni-none", "omni-radtan"):
        return make("unified", where, **base, xi=p["xi"], k1=d.get("k1", 0.0), k2=d.get("k2", 0.0),
                    p1=d.get("r1", 0.0), p2=d.get("r2", 0.0))
    if combo == "ds-none":
        return make("double_sphere", where, **base, xi=p["xi"], alpha=p["alpha"])
    return make("eucm", where, **base, alpha=p["alpha"], beta=p["beta"])


def from_camera(camera: Camera) -> dict[str, Any]:
    """The ``camN`` node of ``camera``."""
    fam, c = family_of(camera), camera
    if fam not in WRITES:
        raise unsupported(FORMAT, c, WRITES)
    fpc = [float(c.fx), float(c.fy), float(c.cx - OPENCV_SHIFT), float(c.cy - OPENCV_SHIFT)]
    if fam == "pinhole":
        model, intr, dist, coeffs = "pinhole", fpc, "none", []
    elif fam == "opencv":
        require_zero(c, ("k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4"), FORMAT, WRITES)
        model, intr, dist, coeffs = "pinhole", fpc, "radtan", [c.k1, c.k2, c.p1, c.p2]
    elif fam == "kannala_brandt":
        if c.k0 != 1:
            raise unsupported(FORMAT, c, WRITES, f"Kalibr's equidistant model has k0 = 1, got k0 = {c.k0}")
        require_max_fov(c, {1: 1.0, 3: c.k1, 5: c.k2, 7: c.k3, 9: c.k4}, FORMAT, WRITES,
                        "Kalibr's equidistant model")
        model, intr, dist, coeffs = "pinhole", fpc, "equidistant", [c.k1, c.k2, c.k3, c.k4]
    elif fam == "fov":
        model, intr, dist, coeffs = "pinhole", fpc, "fov", [c.omega]
    elif fam == "unified":
        require_zero(c, ("s",), FORMAT, WRITES)
        model, intr, dist, coeffs = "omni", [float(c.xi)] + fpc, "radtan", [c.k1, c.k2, c.p1, c.p2]
    elif fam == "double_sphere":
        model, intr, dist, coeffs = "ds", [float(c.xi), float(c.alpha)] + fpc, "none", []
    else:
        model, intr, dist, coeffs = "eucm", [float(c.alpha), float(c.beta)] + fpc, "none", []
    _check_kalibr_accepts(c, model, intr)
    return {"camera_model": model, "intrinsics": intr, "distortion_model": dist,
            "distortion_coeffs": [float(v) for v in coeffs], "resolution": [int(c.width), int(c.height)]}


def node_name(key: Any) -> str:
    """The camchain node of ``key``: Kalibr names cameras ``cam0``, ``cam1``...; an integer ``n`` is ``camN``."""
    return f"cam{key}" if isinstance(key, int) and not isinstance(key, bool) else str(key)


def _check_kalibr_accepts(camera: Camera, model: str, intr: list[float]) -> None:
    """Refuse values Kalibr's ``CameraParameters.checkIntrinsics`` rejects (the file would not load there)."""
    p = dict(zip(INTRINSICS[model], intr))
    rules = [("fu", p["fu"] >= 0, ">= 0"), ("fv", p["fv"] >= 0, ">= 0"),
             ("pu", p["pu"] >= 0, ">= 0 (omnidl cx >= 0.5)"), ("pv", p["pv"] >= 0, ">= 0 (omnidl cy >= 0.5)")]
    if model == "omni":
        rules.append(("xi", p["xi"] >= 0, ">= 0"))
    if model in ("ds", "eucm"):
        rules.append(("alpha", 0 <= p["alpha"] < 1, "in [0, 1)"))
    if model == "eucm":
        rules.append(("beta", p["beta"] >= 0, ">= 0"))
    for name, ok, rule in rules:
        if not ok:
            raise unsupported(FORMAT, camera, WRITES, f"Kalibr's reader requires {model} {name} {rule}, got "
                              f"{p[name]!r}")


def _nodes(path: str | Path) -> dict[str, dict]:
    path = Path(path)
    where = f"Kalibr camchain {str(path)!r}"
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise ValueError(f"{where}: cannot read it as text ({e})") from None
    data = safe_yaml(text, where)
    if not isinstance(data, dict):
        raise ValueError(f"{where}: expected a mapping of camN nodes")
    return {str(k): v for k, v in data.items() if isinstance(v, dict) and "camera_model" in v}


def read_all(path: str | Path) -> dict[str, Camera]:
    """Every ``camN`` of a camchain as ``{name: Camera}`` (file order)."""
    return {k: to_camera(v, f"Kalibr camchain {str(path)!r} node {k!r}") for k, v in _nodes(path).items()}


def read(path: str | Path, camera: str | int | None = None) -> Camera:
    """Camera ``camera`` (``'cam1'`` or ``1``; default: the first) of a Kalibr camchain."""
    nodes = _nodes(path)
    if isinstance(camera, int) and not isinstance(camera, bool):
        camera = f"cam{camera}"
    node = select(nodes, camera, f"Kalibr camchain {str(path)!r}")
    name = next(k for k, v in nodes.items() if v is node)
    return to_camera(node, f"Kalibr camchain {str(path)!r} node {name!r}")


def dumps(cameras: Camera | Mapping[str, Camera], path: str | Path) -> bytes:
    """The bytes :func:`write` writes (``path`` only picks the layout by its suffix)."""
    import yaml
    items = cameras.items() if isinstance(cameras, Mapping) else [("cam0", cameras)]
    data = {node_name(k): from_camera(v) for k, v in items}
    return (yaml.safe_dump(data, sort_keys=False, default_flow_style=None)).encode()


def write(cameras: Camera | Mapping[str, Camera], path: str | Path) -> None:
    """Write one camera (``cam0``) or ``{name: Camera}`` as a camchain YAML (intrinsics only)."""
    atomic_write_bytes(path, dumps(cameras, path))



def looks_like(data: Mapping[str, Any]) -> bool:
    return any(isinstance(v, dict) and "camera_model" in v and "intrinsics" in v for v in data.values())
