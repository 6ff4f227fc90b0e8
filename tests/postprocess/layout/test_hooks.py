"""Hooks, ray construction through the camera model, exports and pictures."""
import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from omnidl.cameras import build
from omnidl.postprocess import get_hook, list_hooks
from omnidl.postprocess.layout import Layout, column_rays_from_boundary
from omnidl.apps.layout.simulate import Room, ring_camera, simulate_columns
from omnidl.postprocess.layout.viz import draw_wireframe, plot_top_view, project_points

ROOM = Room(np.array([[3.0, -2.5], [3.0, 3.5], [-0.5, 3.5], [-2.0, 2.0], [-2.0, -2.5]]), 1.25, -1.45)


def _closed_form_rays(boundary, rc, W):
    """Circular panorama of radius ``rc`` in closed form (an oracle independent of the camera classes)."""
    lon = 2 * math.pi * (np.arange(W) + 0.5) / W - math.pi
    b = np.stack([np.sin(lon), np.cos(lon), np.zeros(W)], -1)

    def d(lat):
        return np.stack([np.cos(lat) * np.sin(lon), np.cos(lat) * np.cos(lon), np.sin(lat)], -1)
    return SimpleNamespace(origin=rc * b, ceiling=d(-boundary[0]), floor=d(-boundary[1]))


def _outputs(rc, W=256):
    rays, prob = simulate_columns(ROOM, ring_camera(rc, W))
    lat_c, lat_f = rays.elevations()
    bon = torch.from_numpy(np.stack([-lat_c, -lat_f]))[None].float()
    logit = torch.logit(torch.from_numpy(prob).clamp(1e-5, 1 - 1e-5))[None, None].float()
    return {"boundary": bon, "corner": logit}


def test_hooks_registered():
    for name in ("layout_manhattan", "layout_atlanta", "layout_manhattan_central", "layout_atlanta_central"):
        assert name in list_hooks()


def test_rays_through_noncentral_camera_equal_closed_form():
    cam = build({"type": "noncentral_pano", "width": 256, "height": 128, "rc": 0.65})
    out = _outputs(0.65)
    a = _closed_form_rays(out["boundary"][0].double().numpy(), 0.65, 256)
    b = column_rays_from_boundary(out["boundary"][0].double(), camera=cam)
    assert np.allclose(a.ceiling, b.ceiling, atol=1e-6) and np.allclose(a.floor, b.floor, atol=1e-6)
    assert np.allclose(a.origin, b.origin, atol=1e-6) and b.rc == pytest.approx(0.65)
    # the pixel rows of the boundary, re-projected through the camera, land on the same pixels
    u = np.arange(256) + 0.5
    rows = (out["boundary"][0].numpy() / math.pi + 0.5) * 128
    pts = b.origin + 3.0 * b.ceiling                     # any point of the ray
    uv = project_points(pts, cam)
    assert np.allclose(uv[:, 0], u, atol=1e-4) and np.allclose(uv[:, 1], rows[0], atol=1e-3)


@pytest.mark.parametrize("name,ce_max", [("layout_manhattan", 0.6), ("layout_atlanta", 0.05)])
def test_noncentral_hook_with_meta_and_gt_scores(name, ce_max, tmp_path):
    # the room has one oblique wall: exact in Atlanta, only approximate in Manhattan
    out = _outputs(1.0)
    c3 = ROOM.corners_3d
    batch = {"image": torch.rand(1, 3, 128, 256), "meta": [{"rig_radius": 1.0, "name": "room0"}],
             "corners_3d": torch.from_numpy(c3)[None]}
    res = get_hook(name)(out, batch, camera=ring_camera(1.0, 256), export_dir=str(tmp_path))
    assert res["layout_ok"] == 1.0 and res["layout"][0]["ok"]
    assert res["layout_ce"] < ce_max and res["layout_iou_3d"] > (0.95 if ce_max < 0.1 else 0.70)
    js = json.loads((tmp_path / "room0.json").read_text())
    n = len(js["corners_2d"])
    assert js["h_ceiling"] == pytest.approx(1.25, abs=0.02 if ce_max < 0.1 else 0.2)
    obj = (tmp_path / "room0.obj").read_text()
    assert obj.count("\nv ") == 2 * n and obj.count("\nf ") == n + 2
    assert (tmp_path / "room0_overlay.png").exists()
    json.dumps(res)                                         # the evaluator writes hook results as JSON


def test_central_hook_uses_camera_height_and_noncentral_refuses_without_rc():
    out = _outputs(0.0)
    batch = {"image": torch.rand(1, 3, 128, 256), "camera_height": torch.tensor([1.45])}
    equirect = build({"type": "equirect", "width": 256, "height": 128})
    res = get_hook("layout_atlanta_central")(out, batch, camera=equirect)
    assert res["layout"][0]["ok"] and res["layout"][0]["scale"] == "camera_height"
    assert res["layout"][0]["h_ceiling"] == pytest.approx(1.25, abs=0.02)
    res2 = get_hook("layout_atlanta")(out, batch)
    assert not res2["layout"][0]["ok"] and "rig radius" in res2["layout"][0]["reason"]
    res3 = get_hook("layout_atlanta")(out, batch, camera=equirect)
    assert not res3["layout"][0]["ok"] and "scale" in res3["layout"][0]["reason"]


def test_layout_roundtrip_overlay_and_top_view():
    lay = Layout(ok=True, corners=ROOM.polygon.copy(), h_ceiling=1.25, h_floor=-1.45,
                 occluded=np.zeros(5, bool))
    back = Layout.from_dict(json.loads(json.dumps(lay.to_dict())))
    assert np.allclose(back.corners, lay.corners) and back.h_floor == -1.45
    lc, lf = lay.wall_lines()
    assert np.allclose((lc[:, :3] * lc[:, 3:]).sum(1), 0)         # Plücker identity
    img = np.zeros((64, 128, 3), np.uint8)
    over = draw_wireframe(img, lay, ring_camera(1.0, 128))
    assert over.shape == img.shape and over.sum() > 0 and img.sum() == 0
    ax = plot_top_view([lay, back], labels=["a", "b"], camera=ring_camera(1.0, 128))
    assert len(ax.lines) >= 2


def test_layout_visualizer():
    from omnidl.postprocess.layout.viz import LayoutVisualizer
    out = _outputs(1.0)
    rows = (out["boundary"] / math.pi + 0.5) * 128
    batch = {"image": torch.rand(1, 3, 128, 256), "boundary": rows, "corner_heat": torch.sigmoid(out["corner"])}
    im = LayoutVisualizer(strip=8)(out, batch)
    assert im.shape == (3, 136, 256) and 0 <= float(im.min()) and float(im.max()) <= 1
