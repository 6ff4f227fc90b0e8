"""COLMAP ``cameras.txt`` / ``cameras.bin`` (reader and writer).

Layouts (COLMAP's documented formats, ``src/colmap/scene/reconstruction_io``):

* text: ``#`` comment lines, then one camera per line ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]``;
* binary (little endian): ``uint64 num_cameras``, then per camera ``int32 camera_id``, ``int32 model_id``,
  ``uint64 width``, ``uint64 height``, ``float64 params[num_params(model)]``.

Parameter order per model as in COLMAP's ``src/colmap/sensor/models.h`` (``params_info``) and the omnidl
family each maps to:

==============================  =============================================  ===================
SIMPLE_PINHOLE (0)              f, cx, cy                                      pinhole
PINHOLE (1)                     fx, fy, cx, cy                                 pinhole
SIMPLE_RADIAL (2), RADIAL (3)   f, cx, cy, k  /  f, cx, cy, k1, k2             opencv
OPENCV (4), FULL_OPENCV (6)     fx, fy, cx, cy, k1, k2, p1, p2[, k3..k6]       opencv
OPENCV_FISHEYE (5)              fx, fy, cx, cy, k1, k2, k3, k4                 kannala_brandt (k0=1)
FOV (7)                         fx, fy, cx, cy, omega                          fov
SIMPLE_RADIAL_FISHEYE (8)       f, cx, cy, k                                   kannala_brandt
RADIAL_FISHEYE (9)              f, cx, cy, k1, k2                              kannala_brandt
THIN_PRISM_FISHEYE (10)         fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, sx1, sy1   see below
RAD_TAN_THIN_PRISM_FISHEYE (11) fx, fy, cx, cy, k0..k5, p0, p1, s0..s3         fisheye624
SIMPLE_DIVISION (12)            f, cx, cy, k                                   scaramuzza (see below)
DIVISION (13)                   fx, fy, cx, cy, k                              scaramuzza (see below)
SIMPLE_FISHEYE (14), FISHEYE    f, cx, cy  /  fx, fy, cx, cy (equidistant)     kannala_brandt
EUCM (16)                       fx, fy, cx, cy, alpha, beta                    eucm
EQUIRECTANGULAR (17)            w, h (full sphere)                             equirect
==============================  =============================================  ===================

COLMAP's fisheye models distort ``theta = atan(r)``: ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + ...)``,
which is Kannala–Brandt with ``k0 = 1``. THIN_PRISM_FISHEYE applies its radial factor, tangential and
thin-prism terms all to the *undistorted* ``theta (cos psi, sin psi)`` (``r^2 = theta^2``), while
Fisheye624 applies tangential/thin-prism terms to the radially distorted point: the two agree exactly
only when ``p1 = p2 = sx1 = sy1 = 0`` (-> kannala_brandt) or ``k1 = .. = k4 = 0`` (-> fisheye624); other
THIN_PRISM_FISHEYE cameras raise :class:`UnsupportedModelError`. Fisheye families get ``max_fov = pi``
(COLMAP projects ``z > 0`` only), smaller when the theta polynomial stops increasing before 90 deg; a
camera with a wider ``max_fov`` (a 195 deg lens) is refused by the writer instead of being cut to 180 deg.

Division models (Fitzgibbon 2001; COLMAP's ``SimpleDivisionCameraModel``/``DivisionCameraModel``): a pixel
lifts to ``(x0, y0) = ((x - cx) / fx, (y - cy) / fy)`` and the ray ``(x0, y0, 1 + k r^2)``, ``r^2 = x0^2 +
y0^2``. That is exactly omnidl's Scaramuzza/OCamCalib model with ``pol = (-fx, 0, -k / fx)``, affine
``c = fy / fx``, ``d = e = 0`` and the centre ``(cx, cy)`` (ray ``(x_s, y_s, -pol(rho))`` with ``x_s = x - cx``,
``y_s = (y - cy) / c``, ``rho = fx r``), so no new family is needed. Differences to COLMAP's code: COLMAP's
``ImgFromCam`` of these models does not check cheirality (with ``k >= 0`` a point behind the camera lands on
the mirrored pixel), omnidl marks it invalid; with ``k > 0`` the valid disk ``r <= 1 / sqrt(k)`` is taken
0.1 % smaller (Scaramuzza's monotonicity limit); COLMAP's ``CamFromImg`` assumes ``1 + k r^2 > 0`` while
omnidl unprojects beyond 90 deg when ``k < 0``. The writer stores a Scaramuzza camera of that form
(``pol = (a0, 0, a2)``, ``d = e = 0``, no ``invpol``) as SIMPLE_DIVISION (``c = 1``) or DIVISION with
``fx = -a0``, ``fy = c fx``, ``k = -a2 fx``; the ratios read back to floating rounding (<= 1e-9 px).

There is no COLMAP model named ``SPHERICAL`` (checked against ``src/colmap/sensor/models.h`` of COLMAP 4.1.1,
the newest release, and pycolmap 4.2.1): COLMAP's spherical model ("Add Spherical Camera Model", #4441) is
``EQUIRECTANGULAR`` (17), the only member of its ``SPHERICAL_CAMERA_MODEL_CASES``; a file naming
``SPHERICAL`` gets an error saying so.

Pixel convention: COLMAP's is omnidl's (first pixel centre at ``(0.5, 0.5)``): no shift. Writers pick the
simplest COLMAP model that holds the camera exactly; floats are written with ``repr`` (shortest string
that reads back bit-exactly).
"""
from __future__ import annotations

