"""Kalibr ``camchain.yaml`` (reader and writer).

Each camera is a top-level node ``camN`` with ``camera_model``, ``intrinsics``, ``distortion_model``,
``distortion_coeffs`` and ``resolution: [W, H]`` (Kalibr wiki, "Supported models"):

=============  ==========================  =================  ====================  ======================
camera_model   intrinsics                  distortion_model   distortion_coeffs     omnidl family
=============  ==========================  =================  ====================  ======================
pinhole        fu, fv, pu, pv              none / radtan      [] / k1, k2, r1, r2   pinhole / opencv
pinhole        fu, fv, pu, pv              equi               k1, k2, k3, k4        kannala_brandt (k0=1)
pinhole        fu, fv, pu, pv              fov                w                     fov (omega = w)
omni           xi, fu, fv, pu, pv          none / radtan      [] / k1, k2, r1, r2   unified
ds             xi, alpha, fu, fv, pu, pv   none               []                    double_sphere
eucm           alpha, beta, fu, fv, pu, pv none               []                    eucm
=============  ==========================  =================  ====================  ======================

radtan's ``r1, r2`` are OpenCV's ``p1, p2``. Pixel convention: Kalibr follows OpenCV (first pixel centre at
``(0, 0)``): omnidl's ``cx = pu + 0.5``, ``cy = pv + 0.5``; the writer subtracts 0.5.
"""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from ...utils.io import atomic_write_text
from ..base import Camera
from ._common import (OPENCV_SHIFT, family_of, make, positive_int, require_zero, select, theta_poly_max_fov,
                      unsupported)

FORMAT = "kalibr"
INTRINSICS = {"pinhole": ("fu", "fv", "pu", "pv"), "omni": ("xi", "fu", "fv", "pu", "pv"),
              "ds": ("xi", "alpha", "fu", "fv", "pu", "pv"), "eucm": ("alpha", "beta", "fu", "fv", "pu", "pv")}
DISTORTION = {"none": (), "radtan": ("k1", "k2", "r1", "r2"), "equi": ("k1", "k2", "k3", "k4"), "fov": ("w",)}
WRITES = ("pinhole", "opencv", "kannala_brandt", "fov", "unified", "double_sphere", "eucm")


def to_camera(node: Mapping[str, Any], where: str) -> Camera:
    """The omnidl camera of one ``camN`` node."""
    for key in ("camera_model", "intrinsics", "resolution"):
        if key not in node:
            raise ValueError(f"{where}: missing field {key!r}")
    model, dist = str(node["camera_model"]), str(node.get("distortion_model", "none"))
    if model not in INTRINSICS:
        raise ValueError(f"{where}: camera_model {model!r} is not one of {sorted(INTRINSICS)}")
    if dist not in DISTORTION:
        raise ValueError(f"{where}: distortion_model {dist!r} is not one of {sorted(DISTORTION)}")
    names, dnames = INTRINSICS[model], DISTORTION[dist]
    intr, coeffs = list(node["intrinsics"]), list(node.get("distortion_coeffs") or [])
    if len(intr) != len(names):
        raise ValueError(f"{where}: {model} intrinsics are [{', '.join(names)}], got {len(intr)} values {intr}")
    if len(coeffs) != len(dnames):
        raise ValueError(f"{where}: {dist} distortion_coeffs are [{', '.join(dnames)}], got {len(coeffs)} values")
    res = list(node["resolution"])
    if len(res) != 2:
        raise ValueError(f"{where}: resolution must be [width, height], got {res}")
    p = dict(zip(names, (float(v) for v in intr)))
    d = dict(zip(dnames, (float(v) for v in coeffs)))
    base = dict(width=positive_int(res[0], where, "resolution[0]"), height=positive_int(res[1], where, "resolution[1]"),
                fx=p["fu"], fy=p["fv"], cx=p["pu"] + OPENCV_SHIFT, cy=p["pv"] + OPENCV_SHIFT)
    combo = f"{model}-{dist}"
    if combo in ("pinhole-none", "pinhole-radtan"):
        if not any(d.values()):
            return make("pinhole", where, **base)
        return make("opencv", where, **base, k1=d["k1"], k2=d["k2"], p1=d["r1"], p2=d["r2"])
    if combo == "pinhole-equi":
        return make("kannala_brandt", where, **base, k0=1.0, **d, max_fov=theta_poly_max_fov(
            {1: 1.0, 3: d["k1"], 5: d["k2"], 7: d["k3"], 9: d["k4"]}))
    if combo == "pinhole-fov":
        return make("fov", where, **base, omega=d["w"])
    if combo in ("omni-none", "omni-radtan"):
        return make("unified", where, **base, xi=p["xi"], k1=d.get("k1", 0.0), k2=d.get("k2", 0.0),
                    p1=d.get("r1", 0.0), p2=d.get("r2", 0.0))
    if combo == "ds-none":
        return make("double_sphere", where, **base, xi=p["xi"], alpha=p["alpha"])
    if combo == "eucm-none":
        return make("eucm", where, **base, alpha=p["alpha"], beta=p["beta"])
    raise ValueError(f"{where}: the combination camera_model {model!r} with distortion_model {dist!r} is not "
                     "supported (pinhole-none/radtan/equi/fov, omni-none/radtan, ds-none, eucm-none)")


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
            raise unsupported(FORMAT, c, WRITES, f"Kalibr's equi model has k0 = 1, got k0 = {c.k0}")
        model, intr, dist, coeffs = "pinhole", fpc, "equi", [c.k1, c.k2, c.k3, c.k4]
    elif fam == "fov":
        model, intr, dist, coeffs = "pinhole", fpc, "fov", [c.omega]
    elif fam == "unified":
        require_zero(c, ("s",), FORMAT, WRITES)
        model, intr, dist, coeffs = "omni", [float(c.xi)] + fpc, "radtan", [c.k1, c.k2, c.p1, c.p2]
    elif fam == "double_sphere":
        model, intr, dist, coeffs = "ds", [float(c.xi), float(c.alpha)] + fpc, "none", []
    else:
        model, intr, dist, coeffs = "eucm", [float(c.alpha), float(c.beta)] + fpc, "none", []
    return {"camera_model": model, "intrinsics": intr, "distortion_model": dist,
            "distortion_coeffs": [float(v) for v in coeffs], "resolution": [int(c.width), int(c.height)]}


def _nodes(path: str | Path) -> dict[str, dict]:
    import yaml
    path = Path(path)
    where = f"Kalibr camchain {str(path)!r}"
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise ValueError(f"{where}: cannot parse it as YAML ({e})") from None
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


def write(cameras: Camera | Mapping[str, Camera], path: str | Path) -> None:
    """Write one camera (``cam0``) or ``{name: Camera}`` as a camchain YAML (intrinsics only)."""
    import yaml
    items = cameras.items() if isinstance(cameras, Mapping) else [("cam0", cameras)]
    data = {str(k): from_camera(v) for k, v in items}
    atomic_write_text(path, yaml.safe_dump(data, sort_keys=False, default_flow_style=None))


def looks_like(data: Mapping[str, Any]) -> bool:
    return any(isinstance(v, dict) and "camera_model" in v and "intrinsics" in v for v in data.values())
