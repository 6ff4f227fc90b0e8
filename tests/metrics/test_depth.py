"""Depth metrics against hand-computed values (per image, then averaged over images)."""
import math

import pytest
import torch

from omnidl.metrics.depth import DepthMetrics, depth_errors


def _image1():
    # valid pixels: (p, g) = (1.25, 1), (1, 2), (4, 4); the (5, 0) pixel is invalid
    return torch.tensor([[[1.25, 1.0], [5.0, 4.0]]]), torch.tensor([[[1.0, 2.0], [0.0, 4.0]]])


def test_single_image_by_hand():
    p, g = _image1()
    m = depth_errors(p, g)
    assert m["mae"] == pytest.approx((0.25 + 1 + 0) / 3)
    assert m["mre"] == pytest.approx((0.25 / 1 + 1 / 2 + 0) / 3)
    assert m["rmse"] == pytest.approx(math.sqrt((0.0625 + 1) / 3))
    assert m["rmse_log"] == pytest.approx(math.sqrt((math.log(1.25) ** 2 + math.log(0.5) ** 2) / 3))
    # ratios max(p/g, g/p) = 1.25, 2, 1 ; strict "<" as the author's code
    assert m["delta1"] == pytest.approx(1 / 3)
    assert m["delta2"] == pytest.approx(2 / 3)
    assert m["delta3"] == pytest.approx(2 / 3)


def test_dataset_average_is_mean_of_per_image_values():
    p1, g1 = _image1()
    p2 = torch.full((1, 2, 2), 3.0)
    g2 = torch.tensor([[[2.0, 2.0], [2.0, 2.0]]])        # |e| = 1 everywhere: rmse 1, mre 0.5, ratio 1.5
    metric = DepthMetrics()
    metric.update({"depth": torch.stack([p1, p2])}, {"depth": torch.stack([g1, g2])})
    metric.update({"depth": torch.zeros(1, 1, 2, 2)}, {"depth": torch.zeros(1, 1, 2, 2)})   # no valid pixel: skipped
    out = metric.compute()
    m1 = depth_errors(p1, g1)
    assert out["rmse"] == pytest.approx((m1["rmse"] + 1.0) / 2)       # not the global RMSE
    assert out["mre"] == pytest.approx((m1["mre"] + 0.5) / 2)
    assert out["delta1"] == pytest.approx((1 / 3 + 0.0) / 2)
    assert out["delta2"] == pytest.approx((2 / 3 + 1.0) / 2)
    assert out["rmse_log"] == pytest.approx((m1["rmse_log"] + math.log(1.5)) / 2)
    assert out["skipped_images"] == 1.0
    metric.reset()
    assert math.isnan(metric.compute()["mae"])


def test_max_depth_caps_ground_truth_and_clamps_prediction():
    p = torch.tensor([20.0, 5.0, 3.0])
    g = torch.tensor([9.0, 12.0, 3.0])                   # the 12 m pixel is beyond the cap
    m = depth_errors(p, g, max_depth=10.0)
    assert m["mae"] == pytest.approx((1.0 + 0.0) / 2)    # prediction 20 clamped to 10


def test_shape_mismatch_and_prefix():
    with pytest.raises(ValueError, match="differ"):
        DepthMetrics().update({"depth": torch.ones(1, 1, 2, 2)}, {"depth": torch.ones(1, 1, 2, 3)})
    metric = DepthMetrics(prefix="depth/")
    metric.update({"depth": torch.ones(1, 2, 2)}, {"depth": torch.ones(1, 2, 2)})
    assert metric.compute()["depth/delta1"] == 1.0


def test_all_zero_prediction_gives_finite_metrics():
    g = torch.tensor([1.0, 2.0, 4.0])
    m = depth_errors(torch.zeros(3), g)
    assert all(math.isfinite(v) for v in m.values())
    assert m["rmse_log"] == pytest.approx(torch.sqrt(((math.log(1e-7) - g.log()) ** 2).mean()).item())
    assert m["mre"] == pytest.approx(1.0) and m["delta3"] == 0.0