import math
import struct
from collections.abc import Mapping
from pathlib import Path

from ...utils.io import atomic_write_bytes
from ..base import Camera
from ._common import (UnsupportedModelError, family_of, make, positive_int, require_max_fov, select, theta_poly_max_fov,
                      unsupported)

FORMAT = "colmap"
#: model id -> (name, parameter names)
MODELS: dict[int, tuple[str, tuple[str, ...]]] = {
    0: ("SIMPLE_PINHOLE", ("f", "cx", "cy")),
    1: ("PINHOLE", ("fx", "fy", "cx", "cy")),
    2: ("SIMPLE_RADIAL", ("f", "cx", "cy", "k")),
    3: ("RADIAL", ("f", "cx", "cy", "k1", "k2")),
    4: ("OPENCV", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")),
    5: ("OPENCV_FISHEYE", ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")),
    6: ("FULL_OPENCV", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")),
    7: ("FOV", ("fx", "fy", "cx", "cy", "omega")),
    8: ("SIMPLE_RADIAL_FISHEYE", ("f", "cx", "cy", "k")),
    9: ("RADIAL_FISHEYE", ("f", "cx", "cy", "k1", "k2")),
    10: ("THIN_PRISM_FISHEYE", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "sx1", "sy1")),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", ("fx", "fy", "cx", "cy", "k0", "k1", "k2", "k3", "k4", "k5", "p0", "p1",
                                        "s0", "s1", "s2", "s3")),
    12: ("SIMPLE_DIVISION", ("f", "cx", "cy", "k")),
    13: ("DIVISION", ("fx", "fy", "cx", "cy", "k")),
    14: ("SIMPLE_FISHEYE", ("f", "cx", "cy")),
    15: ("FISHEYE", ("fx", "fy", "cx", "cy")),
    16: ("EUCM", ("fx", "fy", "cx", "cy", "alpha", "beta")),
    17: ("EQUIRECTANGULAR", ("w", "h")),
}
MODEL_IDS = {name: mid for mid, (name, _) in MODELS.items()}
WRITES = ("pinhole", "opencv", "kannala_brandt", "fov", "fisheye624", "eucm", "equirect", "scaramuzza")
#: names that are not COLMAP models but that users expect to be (name -> what COLMAP calls it)
NOT_MODELS = {"SPHERICAL": "EQUIRECTANGULAR (model id 17, params w, h: the full sphere)"}


# -- model mapping -------------------------------------------------------------------------------------
def _kb(where: str, width: int, height: int, fx: float, fy: float, cx: float, cy: float, ks: list[float]) -> Camera:
    ks = list(ks) + [0.0] * (4 - len(ks))
    coeffs = {1: 1.0, 3: ks[0], 5: ks[1], 7: ks[2], 9: ks[3]}
    return make("kannala_brandt", where, width=width, height=height, fx=fx, fy=fy, cx=cx, cy=cy, k0=1.0, k1=ks[0],
                k2=ks[1], k3=ks[2], k4=ks[3], max_fov=theta_poly_max_fov(coeffs))


def _fisheye624(where: str, width: int, height: int, p: dict[str, float]) -> Camera:
    coeffs = {1: 1.0, **{2 * i + 3: p[f"k{i}"] for i in range(6)}}
    return make("fisheye624", where, width=width, height=height, **p, max_fov=theta_poly_max_fov(coeffs))


