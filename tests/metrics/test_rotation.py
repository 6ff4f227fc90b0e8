import math

import pytest
import torch

from omnidl.data.horizon import horizon_heatmaps
from omnidl.metrics.rotation import (HorizonMetrics, RotationMetrics, horizon_normal_error, rotation_error,
                                     success_rate)
from omnidl.geometry.rotations import axis_angle_to_matrix, random_tilt_rotation, up_from_rotation


def test_rotation_error_closed_form_and_arccos_formula():
    g = torch.Generator().manual_seed(0)
    R = random_tilt_rotation(20, math.pi, generator=g, dtype=torch.float64)
    angle = torch.rand(20, generator=g, dtype=torch.float64) * math.pi * 0.999
    axis = torch.nn.functional.normalize(torch.randn(20, 3, generator=g, dtype=torch.float64), dim=-1)
    R2 = axis_angle_to_matrix(axis * angle[:, None]) @ R
    err = rotation_error(R, R2)
    assert torch.allclose(err, torch.rad2deg(angle), atol=1e-7)
    M = R @ R2.transpose(-1, -2)
    ref = torch.rad2deg(torch.acos(((torch.diagonal(M, dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)))
    assert torch.allclose(err, ref, atol=1e-5)


def test_horizon_normal_error_and_success_rate():
    n = torch.tensor([[0.0, -1.0, 0.0], [0.0, 1.0, 0.0]])
    gt = torch.tensor([[0.0, -1.0, 0.0], [0.0, -1.0, 0.0]])
    assert torch.allclose(horizon_normal_error(n, gt), torch.tensor([0.0, 180.0]))
    assert torch.allclose(horizon_normal_error(n, gt, sign_agnostic=True), torch.tensor([0.0, 0.0]))
    assert success_rate(torch.tensor([1.0, 3.0, float("nan"), 10.0]), 5.0) == 0.5


def test_horizon_metrics_on_ground_truth_maps_and_upright_baseline():
    R = random_tilt_rotation(6, math.radians(60), generator=torch.Generator().manual_seed(1))
    hl, vp = horizon_heatmaps(R, 32, 64)
    logit = lambda p: torch.logit(p.clamp(1e-4, 1 - 1e-4))
    m = HorizonMetrics()
    m.update({"horizon": logit(hl), "vp": logit(vp)}, {"up": up_from_rotation(R)})
    out = m.compute()
    assert out["horizon_error_mean"] < 0.5 and out["horizon_success@5"] == 1.0
    base = horizon_normal_error(torch.tensor([0.0, -1.0, 0.0]).expand(6, 3), up_from_rotation(R)).mean()
    assert abs(out["upright_baseline_error_mean"] - float(base)) < 1e-4
    m.reset()
    assert m.compute() == {}
    with pytest.raises(KeyError, match="up"):
        m.update({"horizon": hl, "vp": vp}, {})


def test_rotation_metrics():
    R = random_tilt_rotation(4, math.pi, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    m = RotationMetrics(thresholds=(1.0,))
    m.update({"rotation": R}, {"rotation": R})
    out = m.compute()
    assert out["rotation_error_mean"] < 1e-6 and out["rotation_success@1"] == 1.0
    with pytest.raises(ValueError, match="rotations"):
        m.update({"rotation": R[:, :2]}, {"rotation": R})
