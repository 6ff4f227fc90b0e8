"""fit_horizon: the horizon plane from ground-truth heat maps at any tilt, the sign from the VP map, coherence."""
import math

import pytest
import torch

from omnidl.data.horizon import horizon_heatmaps
from omnidl.geometry.horizon import fit_horizon
from omnidl.geometry.rotations import euler_to_matrix, random_tilt_rotation, up_from_rotation
from omnidl.metrics.rotation import horizon_normal_error


@pytest.mark.parametrize("coherence", ["thesis", "reference", "none"])
def test_ground_truth_maps_any_tilt_below_half_a_degree(coherence):
    g = torch.Generator().manual_seed(0)
    R = random_tilt_rotation(12, math.pi, generator=g, dtype=torch.float64)  # tilts up to 180 deg
    hl, vp = horizon_heatmaps(R.float(), 64, 128)
    res = fit_horizon(hl, vp, coherence=coherence)
    err = horizon_normal_error(res["up"].double(), up_from_rotation(R))
    assert res["valid"].all()
    assert err.max() < 0.5


def test_upside_down_and_exact_tilts():
    # tilts of 0, 90, 135 and 180 degrees about x
    pitches = torch.tensor([0.0, 90.0, 135.0, 180.0], dtype=torch.float64).deg2rad()
    R = euler_to_matrix(torch.zeros(4, dtype=torch.float64), pitches, torch.zeros(4, dtype=torch.float64))
    hl, vp = horizon_heatmaps(R, 32, 64)
    res = fit_horizon(hl, vp)
    err = horizon_normal_error(res["up"], up_from_rotation(R))
    assert err.max() < 0.5


def test_symmetric_vp_map_folds_tilts_like_the_reference():
    R = euler_to_matrix(torch.zeros(2, dtype=torch.float64), torch.tensor([30.0, 150.0]).double().deg2rad(),
                        torch.zeros(2, dtype=torch.float64))
    hl, vp = horizon_heatmaps(R, 32, 64, nadir_weight=1.0)
    res = fit_horizon(hl, vp)
    err = horizon_normal_error(res["up"], up_from_rotation(R))
    assert err[0] < 0.5 and abs(err[1] - 180) < 0.5  # beyond 90 deg the zenith/nadir sign is lost
    assert horizon_normal_error(res["up"], up_from_rotation(R), sign_agnostic=True).max() < 0.5


def test_coherence_thesis_rejects_reference_downweights():
    R1 = euler_to_matrix(*torch.tensor([0.0, 0.0, 0.0], dtype=torch.float64))
    R2 = euler_to_matrix(*torch.tensor([math.radians(60), 0.0, 0.0], dtype=torch.float64))
    hl, _ = horizon_heatmaps(R1[None], 32, 64)
    _, vp = horizon_heatmaps(R2[None], 32, 64)
    thesis = fit_horizon(hl, vp, coherence="thesis")
    assert not thesis["valid"][0]  # the only line is 60 deg off the VP: every hypothesis rejected
    ref = fit_horizon(hl, vp, coherence="reference")
    assert ref["valid"][0]  # down-weighted but the only candidate
    assert horizon_normal_error(ref["up"], up_from_rotation(R1[None]), sign_agnostic=True)[0] < 0.5


def test_cached_sphere_grid_is_the_camera_grid_and_is_never_written():
    """fit_horizon reuses one direction grid per map size: equal to the camera's, and unchanged by fits."""
    from omnidl.cameras import Equirectangular
    from omnidl.geometry.horizon import _sphere_grid

    R = random_tilt_rotation(2, 1.0, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    hl, vp = horizon_heatmaps(R.float(), 32, 64)
    first = fit_horizon(hl, vp)
    dirs, area = _sphere_grid(32, 64, torch.float32, "cpu")
    ref = Equirectangular(width=64, height=32).unproject_grid(torch.float32).direction.reshape(-1, 3)
    assert torch.equal(dirs, ref)
    assert torch.equal(area, torch.sqrt((1 - ref[:, 1] ** 2).clamp_min(0)))
    again = fit_horizon(hl, vp)
    assert torch.equal(first["up"], again["up"]) and torch.equal(dirs, ref)
    assert _sphere_grid(32, 64, torch.float32, "cpu")[0] is dirs