def to_camera(model: str, width: int, height: int, params: list[float], where: str = "COLMAP camera") -> Camera:
    """The omnidl camera of a COLMAP ``model`` name with ``params`` (in COLMAP's order)."""
    if model in NOT_MODELS:
        raise UnsupportedModelError(f"{where}: COLMAP has no camera model {model!r} (COLMAP 4.1.1 models.h); its "
                                    f"spherical model is {NOT_MODELS[model]}")
    if model not in MODEL_IDS:
        raise ValueError(f"{where}: unknown COLMAP camera model {model!r}; known: {sorted(MODEL_IDS)}")
    names = MODELS[MODEL_IDS[model]][1]
    if len(params) != len(names):
        raise ValueError(f"{where}: COLMAP model {model} needs {len(names)} parameters ({', '.join(names)}), "
                         f"got {len(params)}")
    p = dict(zip(names, (float(v) for v in params)))
    size = dict(width=width, height=height)
    if "f" in p:
        p["fx"] = p["fy"] = p.pop("f")
    if model in ("SIMPLE_PINHOLE", "PINHOLE"):
        return make("pinhole", where, **size, **p)
    if model in ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV"):
        if "k" in p:
            p["k1"] = p.pop("k")
        return make("opencv", where, **size, **p)
    if model in ("OPENCV_FISHEYE", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "SIMPLE_FISHEYE", "FISHEYE"):
        if "k" in p:
            p["k1"] = p.pop("k")
        return _kb(where, width, height, p["fx"], p["fy"], p["cx"], p["cy"],
                   [p.get(f"k{i}", 0.0) for i in range(1, 5)])
    if model == "THIN_PRISM_FISHEYE":
        ks = [p["k1"], p["k2"], p["k3"], p["k4"]]
        extra = [p["p1"], p["p2"], p["sx1"], p["sy1"]]
        if not any(extra):
            return _kb(where, width, height, p["fx"], p["fy"], p["cx"], p["cy"], ks)
        if not any(ks):
            # r^2 = theta^2 in both; COLMAP x += 2 p1 xy + p2 (r^2 + 2x^2) + sx1 r^2,
            # y += 2 p2 xy + p1 (r^2 + 2y^2) + sy1 r^2 (OpenCV's p1/p2 = Fisheye624's p1/p0 as defined there)
            f624 = dict(fx=p["fx"], fy=p["fy"], cx=p["cx"], cy=p["cy"], **{f"k{i}": 0.0 for i in range(6)},
                        p0=p["p2"], p1=p["p1"], s0=p["sx1"], s1=0.0, s2=p["sy1"], s3=0.0)
            return _fisheye624(where, width, height, f624)
        raise UnsupportedModelError(
            f"{where}: THIN_PRISM_FISHEYE with both radial (k1..k4 = {ks}) and tangential/thin-prism "
            f"(p1, p2, sx1, sy1 = {extra}) terms has no exact omnidl model: COLMAP applies the tangential and "
            "prism terms to the undistorted angle, Fisheye624 to the distorted one")
    if model == "RAD_TAN_THIN_PRISM_FISHEYE":
        return _fisheye624(where, width, height, p)
    if model in ("SIMPLE_DIVISION", "DIVISION"):
        return _division(where, width, height, p)
    if model == "FOV":
        return make("fov", where, **size, **p)
    if model == "EUCM":
        return make("eucm", where, **size, **p)
    if model == "EQUIRECTANGULAR":
        if (p["w"], p["h"]) != (width, height):
            raise UnsupportedModelError(f"{where}: EQUIRECTANGULAR with params (w, h) = ({p['w']}, {p['h']}) "
                                        f"differing from the image size {width}x{height} is not supported")
        return make("equirect", where, **size)
    raise UnsupportedModelError(f"{where}: COLMAP model {model} has no omnidl camera family")


def _division(where: str, width: int, height: int, p: dict[str, float]) -> Camera:
    """COLMAP's (SIMPLE_)DIVISION as the Scaramuzza camera with the same rays (see the module doc)."""
    if not p["fx"] > 0 or not p["fy"] > 0:
        raise ValueError(f"{where}: division model focal lengths must be > 0, got fx={p['fx']}, fy={p['fy']}")
    return make("scaramuzza", where, width=width, height=height, pol=(-p["fx"], 0.0, -p["k"] / p["fx"]), invpol=(),
                cx=p["cx"], cy=p["cy"], c=p["fy"] / p["fx"], d=0.0, e=0.0)


