import math

import pytest
import torch

from omnidl.data.horizon import horizon_heatmaps
from omnidl.metrics.rotation import rotation_error
from omnidl.geometry.panorama import rotate_panorama
from omnidl.geometry.rotations import random_tilt_rotation
from omnidl.postprocess.gyroscope.pipeline import Gyroscope, GyroscopeOptions, stabilise
from omnidl.postprocess.gyroscope.scene import procedural_panorama

OPTS = GyroscopeOptions(work_height=64, pvg_level=4, mpp_max_iter=20, pvg_max_iter=15)


class GroundTruthMaps:
    """horizon_fn returning the true heat maps of the frames (looked up by identity)."""

    def __init__(self, frames, rotations):
        self.table = [(f, R) for f, R in zip(frames, rotations)]

    def __call__(self, images):
        Rs = []
        for img in images:
            R = next(R for f, R in self.table if f.shape == img.shape and torch.equal(f, img))
            Rs.append(R)
        return horizon_heatmaps(torch.stack(Rs).float(), 32, 64)


def test_pipeline_on_ground_truth_maps_recovers_random_rotations():
    g = torch.Generator().manual_seed(0)
    R_gt = random_tilt_rotation(3, math.pi, generator=g, dtype=torch.float64)
    ref = procedural_panorama(None, 64, 128, seed=4)[0]
    frames = list(procedural_panorama(R_gt, 64, 128, seed=4))
    fn = GroundTruthMaps([ref] + frames, [torch.eye(3, dtype=torch.float64)] + list(R_gt))
    gyro = Gyroscope(fn, OPTS)
    gyro.set_reference(ref)
    est = gyro.estimate(torch.stack(frames))
    err = rotation_error(R_gt, est["rotation"].double())
    assert err.median() < 0.5 and err.max() < 1.0, err
    # stabilised frames look like the reference
    stab, _ = rotate_panorama(torch.stack(frames), est["rotation"].transpose(-1, -2))
    assert (stab[:, :, 8:-8] - ref[:, 8:-8]).abs().mean() < 0.02


def test_stabilise_flags_bad_frames_and_continues():
    ref = procedural_panorama(None, 64, 128, seed=5)[0]
    R = random_tilt_rotation(1, math.radians(20), generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    good = procedural_panorama(R, 64, 128, seed=5)[0]
    black = torch.zeros(3, 64, 128)
    wrong = torch.rand(3, 32, 64)
    seen = []
    fn = GroundTruthMaps([ref, good], [torch.eye(3, dtype=torch.float64), R[0]])
    recs = stabilise([good, black, wrong, None, good], ref, horizon_fn=fn, options=OPTS,
                     on_frame=lambda r, f, s: seen.append(s is not None))
    assert [r.status for r in recs] == ["ok", "no_estimate", "no_estimate", "no_estimate", "ok"]
    assert "black" in recs[1].reason and "shape" in recs[2].reason and "read" in recs[3].reason
    assert seen == [True, False, False, False, True]
    assert rotation_error(R[0], torch.tensor(recs[0].rotation, dtype=torch.float64)) < 0.5
    with pytest.raises(ValueError, match="reference"):
        stabilise([good], None)
    with pytest.raises(ValueError, match="black"):
        stabilise([good], black)
