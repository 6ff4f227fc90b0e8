"""The layout pipeline works on a camera the layout code never names (issue 13, "layout asks the camera").

The camera is defined here only: a non-central *cylindrical* panorama whose seam is rotated. Its rows are
not equirectangular (``v = H/2 - f tan(lat)``), its columns start at a longitude offset, and its optical
centres lie on a ring. The ground truth comes from the data engine (``omnidl.data.synthetic.render_sample``
renders a room through this camera and gives the boundary rows, corner heat and 3D corners); the layout
hook recovers the room from those targets, with no layout code knowing the camera.
"""
import math
from dataclasses import dataclass

import pytest
import torch

from omnidl.cameras import Camera, Rays
from omnidl.cameras.base import in_image
from omnidl.data.synthetic import render_sample
from omnidl.metrics.layout import LayoutMetrics
from omnidl.geometry.boundary import rows_to_angles
from omnidl.postprocess import get_hook


@dataclass(frozen=True)
class RotatedRingCylinder(Camera):
    """Test-only camera: column ``u`` looks at azimuth ``lon0 - pi + 2 pi u / W`` (OpenCV ``atan2(x, z)``),
    row ``v`` at elevation ``atan((H/2 - v) / focal)``, and every column's rays start on the horizontal
    ring of radius ``rc`` (leaving radially)."""

    central = False

    rc: float = 0.5
    lon0: float = 1.0
    focal: float = 20.0

    @property
    def wraps_horizontally(self) -> bool:
        return True

    def unproject(self, uv: torch.Tensor) -> Rays:
        lon = self.lon0 - math.pi + 2 * math.pi * uv[..., 0] / self.width
        t = (self.height / 2 - uv[..., 1]) / self.focal                      # tan(elevation)
        s, c = torch.sin(lon), torch.cos(lon)
        d = torch.stack([s, -t, c], -1) / torch.sqrt(1 + t * t).unsqueeze(-1)
        o = self.rc * torch.stack([s, torch.zeros_like(s), c], -1)
        return Rays(o, d, in_image(uv, self.width, self.height))

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x, y, z = points.unbind(-1)
        rho = torch.sqrt(x * x + z * z)
        ok = rho > self.rc
        lon = torch.atan2(x, z)
        u = torch.remainder(lon - self.lon0 + math.pi, 2 * math.pi) * self.width / (2 * math.pi)
        v = self.height / 2 + self.focal * y / torch.where(ok, rho - self.rc, torch.ones_like(rho))
        uv = torch.stack([u, v], -1)
        return uv, ok & (v >= 0) & (v < self.height)


CAMERA = RotatedRingCylinder(width=256, height=128)


def _engine_sample(index: int) -> dict:
    return render_sample(CAMERA, seed=3, split="test", index=index, rotation="upright", furniture=False)


def test_test_camera_is_consistent():
    uv = torch.tensor([[10.5, 20.5], [200.5, 100.5]], dtype=torch.float64)
    r = CAMERA.unproject(uv)
    back, ok = CAMERA.project(r.origin + 3.0 * r.direction)
    assert ok.all() and torch.allclose(back, uv, atol=1e-9)


@pytest.mark.parametrize("index", [1, 2, 3])
def test_layout_hook_recovers_engine_room_through_unnamed_camera(index):
    s = _engine_sample(index)
    n = int(s["num_walls"])
    assert float(s["boundary_valid"].float().mean()) > 0.8     # floor/ceiling next to the rig leave the view
    outputs = {"boundary": rows_to_angles(s["boundary"].double(), CAMERA.height)[None].float(),
               "corner": torch.logit(s["corner_heat"].double().clamp(1e-4, 1 - 1e-4))[None].float()}
    batch = {"image": s["image"][None], "corners_cam": s["corners_cam"][None], "num_walls": s["num_walls"][None],
             "boundary": s["boundary"][None], "boundary_valid": s["boundary_valid"][None],
             "corner_heat": s["corner_heat"][None]}
    world = "manhattan" if s["meta"].get("manhattan") else "atlanta"
    res = get_hook(f"layout_{world}")(outputs, batch, camera=CAMERA)
    lay = res["layout"][0]
    assert lay["ok"], lay.get("reason")
    assert lay["scale"] == "metric" and len(lay["corners_2d"]) == n
    # metric scale from the ring of the test camera: corners within a few cm, 3D IoU close to 1
    assert res["layout_ce"] < 0.05 and res["layout_iou_3d"] > 0.97
    # the metric reads the hook's layouts from the outputs and agrees with the hook's own scores
    m = LayoutMetrics()
    m.update({**outputs, "layout": res["layout"]}, batch)
    r = m.compute()
    assert r["layout_fail_rate"] == 0 and r["ce"] == pytest.approx(res["layout_ce"])
    assert r["boundary_px"] == pytest.approx(0.0, abs=1e-3)
    for k in ("cen", "iou_3d", "iou_3d_u2s", "iou_2d"):          # issue 14: the same fractions in hook and metric
        assert 0.0 <= r[k] <= 1.0 and r[k] == pytest.approx(res[f"layout_{k}"])
