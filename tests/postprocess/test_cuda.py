"""GPU checks of the post-processing (``pytest -m cuda``; skipped without a CUDA device): the visual gyroscope
(horizon fit, MPP, PVG) on CUDA frames gives the CPU's rotation, and the layout hooks take CUDA network outputs
(the layout geometry itself is NumPy on the CPU: the hooks move the few ``(2, W)`` boundary rows there)."""
import math

import numpy as np
import pytest
import torch

from omnidl.data.horizon import horizon_heatmaps
from omnidl.geometry.rotations import random_tilt_rotation
from omnidl.metrics.rotation import rotation_error
from omnidl.postprocess import get_hook
from omnidl.postprocess.gyroscope.pipeline import Gyroscope, GyroscopeOptions
from omnidl.postprocess.gyroscope.scene import procedural_panorama
from omnidl.apps.layout.simulate import Room, ring_camera, simulate_columns

pytestmark = [pytest.mark.cuda,
              pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA is not available")]
CUDA = torch.device("cuda")
OPTS = GyroscopeOptions(work_height=64, pvg_level=4, mpp_max_iter=20, pvg_max_iter=15)


def test_gyroscope_on_cuda_frames_matches_the_cpu():
    g = torch.Generator().manual_seed(0)
    R_gt = random_tilt_rotation(2, math.radians(30), generator=g, dtype=torch.float64)
    ref = procedural_panorama(None, 64, 128, seed=4)[0]
    frames = procedural_panorama(R_gt, 64, 128, seed=4)
    maps = [horizon_heatmaps(torch.eye(3, dtype=torch.float64)[None].float(), 32, 64),   # the reference's
            horizon_heatmaps(R_gt.float(), 32, 64)]                                      # the frames'
    est = {}
    for dev in ("cpu", CUDA):
        calls = []

        def fn(images, dev=dev):
            assert images.device.type == torch.device(dev).type
            h, vp = maps[len(calls)]
            calls.append(1)
            return h.to(images.device), vp.to(images.device)
        gyro = Gyroscope(fn, OPTS)
        gyro.set_reference(ref.to(dev))
        est[str(dev)] = gyro.estimate(frames.to(dev))
    cuda = est[str(CUDA)]
    assert cuda["rotation"].device.type == "cuda"
    err = rotation_error(R_gt, cuda["rotation"].double().cpu())
    assert err.max() < 1.0, err
    # float32 reductions run in another order on the GPU: the same estimate to a small fraction of a degree
    assert rotation_error(cuda["rotation"].double().cpu(), est["cpu"]["rotation"].double()).max() < 0.05


@pytest.mark.parametrize("name", ["layout_manhattan", "layout_atlanta"])
def test_layout_hook_takes_cuda_outputs(name):
    room = Room(np.array([[3.0, -2.5], [3.0, 3.5], [-0.5, 3.5], [-2.0, 2.0], [-2.0, -2.5]]), 1.25, -1.45)
    rays, prob = simulate_columns(room, ring_camera(1.0, 256))
    lat_c, lat_f = rays.elevations()
    out = {"boundary": torch.from_numpy(np.stack([-lat_c, -lat_f]))[None].float(),
           "corner": torch.logit(torch.from_numpy(prob).clamp(1e-5, 1 - 1e-5))[None, None].float()}
    batch = {"image": torch.rand(1, 3, 128, 256), "meta": [{"rig_radius": 1.0, "name": "room0"}]}
    cpu = get_hook(name)(out, batch, camera=ring_camera(1.0, 256))
    gpu = get_hook(name)({k: v.to(CUDA) for k, v in out.items()},
                         {**batch, "image": batch["image"].to(CUDA)}, camera=ring_camera(1.0, 256))
    assert gpu["layout"][0]["ok"] == cpu["layout"][0]["ok"] is True
    np.testing.assert_allclose(gpu["layout"][0]["corners_2d"], cpu["layout"][0]["corners_2d"], atol=1e-5)
