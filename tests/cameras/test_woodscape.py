"""WoodScape radial polynomial: the dataset's reference projection (its calibration README / projection.py maths
re-done in numpy), its pixel convention, the calibration JSON, > 180 deg rays and the inverse."""
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from omnidl.cameras import build
from omnidl.cameras.woodscape import WoodScape, read_woodscape_json

CONFIG = Path(__file__).resolve().parents[2] / "configs" / "camera" / "woodscape.yaml"
# intrinsic block of valeoai/WoodScape scripts/calibration/front.json (extrinsics left out)
FRONT = {"intrinsic": {"aspect_ratio": 1.0, "cx_offset": 3.942, "cy_offset": -3.093, "height": 966.0,
                       "k1": 339.749, "k2": -31.988, "k3": 48.275, "k4": -7.201, "model": "radial_poly",
                       "poly_order": 4, "width": 1280.0}, "name": "FV"}


def _reference_project(intr, pts):
    """WoodScape's projection (calibration_readme.txt), image origin at the centre of the upper-left pixel."""
    x, y, z = pts.T
    chi = np.sqrt(x * x + y * y)
    theta = np.pi / 2 - np.arctan2(z, chi)
    rho = sum(intr[f"k{i}"] * theta ** i for i in range(1, 5))
    u = rho * x / chi + intr["cx_offset"] + intr["width"] / 2 - 0.5
    v = rho * y / chi * intr["aspect_ratio"] + intr["cy_offset"] + intr["height"] / 2 - 0.5
    return np.stack([u, v], -1)


def _reference_theta(intr, rho):
    """WoodScape's inverse: the smallest real root in |theta| < pi of the polynomial (np.roots)."""
    out = []
    for r in rho:
        roots = np.roots([intr["k4"], intr["k3"], intr["k2"], intr["k1"], -r])
        roots = np.real(roots[roots.imag == 0])
        out.append(np.min(roots[np.abs(roots) < np.pi]))
    return np.array(out)


def _dirs(n, theta_max, seed):
    g = np.random.default_rng(seed)
    theta = theta_max * np.sqrt(g.random(n))
    psi = g.uniform(-np.pi, np.pi, n)
    return np.stack([np.sin(theta) * np.cos(psi), np.sin(theta) * np.sin(psi), np.cos(theta)], -1)


@pytest.fixture
def front_file(tmp_path):
    path = tmp_path / "front.json"
    path.write_text(json.dumps(FRONT))
    return path


@pytest.mark.parametrize("aspect", [1.0, 1.07])
def test_agrees_with_the_reference_projection(front_file, aspect):
    cam = build({"type": "woodscape", "calib_file": str(front_file), "aspect_ratio": aspect})
    intr = {**FRONT["intrinsic"], "aspect_ratio": aspect}
    pts = _dirs(3000, math.radians(95), 0) * np.random.default_rng(1).uniform(0.5, 5, (3000, 1))
    uv, valid = cam.project(torch.from_numpy(pts))
    ref = _reference_project(intr, pts)
    inside = (ref[:, 0] > 0) & (ref[:, 0] < 1279) & (ref[:, 1] > 0) & (ref[:, 1] < 965)
    assert valid.numpy()[inside].all() and inside.sum() > 2000
    # omnidl puts the centre of the upper-left pixel at (0.5, 0.5), WoodScape at (0, 0)
    assert np.abs(uv.numpy() - 0.5 - ref)[inside].max() < 1e-9
    # inverse against the reference root finder
    m = np.stack([uv[:, 0].numpy() - cam.cx, (uv[:, 1].numpy() - cam.cy) / aspect], -1)[inside][:300]
    theta_ref = _reference_theta(intr, np.linalg.norm(m, axis=1))
    rays = cam.unproject(uv[torch.from_numpy(inside)][:300])
    assert rays.valid.all()
    assert np.abs(np.arccos(np.clip(rays.direction[:, 2].numpy(), -1, 1)) - theta_ref).max() < 1e-7
    assert np.abs(rays.direction.numpy() - pts[inside][:300] / np.linalg.norm(pts[inside][:300], axis=1,
                                                                              keepdims=True)).max() < 1e-12


def test_reads_the_calibration_json(front_file):
    fields = read_woodscape_json(front_file)
    assert fields == dict(k1=339.749, k2=-31.988, k3=48.275, k4=-7.201, cx_offset=3.942, cy_offset=-3.093,
                          aspect_ratio=1.0, width=1280, height=966)
    cam = WoodScape.from_file(front_file)
    assert (cam.cx, cam.cy) == (643.942, 479.907)
    uv, valid = cam.project(torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64))
    assert valid and uv.tolist() == [643.942, 479.907]
    assert cam == build(OmegaConf.load(CONFIG))


def test_front_camera_sees_190_degrees_across_the_width(front_file):
    cam = WoodScape.from_file(front_file)
    # rho(95 deg) is ~ width / 2: the 190 deg lens fills the image width
    assert float(cam.rho(torch.tensor(math.radians(95.0), dtype=torch.float64))) == pytest.approx(640, abs=2)
    left = cam.unproject(torch.tensor([10.0, cam.cy], dtype=torch.float64))
    assert left.valid and math.degrees(math.acos(float(left.direction[2]))) > 90


def test_rays_beyond_90_degrees_and_the_field_of_view_limit():
    cam = WoodScape(width=2000, height=2000, k1=300.0, k2=-10.0, k3=5.0, k4=-0.5, max_fov=math.radians(220))
    d = torch.from_numpy(_dirs(2000, math.radians(110), 2))
    uv, valid = cam.project(3 * d)
    assert valid.all()
    rays = cam.unproject(uv)
    assert rays.valid.all() and (rays.direction - d).abs().max() < 1e-12
    t = math.radians(110.01)
    _, valid = cam.project(torch.tensor([math.sin(t), 0.0, math.cos(t)], dtype=torch.float64))
    assert not valid
    rim = cam.rho_max
    rays = cam.unproject(torch.tensor([[cam.cx + rim - 1e-6, cam.cy], [cam.cx + rim + 1e-6, cam.cy]],
                                      dtype=torch.float64))
    assert rays.valid.tolist() == [True, False]


def test_bad_input_raises(tmp_path):
    with pytest.raises(ValueError, match="not increasing"):
        WoodScape(width=64, height=64, k1=10.0, k2=-10.0, max_fov=math.radians(180))
    with pytest.raises(ValueError, match="k1 must be > 0"):
        WoodScape(width=64, height=64, k1=0.0)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"intrinsic": {**FRONT["intrinsic"], "k3": "x"}}))
    with pytest.raises(ValueError, match=r"bad.json.*intrinsic.k3"):
        read_woodscape_json(bad)
    bad.write_text(json.dumps({"intrinsic": {**FRONT["intrinsic"], "model": "pinhole"}}))
    with pytest.raises(ValueError, match="radial_poly"):
        read_woodscape_json(bad)
    bad.write_text("{not json")
    with pytest.raises(ValueError, match="cannot be read as JSON"):
        read_woodscape_json(bad)