def _division_params(c: Camera) -> tuple[str, list[float]]:
    """``(model, params)`` of a Scaramuzza camera of the division form, else :class:`UnsupportedModelError`."""
    pol = tuple(c.pol) + (0.0,) * (3 - len(c.pol))
    why = []
    if len(c.pol) > 3 or pol[1] != 0:
        why.append(f"pol = {list(c.pol)} is not (a0, 0, a2)")
    if c.d != 0 or c.e != 0:
        why.append(f"the affine terms d = {c.d}, e = {c.e} are not 0")
    if c.invpol:
        why.append("it has an invpol (COLMAP stores none)")
    if why:
        raise unsupported(FORMAT, c, WRITES, "COLMAP holds a scaramuzza camera only as a division model (pol = (a0, 0, "
                          "a2), d = e = 0, no invpol); " + "; ".join(why))
    fx = -pol[0]
    k = -pol[2] * fx
    if c.c == 1:
        return "SIMPLE_DIVISION", [fx, c.cx, c.cy, k]
    return "DIVISION", [fx, c.c * fx, c.cx, c.cy, k]


def from_camera(camera: Camera) -> tuple[str, list[float]]:
    """``(model name, params)`` of the simplest COLMAP model that represents ``camera`` exactly."""
    fam = family_of(camera)
    c = camera
    if fam == "pinhole":
        return ("SIMPLE_PINHOLE", [c.fx, c.cx, c.cy]) if c.fx == c.fy else ("PINHOLE", [c.fx, c.fy, c.cx, c.cy])
    if fam == "opencv":
        if any((c.s1, c.s2, c.s3, c.s4)):
            raise unsupported(FORMAT, c, WRITES, "COLMAP's OpenCV models have no thin-prism s1..s4")
        high = any((c.k3, c.k4, c.k5, c.k6))
        if not high and c.p1 == 0 and c.p2 == 0 and c.fx == c.fy:
            return ("SIMPLE_RADIAL", [c.fx, c.cx, c.cy, c.k1]) if c.k2 == 0 else \
                ("RADIAL", [c.fx, c.cx, c.cy, c.k1, c.k2])
        base = [c.fx, c.fy, c.cx, c.cy, c.k1, c.k2, c.p1, c.p2]
        return ("FULL_OPENCV", base + [c.k3, c.k4, c.k5, c.k6]) if high else ("OPENCV", base)
    if fam == "kannala_brandt":
        if c.k0 != 1:
            raise unsupported(FORMAT, c, WRITES, f"COLMAP's fisheye models have k0 = 1, got k0 = {c.k0}")
        require_max_fov(c, {1: 1.0, 3: c.k1, 5: c.k2, 7: c.k3, 9: c.k4}, FORMAT, WRITES, "COLMAP's fisheye models")
        if c.fx == c.fy and c.k3 == 0 and c.k4 == 0:
            return ("SIMPLE_RADIAL_FISHEYE", [c.fx, c.cx, c.cy, c.k1]) if c.k2 == 0 else \
                ("RADIAL_FISHEYE", [c.fx, c.cx, c.cy, c.k1, c.k2])
        return "OPENCV_FISHEYE", [c.fx, c.fy, c.cx, c.cy, c.k1, c.k2, c.k3, c.k4]
    if fam == "fisheye624":
        require_max_fov(c, {1: 1.0, **{2 * i + 3: getattr(c, f"k{i}") for i in range(6)}}, FORMAT, WRITES,
                        "RAD_TAN_THIN_PRISM_FISHEYE")
        return "RAD_TAN_THIN_PRISM_FISHEYE", [getattr(c, n) for n in MODELS[11][1]]
    if fam == "fov":
        return "FOV", [c.fx, c.fy, c.cx, c.cy, c.omega]
    if fam == "eucm":
        return "EUCM", [c.fx, c.fy, c.cx, c.cy, c.alpha, c.beta]
    if fam == "scaramuzza":
        return _division_params(c)
    if fam == "equirect":
        if (c.lon_min, c.lon_max, c.lat_min, c.lat_max) != (-math.pi, math.pi, -math.pi / 2, math.pi / 2):
            raise unsupported(FORMAT, c, WRITES, "COLMAP's EQUIRECTANGULAR is the full sphere only")
        return "EQUIRECTANGULAR", [float(c.width), float(c.height)]
    raise unsupported(FORMAT, c, WRITES)


# -- files ---------------------------------------------------------------------------------------------
Row = tuple  # (model name, width, height, params, where)


def _rows(path: Path) -> dict[int, Row]:
    return _rows_bin(path) if path.suffix.lower() == ".bin" else _rows_txt(path)


