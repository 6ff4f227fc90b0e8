"""Robustness tables: camera parameters and calibration files (issue 14; reliability findings section 2).

Table 1 is the findings' section 2, row by row (``fNN-...``; rows marked *fixed* were silent garbage or
unclear crashes before the validation layer of :mod:`omnidl.cameras.validate`). Table 2 gives every
registered family NaN / inf / zero / negative / non-integer parameters and sizes. Table 3 corrupts a
calibration file of every :mod:`omnidl.cameras.io` format.
"""
from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import pytest
import torch

from omnidl.cameras import (CAMERA_CONFIG_DIR, Equirectangular, KannalaBrandt, Pinhole, Scaramuzza, build,
                            check_image_size, get_camera_class, io, list_cameras, resolve_camera)
from omnidl.cameras.validate import Domain

from .verdicts import ERROR, OK, SKIP, expect, row

KB_GOOD = "540 480 287 287 1080 960 195 0 0 0 0"


def kb_file(text: str | bytes, name: str = "kb.txt"):
    """A maker: write a KB calibration text (or bytes) to ``tmp/name`` and resolve it as a camera."""
    def make(tmp: Path):
        p = tmp / name
        p.write_bytes(text) if isinstance(text, bytes) else p.write_text(text)
        return resolve_camera(str(p))
    return make


def kb_values(**changes) -> str:
    names = ("cx", "cy", "fx", "fy", "w", "h", "fov", "k1", "k2", "k3", "k4")
    vals = dict(zip(names, KB_GOOD.split()))
    vals.update({k: str(v) for k, v in changes.items()})
    return " ".join(vals[n] for n in names)


def _ocam_text() -> str:
    import tempfile
    with tempfile.TemporaryDirectory() as d:
        return io.save(Scaramuzza.example(), Path(d) / "calib_results.txt", format="ocamcalib").read_text()


OCAM = _ocam_text()


def ocam_file(edit, then=None):
    """A maker: the saved OCamCalib file of ``Scaramuzza.example()`` edited by ``edit(text)``, loaded."""
    def make(tmp: Path):
        p = tmp / "calib_results.txt"
        p.write_text(edit(OCAM))
        cam = resolve_camera({"type": "scaramuzza", "calib_file": str(p)})
        return cam if then is None else then(cam)
    return make


def yaml_file(text: str):
    def make(tmp: Path):
        p = tmp / "cam.yaml"
        p.write_text(text)
        return resolve_camera(str(p))
    return make


def every_config(fn):
    """A maker: ``fn(camera)`` for every ``configs/camera`` YAML; each must raise the same kind of error
    (checked by re-raising the last one after asserting all raised)."""
    def make(tmp: Path):
        errors = []
        for path in sorted(CAMERA_CONFIG_DIR.glob("*.yaml")):
            cam = resolve_camera(str(path))
            try:
                fn(cam)
            except ValueError as e:
                errors.append(e)
            else:
                raise AssertionError(f"{path.name}: no error")
        raise errors[-1]
    return make


def project_all_configs(points):
    def make(tmp: Path):
        out = []
        for path in sorted(CAMERA_CONFIG_DIR.glob("*.yaml")):
            cam = resolve_camera(str(path))
            uv, valid = cam.project(points)
            rays = cam.unproject(torch.tensor([[math.nan, 1.0], [math.inf, 2.0], [3.0, -math.inf]],
                                              dtype=torch.float64))
            out.append((path.stem, uv, valid, rays))
        return out
    return make


def fisheye_dataset(width, height, kb_text=KB_GOOD):
    def make(tmp: Path):
        from omnidl.data.fisheye import FisheyeFromPanoramas
        p = tmp / "kb.txt"
        p.write_text(kb_text)
        return FisheyeFromPanoramas(camera=str(p), width=width, height=height,
                                    panoramas={"type": "synthetic", "width": 256, "height": 128, "length": 2},
                                    length=2)
    return make


def _all_finite_invalid(n_nan_rows: int):
    def check(out):
        for name, uv, valid, rays in out:
            assert torch.isfinite(uv).all(), name
            assert not valid[:n_nan_rows].any(), name
            assert torch.isfinite(rays.direction).all() and torch.isfinite(rays.origin).all(), name
            assert not rays.valid.any(), name
    return check


NAN, INF = math.nan, math.inf
D = torch.float64
SPECIAL_POINTS = torch.tensor([[NAN, 0, 1], [0, NAN, 1], [0, 0, NAN], [INF, 0, 1], [0, -INF, 1]], dtype=D)
TINY_POINTS = torch.tensor([[0.0, 0, 0], [1e-30, 0, 0], [0, -1e-300, 0]], dtype=D)
KB = r"Kannala-Brandt calibration file '.*kb\.txt'"

