"""Rectification baseline (§7.4.3): round trip through a perspective network, unrectifiable fraction."""
import math

import pytest
import torch

from omnidl.cameras import resolve_camera
from omnidl.apps.fisheye.rectified import RectifiedModel, rectification_report


class RedAsDepth(torch.nn.Module):
    """A 'perspective network' that returns its red channel as depth and RGB as logits."""

    def forward(self, x):
        return {"depth": x[:, :1], "semantic": x}


def smooth_image(cam):
    d = cam.unproject_grid(dtype=torch.float64).direction
    return torch.stack([1.5 + d[..., 0], 1 + 0 * d[..., 0], 1 + d[..., 1]], 0).float()[None]


@pytest.mark.parametrize("name", ["kb_f165", "kb_f195"])
def test_round_trip_and_coverage(name):
    cam = resolve_camera(name, 72, 64, check_aspect=True)
    rect = RectifiedModel(RedAsDepth(), cam, fov_deg=150)
    x = smooth_image(cam)
    out = rect(x)
    cov = out["rectified"][0, 0]
    assert out["depth"].shape == (1, 1, 64, 72) and out["semantic"].shape == (1, 3, 64, 72)
    inner = cov & (torch.nn.functional.max_pool2d((~cov).float()[None, None], 5, 1, 2)[0, 0] == 0)
    err = (out["depth"][0, 0] - x[0, 0]).abs()[inner]
    assert float(err.max()) < 0.1                # bilinear twice on a smooth image
    assert bool((out["depth"][0, 0][~cov] == 0).all())
    rep = rectification_report(cam, fov_deg=150)
    # closed form for the (effectively equidistant) cameras: pixels 90° or more off-axis cannot be rectified
    f = cam.base.fx * cam.scale_x
    uv = cam.pixel_grid(torch.float64)
    valid = cam.unproject_grid(dtype=torch.float64).valid
    theta = torch.hypot(uv[..., 0] - cam.base.cx * cam.scale_x, (uv[..., 1] - cam.base.cy * cam.scale_y)) / f
    behind = float((valid & (theta >= math.pi / 2)).sum()) / float(valid.sum())
    assert rep["unrectifiable"] == pytest.approx(behind, abs=0.01)
    if name == "kb_f165":
        assert rep["unrectifiable"] == 0.0
    else:
        assert 0.1 < rep["unrectifiable"] < 0.2
    assert rep["covered"] <= rep["rectifiable"]
    assert float(cov.double().mean()) == pytest.approx(rep["covered"] * float(valid.double().mean()), abs=0.03)
    assert rep["pinhole_fov_deg"] == pytest.approx(150.0)


def test_size_mismatch_is_an_error():
    cam = resolve_camera("kb_f165", 36, 32, check_aspect=True)
    with pytest.raises(ValueError, match="disagrees with the fisheye calibration"):
        RectifiedModel(RedAsDepth(), cam)(torch.rand(1, 3, 32, 32))