def read_all(path: str | Path) -> dict[int, Camera]:
    """Every camera of a ``cameras.txt``/``cameras.bin`` as ``{camera_id: Camera}`` (file order)."""
    return {cid: to_camera(*row) for cid, row in _rows(Path(path)).items()}


def read(path: str | Path, camera: int | None = None) -> Camera:
    """The camera ``camera`` (a COLMAP camera id; default: the first) of a COLMAP cameras file."""
    return to_camera(*select(_rows(Path(path)), camera, f"COLMAP file {str(path)!r}"))


def _rows_txt(path: Path) -> dict[int, Row]:
    out: dict[int, Row] = {}
    for no, line in enumerate(path.read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        where = f"COLMAP file {str(path)!r} line {no}"
        tok = line.split()
        if len(tok) < 4:
            raise ValueError(f"{where}: expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]', got {line!r}")
        try:
            cid, params = int(tok[0]), [float(t) for t in tok[4:]]
        except ValueError as e:
            raise ValueError(f"{where}: non-numeric camera id or parameter ({e})") from None
        w, h = positive_int(tok[2], where, "WIDTH"), positive_int(tok[3], where, "HEIGHT")
        out[cid] = (tok[1], w, h, params, f"{where} (camera {cid})")
    return out


def _rows_bin(path: Path) -> dict[int, Row]:
    data = path.read_bytes()
    where = f"COLMAP file {str(path)!r}"
    if len(data) < 8:
        raise ValueError(f"{where}: too short for a cameras.bin (needs a uint64 camera count)")
    (n,), off = struct.unpack_from("<Q", data, 0), 8
    out: dict[int, Row] = {}
    for i in range(n):
        if off + 24 > len(data):
            raise ValueError(f"{where}: truncated at camera {i} of {n}")
        cid, mid, w, h = struct.unpack_from("<iiQQ", data, off)
        off += 24
        if mid not in MODELS:
            raise ValueError(f"{where}: camera {cid} has unknown model id {mid}; known: {sorted(MODELS)}")
        name, names = MODELS[mid]
        if off + 8 * len(names) > len(data):
            raise ValueError(f"{where}: truncated in the parameters of camera {cid}")
        params = list(struct.unpack_from(f"<{len(names)}d", data, off))
        off += 8 * len(names)
        out[cid] = (name, int(w), int(h), params, f"{where} (camera {cid})")
    if off != len(data):
        raise ValueError(f"{where}: {len(data) - off} bytes after the {n} cameras")
    return out


def _entries(cameras: Camera | Mapping[int, Camera]) -> list[tuple[int, str, int, int, list[float]]]:
    items = cameras.items() if isinstance(cameras, Mapping) else [(1, cameras)]
    out = []
    for cid, cam in items:
        model, params = from_camera(cam)
        out.append((int(cid), model, int(cam.width), int(cam.height), [float(v) for v in params]))
    return out


def dumps(cameras: Camera | Mapping[int, Camera], path: str | Path) -> bytes:
    """The bytes :func:`write` writes (``path`` only picks the layout by its suffix)."""
    path = Path(path)
    rows = _entries(cameras)
    if path.suffix.lower() == ".bin":
        blob = [struct.pack("<Q", len(rows))]
        for cid, model, w, h, params in rows:
            blob.append(struct.pack(f"<iiQQ{len(params)}d", cid, MODEL_IDS[model], w, h, *params))
        return b"".join(blob)
    lines = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
             f"# Number of cameras: {len(rows)}"]
    lines += [" ".join([str(cid), model, str(w), str(h)] + [repr(v) for v in params])
              for cid, model, w, h, params in rows]
    return ("\n".join(lines) + "\n").encode()


def write(cameras: Camera | Mapping[int, Camera], path: str | Path) -> None:
    """Write one camera (id 1) or ``{camera_id: Camera}`` as ``cameras.txt`` (``.bin`` suffix: binary)."""
    atomic_write_bytes(path, dumps(cameras, path))



def looks_like(text: str) -> bool:
    """True when the first data line of ``text`` is ``<int> <COLMAP MODEL> <int> <int> ...``."""
    for line in text.splitlines():
        s = line.strip()
        if s and not s.startswith("#"):
            tok = s.split()
            return len(tok) >= 4 and tok[0].lstrip("-").isdigit() and (tok[1] in MODEL_IDS or tok[1] in NOT_MODELS)
    return "CAMERA_ID, MODEL, WIDTH, HEIGHT" in text