# -- table 1: findings section 2, row by row -----------------------------------------------------
FINDINGS = [
    row("f01-kb-10-values", kb_file("1 2 3 4 5 6 7 8 9 10"), None, verdict=ERROR,
        match=rf"{KB}: expected 11 values .*found 10"),
    row("f02-kb-12-values", kb_file(KB_GOOD + " 0"), None, verdict=ERROR, match=rf"{KB}: expected 11 .*found 12"),
    row("f03-kb-0-values", kb_file(""), None, verdict=ERROR, match=rf"{KB}: expected 11 values .*found 0"),
    row("f04-kb-fx-nan", kb_file(kb_values(fx="nan")), None, verdict=ERROR, match=rf"{KB}: .*fx.*nan"),
    row("f05-kb-cx-nan-fixed", kb_file(kb_values(cx="nan")), None, verdict=ERROR,
        match=rf"{KB}: kannala_brandt camera: cx must be finite .*got nan"),
    row("f05b-fisheye-dataset-kb-cx-nan-fixed", fisheye_dataset(135, 120, kb_values(cx="nan")), None,
        verdict=ERROR, match=rf"{KB}: kannala_brandt camera: cx must be finite .*got nan"),
    row("f06-kb-cy-inf-fixed", kb_file(kb_values(cy="inf")), None, verdict=ERROR,
        match=rf"{KB}: kannala_brandt camera: cy must be finite .*got inf"),
    row("f07-kb-k2-nan", kb_file(kb_values(k2="nan")), None, verdict=ERROR, match=rf"{KB}: .*k2 must be finite.*nan"),
    row("f08-kb-negative-focal", kb_file(kb_values(fx="-287")), None, verdict=ERROR,
        match=rf"{KB}: .*fx.* must be > 0.*-287"),
    row("f09-kb-fov-0", kb_file(kb_values(fov="0")), None, verdict=ERROR, match=rf"{KB}: .*max_fov must be in"),
    row("f10-kb-fov-400", kb_file(kb_values(fov="400")), None, verdict=ERROR, match=rf"{KB}: .*max_fov must be in"),
    row("f11-kb-fov-360", kb_file(kb_values(fov="360")), None, verdict=ERROR, match=rf"{KB}: .*max_fov must be in"),
    row("f12-kb-width-0", kb_file(kb_values(w="0")), None, verdict=ERROR,
        match=rf"{KB}: width must be a positive integer, got 0"),
    row("f13-kb-width-1080.5", kb_file(kb_values(w="1080.5")), None, verdict=ERROR,
        match=rf"{KB}: width must be a positive integer, got 1080.5"),
    row("f14-kb-missing", lambda tmp: resolve_camera(str(tmp / "nope.txt")), None, verdict=ERROR,
        match=r"'.*nope\.txt' does not exist"),
    row("f15-kb-nul-bytes", kb_file(b"\0" * 64), None, verdict=ERROR, match=rf"{KB}: not all entries are numbers"),
    row("f16-kb-non-utf8-fixed", kb_file(b"\xff\xfe\x80 540 480"), None, verdict=ERROR,
        match=rf"{KB} cannot be read as text: .*utf-8"),
    row("f17a-kb-fields-width-neg-fixed", lambda tmp: KannalaBrandt(width=-5, height=8, fx=5.0, fy=5.0), None,
        verdict=ERROR, match=r"kannala_brandt camera: width must be a positive integer .*got -5"),
    row("f17b-kb-fields-width-0-fixed", lambda tmp: build(type="kannala_brandt", width=0, height=8, fx=5.0, fy=5.0),
        None, verdict=ERROR, match=r"kannala_brandt camera: width must be a positive integer .*got 0"),
    row("f18-ocam-cut-in-half", ocam_file(lambda t: t[:len(t) // 2]), None, verdict=ERROR,
        match=r"OCamCalib file '.*calib_results\.txt': expected 5 data lines .*found 1"),
    row("f19-ocam-cut-mid-number-caught-by-size-check",
        ocam_file(lambda t: t.replace("\n64 64", "\n64 6"), lambda c: check_image_size((64, 64), c)), None,
        verdict=ERROR, match=r"64x64 \(W x H\) disagrees with the calibration \(6x64\)"),
    row("f20-ocam-no-size-line", ocam_file(lambda t: t.replace("\n64 64", "")), None, verdict=ERROR,
        match=r"OCamCalib file '.*': expected 5 data lines .*found 4"),
    row("f21-ocam-pol-count", ocam_file(lambda t: t.replace("\n5 ", "\n6 ", 1)), None, verdict=ERROR,
        match=r"OCamCalib file '.*': the pol line must start with its number of coefficients"),
    row("f22-ocam-nan-pol-fixed", ocam_file(lambda t: t.replace("0.02385944", "nan")), None, verdict=ERROR,
        match=r"OCamCalib file '.*calib_results\.txt': scaramuzza camera: pol must hold finite numbers only, got nan"),
    row("f23-ocam-nan-centre-fixed", ocam_file(lambda t: t.replace("31.9 31.2", "nan 31.2")), None, verdict=ERROR,
        match=r"OCamCalib file '.*': scaramuzza camera: cy must be finite .*got nan"),
    row("f24-ocam-size-0-fixed", ocam_file(lambda t: t.replace("\n64 64", "\n0 0")), None, verdict=ERROR,
        match=r"OCamCalib file '.*': image size line: height must be a positive integer, got 0"),
    row("f25-ocam-size-float-fixed", ocam_file(lambda t: t.replace("\n64 64", "\n480.7 640.2")), None,
        verdict=ERROR, match=r"OCamCalib file '.*': image size line: height must be a positive integer, got 480.7"),
    row("f26-ocam-singular-affine", ocam_file(lambda t: t.replace("1.002 0.003 -0.002", "0 0 0")), None,
        verdict=ERROR, match=r"OCamCalib file '.*': .*singular affine matrix \(c - d\*e = 0\)"),
    row("f27-ocam-invpol-0-coefficients", ocam_file(lambda t: t), "invpol_fitted", verdict=OK),
    row("f28-ocam-extra-garbage-line", ocam_file(lambda t: t + "\n1 2 3 garbage\n"), "same_as_example", verdict=OK),
    row("f29-yaml-unknown-key", yaml_file("type: pinhole\nwidth: 8\nheight: 8\nfoo: 1\n"), None, verdict=ERROR,
        match=r"camera type 'pinhole': unknown field\(s\) \['foo'\]"),
    row("f30-yaml-fx-abc-fixed", yaml_file("type: pinhole\nwidth: 8\nheight: 8\nfx: abc\n"), None, verdict=ERROR,
        match=r"pinhole camera: fx must be finite \(a real number\), got 'abc' \(str\)"),
    row("f31-yaml-width-string-fixed", yaml_file("type: pinhole\nwidth: '64'\nheight: 8\n"), None, verdict=ERROR,
        match=r"pinhole camera: width must be a positive integer .*got '64' \(str\)"),
    row("f32-yaml-width-64.7-fixed", yaml_file("type: pinhole\nwidth: 64.7\nheight: 48\n"), None, verdict=ERROR,
        match=r"pinhole camera: width must be a positive integer .*got 64.7"),
    row("f33-yaml-no-type", yaml_file("width: 8\nheight: 8\n"), None, verdict=ERROR,
        match=r"cam\.yaml: expected a mapping with a 'type' field"),
    row("f34-yaml-unknown-type", yaml_file("type: foocam\nwidth: 8\n"), None, verdict=ERROR,
        match=r"unknown camera type 'foocam'; known:"),
    row("f35-yaml-syntax-error", yaml_file("type: [pinhole\n"), None, verdict=ERROR,
        match=r"cam\.yaml: cannot read it as YAML"),
    row("f36-pinhole-fx-0-fixed", yaml_file("type: pinhole\nwidth: 8\nheight: 8\nfx: 0\nfy: 5\n"), None,
        verdict=ERROR, match=r"pinhole camera: fx must be > 0, got 0"),
    row("f37-pinhole-fx-neg-fixed", yaml_file("type: pinhole\nwidth: 8\nheight: 8\nfx: -50\nfy: 5\n"), None,
        verdict=ERROR, match=r"pinhole camera: fx must be > 0, got -50"),
    row("f38a-equirect-width-0-fixed", yaml_file("type: equirect\nwidth: 0\nheight: 8\n"), None, verdict=ERROR,
        match=r"equirect camera: width must be a positive integer .*got 0"),
    row("f38b-equirect-width-neg-fixed", yaml_file("type: equirect\nwidth: -8\nheight: 8\n"), None, verdict=ERROR,
        match=r"equirect camera: width must be a positive integer .*got -8"),
    row("f39-unified-xi-nan", yaml_file("type: unified\nwidth: 8\nheight: 8\nxi: .nan\n"), None, verdict=ERROR,
        match=r"unified camera: xi must be .*nan"),
    row("f40-fisheye-max-fov-0", yaml_file("type: fisheye\nwidth: 8\nheight: 8\nmax_fov: 0\n"), None,
        verdict=ERROR, match=r"fisheye camera: max_fov"),
    row("f41-project-nan-inf-every-config-fixed", project_all_configs(SPECIAL_POINTS), "finite_invalid_3",
        verdict=OK),
    row("f42-project-origin-tiny-every-config", project_all_configs(TINY_POINTS), "finite_invalid_3", verdict=OK),
    row("f43-resized-0x0-every-config-fixed", every_config(lambda c: c.resized(0, 0)), None, verdict=ERROR,
        match=r"camera: resized\(0, 0\): width must be a positive integer"),
    row("f44-resized-negative-every-config-fixed", every_config(lambda c: c.resized(-4, -2)), None, verdict=ERROR,
        match=r"camera: resized\(-4, -2\): width must be a positive integer .*got -4"),
    row("f45-fisheye-dataset-0x0-fixed", fisheye_dataset(0, 0), None, verdict=ERROR,
        match=r"image size 0x0 \(W x H\): width must be a positive integer"),
    row("f46-fisheye-dataset-aspect", fisheye_dataset(200, 50), None, verdict=ERROR,
        match=r"200x50 \(W x H\) disagrees with the calibration of '.*kb\.txt' \(1080x960\)"),
]


def _check_ok(kind, out):
    if kind == "invpol_fitted":
        assert out.invpol == () and out.project(torch.tensor([[0.1, 0.2, 1.0]], dtype=D))[1].all()
    elif kind == "same_as_example":
        assert out.pol == pytest.approx(Scaramuzza.example().pol) and (out.width, out.height) == (64, 64)
    elif kind == "finite_invalid_3":
        _all_finite_invalid(3)(out)
    else:  # pragma: no cover
        raise AssertionError(kind)


@pytest.mark.parametrize("make,check,verdict,match", FINDINGS)
def test_findings_cameras(make, check, verdict, match, tmp_path):
    out = expect(lambda: make(tmp_path), verdict, match)
    if verdict == OK:
        _check_ok(check, out)


# -- table 2: every registered family, bad parameters --------------------------------------------
def _first_float(cls) -> str:
    return next(f.name for f in dataclasses.fields(cls) if str(f.type).replace(" ", "") == "float")


def _outside(dom: Domain) -> float:
    if math.isfinite(dom.lo):
        return dom.lo - 1.0 if dom.lo_closed else dom.lo
    return dom.hi + 1.0 if dom.hi_closed else dom.hi


def _family_rows():
    rows = []
    for name in list_cameras():
        cls = get_camera_class(name)
        f = _first_float(cls)
        for tag, value in (("nan", NAN), ("inf", INF), ("neg-inf", -INF)):
            rows.append(row(f"{name}-{f}-{tag}", name, {f: value}, verdict=ERROR,
                            match=rf"{name} camera: {f} must be finite .*got -?(nan|inf)"))
        for side, value in (("width", 0), ("height", -8), ("width", 64.7)):
            rows.append(row(f"{name}-{side}-{value}", name, {side: value}, verdict=ERROR,
                            match=rf"{name} camera: {side} must be a positive integer .*got {value}"))
        for field, dom in cls.domains.items():
            bad = _outside(dom)
            rows.append(row(f"{name}-{field}-{bad:g}", name, {field: bad}, verdict=ERROR,
                            match=rf"{name}.*{field}.*{bad:g}"))
        rows.append(row(f"{name}-resized-0x0", name, "resized(0, 0)", verdict=ERROR,
                        match=rf"{name} camera: resized\(0, 0\): width must be a positive integer"))
        rows.append(row(f"{name}-resized-float", name, "resized(8.5, 4)", verdict=ERROR,
                        match=rf"{name} camera: resized\(8.5, 4\): width must be a positive integer .*8.5"))
        rows.append(row(f"{name}-example-ok", name, {}, verdict=OK))
    return rows


@pytest.mark.parametrize("name,change,verdict,match", _family_rows())
def test_family_parameters(name, change, verdict, match):
    ex = get_camera_class(name).example()
    if isinstance(change, str):
        w, h = (float(v) if "." in v else int(v) for v in change[len("resized("):-1].split(", "))
        expect(lambda: ex.resized(w, h), verdict, match)
        return
    out = expect(lambda: dataclasses.replace(ex, **change), verdict, match)
    if verdict == OK:
        assert out == ex and hash(out) == hash(ex)


# -- table 3: calibration files of every io format -----------------------------------------------
PINHOLE = Pinhole(width=64, height=48, fx=50.0, fy=50.0, cx=32.0, cy=24.0)
WOODSCAPE = {"intrinsic": {"model": "radial_poly", "poly_order": 4, "k1": 339.749, "k2": -31.988, "k3": 48.275,
                           "k4": -7.201, "cx_offset": 3.942, "cy_offset": -3.02, "aspect_ratio": 1.0,
                           "width": 1280, "height": 966}}


def saved(fmt: str, name: str, edit, camera=PINHOLE, binary: bool = False):
    """A maker: ``camera`` saved as ``fmt`` to ``tmp/name``, edited by ``edit(text)``, loaded by ``io.load``."""
    def make(tmp: Path):
        p = io.save(camera, tmp / name, format=fmt)
        text = p.read_text()
        p.write_bytes(edit(text)) if binary else p.write_text(edit(text))
        return io.load(p)
    return make


def woodscape(**changes):
    def make(tmp: Path):
        d = json.loads(json.dumps(WOODSCAPE))
        d["intrinsic"].update(changes)
        p = tmp / "front.json"
        p.write_text(json.dumps(d))
        return io.load(p)
    return make


COLMAP = r"COLMAP file '.*cameras\.txt' line 4"
KALIBR = r"Kalibr camchain '.*camchain\.yaml' node 'cam0'"
OPENCV = r"OpenCV FileStorage file '.*cv\.yaml'"
ORB = r"ORB-SLAM3 settings '.*orb\.yaml'"
OCAMF = r"OCamCalib file '.*calib_results\.txt'"
WS = r"WoodScape calibration file '.*front\.json'"
KBT = r"Kannala-Brandt calibration file '.*kb\.txt'|invalid kannala_brandt calibration"

CALIB_FILES = [
    row("colmap-fx-nan", saved("colmap", "cameras.txt", lambda t: t.replace("64 48 50.0", "64 48 nan")), verdict=ERROR,
        match=rf"{COLMAP} .*pinhole camera: fx must be finite .*nan"),
    row("colmap-fx-0", saved("colmap", "cameras.txt", lambda t: t.replace("64 48 50.0", "64 48 0")), verdict=ERROR,
        match=rf"{COLMAP} .*pinhole camera: fx must be > 0, got 0"),
    row("colmap-fx-neg", saved("colmap", "cameras.txt", lambda t: t.replace("64 48 50.0", "64 48 -50")),
        verdict=ERROR, match=rf"{COLMAP} .*fx must be > 0, got -50"),
    row("colmap-cx-inf", saved("colmap", "cameras.txt", lambda t: t.replace("32.0 24.0", "inf 24.0")), verdict=ERROR,
        match=rf"{COLMAP} .*cx must be finite .*inf"),
    row("colmap-width-0", saved("colmap", "cameras.txt", lambda t: t.replace("64 48 50.0", "0 48 50.0")),
        verdict=ERROR, match=rf"{COLMAP}: WIDTH must be a positive integer, got '0'"),
    row("colmap-truncated-params", saved("colmap", "cameras.txt", lambda t: t.replace("50.0 32.0 24.0", "50.0")),
        verdict=ERROR, match=rf"{COLMAP} .*SIMPLE_PINHOLE needs 3 parameters .*got 1"),
    row("colmap-non-utf8", saved("colmap", "cameras.txt", lambda t: t.encode() + b"\xff\xfe", binary=True),
        verdict=ERROR, match=r"calibration file '.*cameras\.txt': cannot read it as text"),
    row("kalibr-fx-nan", saved("kalibr", "camchain.yaml", lambda t: t.replace("[50.0, 50.0", "[.nan, 50.0")),
        verdict=ERROR, match=rf"{KALIBR}: .*fx must be finite .*nan"),
    row("kalibr-fx-0", saved("kalibr", "camchain.yaml", lambda t: t.replace("[50.0, 50.0", "[0.0, 50.0")),
        verdict=ERROR, match=rf"{KALIBR}: .*fx must be > 0, got 0"),
    row("kalibr-cx-inf", saved("kalibr", "camchain.yaml", lambda t: t.replace("31.5, 23.5]", ".inf, 23.5]")),
        verdict=ERROR, match=rf"{KALIBR}: .*cx must be finite .*inf"),
    row("kalibr-resolution-0", saved("kalibr", "camchain.yaml", lambda t: t.replace("[64, 48]", "[0, 48]")),
        verdict=ERROR, match=rf"{KALIBR}: resolution\[0\] must be a positive integer, got 0"),
    row("kalibr-3-intrinsics", saved("kalibr", "camchain.yaml", lambda t: t.replace(", 23.5]", "]")),
        verdict=ERROR, match=rf"{KALIBR}: pinhole intrinsics are \[fu, fv, pu, pv\], got 3 values"),
    row("opencv-fx-nan", saved("opencv", "cv.yaml", lambda t: t.replace("data: [ 50.0, 0.0", "data: [ .nan, 0.0")),
        verdict=ERROR, match=rf"{OPENCV}: .*fx must be finite .*nan"),
    row("opencv-fx-0", saved("opencv", "cv.yaml", lambda t: t.replace("data: [ 50.0, 0.0", "data: [ 0.0, 0.0")),
        verdict=ERROR, match=rf"{OPENCV}: .*fx must be > 0, got 0"),
    row("opencv-k1-nan", saved("opencv", "cv.yaml", lambda t: t.replace("data: [ 0.0, 0.0, 0.0, 0.0, 0.0 ]",
                                                                         "data: [ .nan, 0.0, 0.0, 0.0, 0.0 ]")),
        verdict=ERROR, match=rf"{OPENCV}: .*opencv camera: k1 must be finite .*nan"),
    row("opencv-width-0", saved("opencv", "cv.yaml", lambda t: t.replace("image_width: 64", "image_width: 0")),
        verdict=ERROR, match=rf"{OPENCV}: image_width must be a positive integer, got 0"),
    row("opencv-cut-in-half", saved("opencv", "cv.yaml", lambda t: t[:len(t) // 2]), verdict=ERROR,
        match=r"calibration file '.*cv\.yaml': format not recognised"),
    row("orbslam3-fx-nan", saved("orbslam3", "orb.yaml", lambda t: t.replace("Camera1.fx: 50.0", "Camera1.fx: .nan")),
        verdict=ERROR, match=rf"{ORB}: .*fx must be finite .*nan"),
    row("orbslam3-fx-0", saved("orbslam3", "orb.yaml", lambda t: t.replace("Camera1.fx: 50.0", "Camera1.fx: 0.0")),
        verdict=ERROR, match=rf"{ORB}: .*fx must be > 0, got 0"),
    row("orbslam3-cy-inf", saved("orbslam3", "orb.yaml", lambda t: t.replace("Camera1.cy: 23.5", "Camera1.cy: .inf")),
        verdict=ERROR, match=rf"{ORB}: .*cy must be finite .*inf"),
    row("orbslam3-width-0", saved("orbslam3", "orb.yaml", lambda t: t.replace("Camera.width: 64", "Camera.width: 0")),
        verdict=ERROR, match=rf"{ORB}: Camera.width must be a positive integer, got 0"),
    row("orbslam3-missing-cy", saved("orbslam3", "orb.yaml", lambda t: t.replace("Camera1.cy: 23.5\n", "")),
        verdict=ERROR, match=rf"{ORB}: missing Camera1.cy"),
    row("ocamcalib-io-nan-pol", saved("ocamcalib", "calib_results.txt", lambda t: t.replace("0.02385944", "nan"),
                                      camera=Scaramuzza.example()),
        verdict=ERROR, match=rf"{OCAMF}: .*pol must hold finite numbers only"),
    row("ocamcalib-io-size-0", saved("ocamcalib", "calib_results.txt", lambda t: t.replace("\n64 64", "\n0 0"),
                                     camera=Scaramuzza.example()),
        verdict=ERROR, match=rf"{OCAMF}: image size line: height must be a positive integer, got 0"),
    row("ocamcalib-io-non-utf8", saved("ocamcalib", "calib_results.txt", lambda t: b"\xff\xfe" + t.encode(),
                                       camera=Scaramuzza.example(), binary=True),
        verdict=ERROR, match=r"calibration file '.*calib_results\.txt': cannot read it as text"),
    row("kb-txt-io-cx-nan", saved("kb_txt", "kb.txt", lambda t: "nan" + t[t.index("\n"):],
                                  camera=KannalaBrandt.example()),
        verdict=ERROR, match=rf"({KBT}).*cx must be finite .*nan"),
    row("kb-txt-io-fx-0", saved("kb_txt", "kb.txt", lambda t: t.replace("\n17.0\n", "\n0\n"),
                                camera=KannalaBrandt.example()),
        verdict=ERROR, match=rf"({KBT}).*fx.*must be > 0"),
    row("woodscape-k1-nan", woodscape(k1=NAN), verdict=ERROR, match=rf"{WS}: .*k1 must be finite .*nan"),
    row("woodscape-k1-0", woodscape(k1=0), verdict=ERROR, match=rf"{WS}: .*k1 must be > 0"),
    row("woodscape-cx-inf", woodscape(cx_offset=INF), verdict=ERROR, match=rf"{WS}: .*cx_offset must be finite .*inf"),
    row("woodscape-aspect-0", woodscape(aspect_ratio=0.0), verdict=ERROR, match=rf"{WS}: .*aspect_ratio must be > 0"),
    row("woodscape-width-0", woodscape(width=0), verdict=ERROR,
        match=rf"{WS}: intrinsic.width must be a positive integer, got 0"),
    row("woodscape-k1-string", woodscape(k1="abc"), verdict=ERROR, match=rf"{WS}: intrinsic.k1 must be a number"),
    row("omnidl-yaml-io-fx-nan", saved("omnidl", "cam.yaml", lambda t: t.replace("fx: 50.0", "fx: .nan")),
        verdict=ERROR, match=r"pinhole camera: fx must be finite .*nan"),
    row("colmap-roundtrip-ok", saved("colmap", "cameras.txt", lambda t: t), verdict=OK),
    row("kalibr-roundtrip-ok", saved("kalibr", "camchain.yaml", lambda t: t), verdict=OK),
    row("opencv-roundtrip-ok", saved("opencv", "cv.yaml", lambda t: t), verdict=OK),
    row("orbslam3-roundtrip-ok", saved("orbslam3", "orb.yaml", lambda t: t), verdict=OK),
]


@pytest.mark.parametrize("make,verdict,match", CALIB_FILES)
def test_calibration_files(make, verdict, match, tmp_path):
    out = expect(lambda: make(tmp_path), verdict, match)
    if verdict == OK:
        assert out == PINHOLE


def test_resized_equirect_is_a_full_panorama_again():
    """A valid resize still works after the checks (OK control)."""
    cam = Equirectangular(width=64, height=32).resized(32, 16)
    assert cam.wraps_horizontally and cam.size == (32, 16)


# -- table 4: plausibility at the loaders, new interchange inputs (issues 48 item 4, 49 item 3) -----------------
def text_file(name: str, text: str, **load_kwargs):
    """A maker: ``text`` written to ``tmp/name`` and loaded by ``io.load``."""
    def make(tmp: Path):
        p = tmp / name
        p.write_text(text)
        return io.load(p, **load_kwargs)
    return make


def colmap_row(model: str, w: int, h: int, params: str) -> str:
    return f"# Camera list with one line of data per camera:\n1 {model} {w} {h} {params}\n"


def kalibr_node(intrinsics: str, dist: str = "radtan", coeffs: str = "[-0.28, 0.07, 0.0002, 0.00002]",
                res: str = "[752, 480]", header: str = "") -> str:
    return (f"{header}cam0:\n  camera_model: pinhole\n  intrinsics: {intrinsics}\n  distortion_model: {dist}\n"
            f"  distortion_coeffs: {coeffs}\n  rostopic: /cam0/image_raw\n  resolution: {res}\n")


def tutorial(width="640", height="480", k="6.57e+002, 0., 3.195e+002, 0., 6.57e+002, 2.395e+002, 0., 0., 1."):
    return ("%YAML:1.0\ncalibration_Time: \"08/19/11 20:44:38\"\n"
            f"image_Width: {width}\nimage_Height: {height}\nflagValue: 14\n"
            f"Camera_Matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ {k} ]\n"
            "Distortion_Coefficients: !!opencv-matrix\n   rows: 5\n   cols: 1\n   dt: d\n"
            "   data: [ -0.418, 0.507, 0., 0., -0.578 ]\n")


PLAUS = r"calibration file '.*{}': the principal point \(cx, cy\) = \({}\) lies outside the {} image"
KAL = r"Kalibr camchain '.*camchain\.yaml' node 'cam0'"
PLAUSIBILITY = [
    row("p01-colmap-principal-point-outside", text_file("cameras.txt", colmap_row("PINHOLE", 640, 480,
                                                                                  "300 300 900 240")),
        verdict=SKIP, match=PLAUS.format(r"cameras\.txt", "900, 240", "640x480")),
    row("p02-kalibr-principal-point-negative",
        text_file("camchain.yaml", kalibr_node("[458.6, 457.3, -20.5, 248.4]")), verdict=SKIP,
        match=PLAUS.format(r"camchain\.yaml", "-20, 248.9", "752x480")),
    row("p03-opencv-tutorial-width-height-swapped", text_file("out_camera_data.yml", tutorial("480", "640",
        "6.57e+002, 0., 6.395e+002, 0., 6.57e+002, 2.395e+002, 0., 0., 1.")), verdict=SKIP,
        match=PLAUS.format(r"out_camera_data\.yml", "640, 240", "480x640") + r".*swapped"),
    row("p04-kb-txt-fov-in-radians", text_file("kb.txt", "540 480 287 287 1080 960 3.4 0 0 0 0"), verdict=ERROR,
        match=r"Kannala-Brandt calibration file '.*kb\.txt': FOV \(7th value\) = 3\.4 deg is under 10 deg.*"
              r"3\.4 rad = 194\.8 deg"),
    row("p05-omnidl-yaml-max-fov-tiny", text_file("cam.yaml", "type: kannala_brandt\nwidth: 64\nheight: 64\nfx: 17.0\n"
                                                  "fy: 17.0\ncx: 32.0\ncy: 32.0\nmax_fov: 0.1\n"), verdict=SKIP,
        match=r"cam\.yaml': kannala_brandt max_fov = 0\.1 rad \(5\.73 deg\) is under 10 deg"),
    row("p06-kalibr-yaml-header-fx-inf", text_file("camchain.yaml", kalibr_node("[.inf, 457.3, 367.2, 248.4]",
                                                                               header="%YAML:1.0\n---\n")),
        verdict=ERROR, match=rf"{KAL}: .*fx must be finite .*inf"),
    row("p07-kalibr-resolution-0", text_file("camchain.yaml", kalibr_node("[458.6, 457.3, 367.2, 248.4]",
                                                                         res="[0, 480]")),
        verdict=ERROR, match=rf"{KAL}: resolution\[0\] must be a positive integer, got 0"),
    row("p08-kalibr-equidistant-3-coeffs", text_file("camchain.yaml", kalibr_node(
        "[458.6, 457.3, 367.2, 248.4]", "equidistant", "[0.01, 0.002, 0.0003]")), verdict=ERROR,
        match=rf"{KAL}: equidistant distortion_coeffs are \[k1, k2, k3, k4\], got 3 values"),
    row("p09-kalibr-intrinsics-not-numbers", text_file("camchain.yaml", kalibr_node("[fu, 457.3, 367.2, 248.4]")),
        verdict=ERROR, match=rf"{KAL}: intrinsics .* must be numbers"),
    row("p10-opencv-tutorial-width-0", text_file("out_camera_data.yml", tutorial("0")), verdict=ERROR,
        match=r"OpenCV FileStorage file '.*out_camera_data\.yml': image_Width must be a positive integer, got 0"),
    row("p11-opencv-tutorial-fx-nan", text_file("out_camera_data.yml", tutorial(
        k=".nan, 0., 3.195e+002, 0., 6.57e+002, 2.395e+002, 0., 0., 1.")), verdict=ERROR,
        match=r"OpenCV FileStorage file '.*out_camera_data\.yml': .*fx must be finite .*nan"),
    row("p12-colmap-division-fx-0", text_file("cameras.txt", colmap_row("DIVISION", 640, 480, "0 300 320 240 -0.1")),
        verdict=ERROR, match=r"COLMAP file '.*cameras\.txt' line 2 .*division model focal lengths must be > 0"),
    row("p13-colmap-division-k-nan", text_file("cameras.txt", colmap_row("SIMPLE_DIVISION", 640, 480,
                                                                          "300 320 240 nan")),
        verdict=ERROR, match=r"COLMAP file '.*cameras\.txt' line 2 .*scaramuzza camera: pol must hold finite numbers"),
    row("p14-colmap-spherical-is-not-a-model", text_file("cameras.txt", colmap_row("SPHERICAL", 640, 320, "640 320")),
        verdict=ERROR, match=r"COLMAP has no camera model 'SPHERICAL'.*EQUIRECTANGULAR \(model id 17"),
    row("p15-yaml-python-object-tag", text_file("cam.yaml", "type: !!python/object/apply:os.getcwd []\n"),
        verdict=ERROR, match=r"cam\.yaml.*refused: the YAML tag '!!python/object/apply:os\.getcwd' would construct"),
    row("p16-kalibr-python-name-tag", text_file("camchain.yaml", "cam0: !!python/name:os.system\n"), verdict=ERROR,
        match=r"camchain\.yaml.*refused: the YAML tag '!!python/name:os\.system'"),
    row("p17-kalibr-equidistant-ok", text_file("camchain.yaml", kalibr_node(
        "[190.97, 190.97, 254.93, 256.89]", "equidistant", "[0.0034, 0.0007, -0.0020, 0.0002]", "[512, 512]")),
        verdict=OK),
    row("p18-opencv-tutorial-ok", text_file("out_camera_data.yml", tutorial()), verdict=OK),
    row("p19-colmap-division-ok", text_file("cameras.txt", colmap_row("DIVISION", 640, 480, "300 301 320 240 -0.1")),
        verdict=OK),
]


@pytest.mark.parametrize("make,verdict,match", PLAUSIBILITY)
def test_plausibility_and_new_interchange_inputs(make, verdict, match, tmp_path):
    import warnings
    with warnings.catch_warnings():
        if verdict == OK:  # OK rows load without an ImplausibleCalibrationWarning
            warnings.simplefilter("error", io.ImplausibleCalibrationWarning)
        out = expect(lambda: make(tmp_path), verdict, match)
    assert verdict == ERROR or torch.isfinite(out.project(torch.tensor([[0.0, 0.0, 1.0]], dtype=D))[0]).all()
