"""Robustness table: panorama resampling and the reproject command line (issue 14).

Depth maps with holes (0 = no measurement) must not be blended into valid ranges: ``mode="masked"`` (the
reproject CLI's ``--depth``) interpolates over the valid taps only. Bad geometry inputs get clear errors.
"""
from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from omnidl.apps.reproject import main as reproject_cli
from omnidl.cameras import Equirectangular, Pinhole
from omnidl.geometry import euler_to_matrix, reproject, rotate_panorama

from .verdicts import ERROR, OK, expect, row

D = torch.float64
PANO = Equirectangular(width=64, height=32)
PIN = Pinhole.from_fov(16, 12, math.radians(70))


def holes_depth(dtype=torch.float32) -> torch.Tensor:
    """``(1, 1, 32, 64)`` piecewise-constant ranges {2, 5} m with holes (0)."""
    d = torch.full((1, 1, 32, 64), 2.0, dtype=dtype)
    d[..., :, 32:] = 5.0
    d[..., 6:12, 10:22] = 0.0
    d[..., 20:27, 40:50] = 0.0
    d[..., 15, 5] = 0.0
    return d


def R(*deg):
    return euler_to_matrix(*(torch.tensor(math.radians(a), dtype=D) for a in deg))


def _no_blend(out):
    """Valid outputs lie in [2, 5] (between valid neighbours), invalid ones are 0."""
    img, valid = out
    assert ((img[valid] >= 2.0 - 1e-6) & (img[valid] <= 5.0 + 1e-6)).all()
    assert (img[~valid] == 0).all()


def _exact_constant(out):
    img, valid = out
    assert valid.any() and (img[valid] == 2.0).all() and (img[~valid] == 0).all()


def _constant_depth():
    d = holes_depth()
    d[d > 0] = 2.0
    return d


ROWS = [
    row("rotate-depth-masked-no-blend-fixed", lambda tmp: rotate_panorama(holes_depth(), R(3, -7, 21), mode="masked",
                                                                      cache=False), _no_blend, verdict=OK),
    row("rotate-depth-invalid0-means-masked", lambda tmp: rotate_panorama(holes_depth(), R(0, 4, 33), invalid=0.0,
                                                                      cache=False), _no_blend, verdict=OK),
    row("reproject-depth-masked-pinhole", lambda tmp: reproject(holes_depth(), PANO, PIN, R(0, -30, 60),
                                                            mode="masked", cache=False), _no_blend, verdict=OK),
    row("rotate-depth-masked-exact-constant", lambda tmp: rotate_panorama(_constant_depth(), R(2, 9, 13),
                                                                      mode="masked", cache=False),
        _exact_constant, verdict=OK),
    row("rotate-bad-mode", lambda tmp: rotate_panorama(holes_depth(), R(0, 0, 1), mode="cubic"), None,
        verdict=ERROR, match=r"mode must be one of \('bilinear', 'nearest', 'masked'\), got 'cubic'"),
    row("masked-integer-image", lambda tmp: rotate_panorama(holes_depth().long(), R(0, 0, 1), mode="masked"), None,
        verdict=ERROR, match=r"masked sampling needs a floating image, got torch.int64"),
    row("rotate-nan-rotation", lambda tmp: rotate_panorama(holes_depth(), torch.full((3, 3), math.nan)), None,
        verdict=ERROR, match=r"rotation contains NaN or inf"),
    row("rotate-rotation-shape", lambda tmp: rotate_panorama(holes_depth(), torch.eye(2)), None, verdict=ERROR,
        match=r"rotation must have shape \(3, 3\) or \(B, 3, 3\), got \(2, 2\)"),
    row("rotate-1d-image", lambda tmp: rotate_panorama(torch.zeros(8), R(0, 0, 1)), None, verdict=ERROR,
        match=r"image must have shape .*got \(8,\)"),
    row("reproject-size-mismatch", lambda tmp: reproject(torch.zeros(1, 1, 30, 64), PANO, PIN), None,
        verdict=ERROR, match=r"image is 64x30 \(WxH\) but the source camera is 64x32"),
]


@pytest.mark.parametrize("make,check,verdict,match", ROWS)
def test_resampling(make, check, verdict, match, tmp_path):
    out = expect(lambda: make(tmp_path), verdict, match)
    if verdict == OK:
        check(out)


# -- the reproject CLI --------------------------------------------------------------------------------
def write_depth(tmp: Path, width: int = 64, height: int = 32) -> Path:
    d = (holes_depth()[0, 0].numpy() * 1000).astype(np.uint16)          # millimetres, 0 = hole
    if (width, height) != (64, 32):
        d = cv2.resize(d, (width, height), interpolation=cv2.INTER_NEAREST)
    p = tmp / "depth.png"
    cv2.imwrite(str(p), d)
    return p


def cli(*extra, size=(64, 32)):
    def make(tmp: Path):
        src = write_depth(tmp, *size)
        out = tmp / "out.png"
        rc = reproject_cli(["--src", str(src), "--dst-camera", "equirect", "--out", str(out), *extra])
        if rc != 0:
            raise RuntimeError(f"exit status {rc}")
        return cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    return make


def cli_error(*extra, size=(64, 32)):
    """A maker: the CLI's exit status 2 and its stderr message become a ValueError."""
    def make(tmp: Path):
        import contextlib
        import io
        src = write_depth(tmp, *size)
        err = io.StringIO()
        with contextlib.redirect_stderr(err):
            rc = reproject_cli(["--src", str(src), "--dst-camera", "equirect", *extra])
        if rc == 2:
            raise ValueError(err.getvalue())
        return rc
    return make


def _cli_no_blend(out):
    assert out.dtype == np.uint16
    valid = out > 0
    assert valid.any() and (out[valid] >= 2000).all() and (out[valid] <= 5000).all()


def _cli_blends(out):
    """Without --depth (plain bilinear) the holes leak: the documented behaviour for images."""
    assert ((out > 0) & (out < 2000)).any()


CLI_ROWS = [
    row("cli-depth-masked-no-blend-fixed", cli("--depth", "--rotation", "2,5,11"), _cli_no_blend, verdict=OK),
    row("cli-invalid-value-masked", cli("--invalid", "0", "--rotation", "0,0,7"), _cli_no_blend, verdict=OK),
    row("cli-depth-nearest-keeps-values", cli("--depth", "--mode", "nearest", "--rotation", "1,2,3"),
        lambda out: set(np.unique(out)) <= {0, 2000, 5000}, verdict=OK),
    row("cli-image-bilinear-default", cli("--rotation", "2,5,11"), _cli_blends, verdict=OK),
    row("cli-depth-with-bilinear", cli_error("--out", "o.png", "--depth", "--mode", "bilinear"), None, verdict=ERROR,
        match=r"--mode bilinear blends the invalid value into valid pixels"),
    row("cli-non-panorama-source-fixed", cli_error("--out", "o.png", size=(64, 64)), None, verdict=ERROR,
        match=r"source image '.*depth\.png' is 64x64 \(W x H\); a full equirectangular panorama is 2:1"),
    row("cli-unknown-output-suffix-fixed", cli_error("--out", "o.xyz"), None, verdict=ERROR,
        match=r"--out 'o\.xyz': OpenCV has no image writer for the suffix '\.xyz'"),
]


@pytest.mark.parametrize("make,check,verdict,match", CLI_ROWS)
def test_reproject_cli(make, check, verdict, match, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    out = expect(lambda: make(tmp_path), verdict, match)
    if verdict == OK:
        assert check(out) is not False
