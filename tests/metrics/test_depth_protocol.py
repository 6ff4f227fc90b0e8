import math

import pytest
import torch

from omnidl.metrics.depth import DepthMetrics
from omnidl.metrics.depth_protocol import (DEPTH_PROTOCOLS, DepthProtocolMetrics, get_depth_protocol,
                                           protocol_depth_errors)


def t(*v):
    return torch.tensor(v, dtype=torch.float64).view(1, 1, -1)


def run(name, pairs, **kw):
    m = DepthProtocolMetrics(name, **kw)
    for p, g in pairs:
        m.update({"depth": p}, {"depth": g})
    return m.compute()


@pytest.mark.parametrize("name", list(DEPTH_PROTOCOLS))
def test_perfect_prediction(name):
    g = t(1.0, 2.0, 4.0, 8.0)
    out = run(name, [(g.clone(), g)])
    for k in ("abs_rel", "sq_rel", "mae", "rmse", "rmse_log", "log10"):
        assert out[k] == pytest.approx(0.0, abs=1e-12)
    assert out["delta1"] == out["delta2"] == out["delta3"] == 1.0


def test_per_image_vs_per_pixel_averaging_hand_computed():
    # image A: 1 valid pixel with error 2; image B: 3 valid pixels with error 0 (0 = invalid gt)
    a = (t(3.0, 5.0), t(1.0, 0.0))
    b = (t(2.0, 2.0, 2.0), t(2.0, 2.0, 2.0))
    img = run("fredsnet", [a, b])
    pix = run("pixel", [a, b])
    assert img["mae"] == pytest.approx((2.0 + 0.0) / 2) and pix["mae"] == pytest.approx(2.0 / 4)
    assert img["rmse"] == pytest.approx((2.0 + 0.0) / 2) and pix["rmse"] == pytest.approx(math.sqrt(4.0 / 4))
    assert img["abs_rel"] == pytest.approx(1.0) and pix["abs_rel"] == pytest.approx(0.5)
    assert img["delta1"] == pytest.approx(0.5) and pix["delta1"] == pytest.approx(0.75)


def test_fredsnet_preset_equals_depth_metrics():
    g = torch.rand(2, 1, 4, 8, dtype=torch.float64) * 5 + 0.5
    g[0, 0, 0, :3] = 0
    p = g * (1 + 0.3 * torch.randn_like(g)).abs()
    a = DepthMetrics()
    a.update({"depth": p}, {"depth": g})
    b = run("fredsnet", [(p, g)])
    for k, k0 in (("abs_rel", "mre"), ("mae", "mae"), ("rmse", "rmse"), ("rmse_log", "rmse_log"), ("delta1", "delta1")):
        assert b[k] == pytest.approx(a.compute()[k0], rel=1e-12)


def test_unifuse_clamps_and_gt_quirk():
    # gt 12 > 10 is masked out; pred 0.05 -> 0.1 (gt 1); pred 14 > 10 sets gt 3 to 10 (pred stays 14, as the
    # script does)
    p, g = t(10.0, 0.05, 14.0), t(12.0, 1.0, 3.0)
    out = protocol_depth_errors(p, g, "unifuse")
    err = [0.9, 4.0]
    assert out["mae"] == pytest.approx(sum(err) / 2)
    assert out["rmse"] == pytest.approx(math.sqrt(sum(e * e for e in err) / 2))
    assert out["rmse_log"] == pytest.approx(math.sqrt((1.0 + math.log10(1.4) ** 2) / 2))
    off = get_depth_protocol("unifuse", unifuse_gt_quirk=False)
    assert protocol_depth_errors(p, g, off)["mae"] == pytest.approx((0.9 + 10.0 - 3.0) / 2)   # pred clamped to 10


def test_median_scaling_and_cap_mask():
    g = t(1.0, 2.0, 3.0, 4.0, 5.0)
    assert run("unifuse_median", [(1.5 * g, g)])["abs_rel"] == pytest.approx(0.0, abs=1e-12)
    assert run("unifuse", [(1.5 * g, g)])["abs_rel"] == pytest.approx(0.5)
    assert run("fredsnet", [(2.5 * g, g)], median_scaling=True)["rmse"] == pytest.approx(0.0, abs=1e-12)
    # masked cap: gt 20 leaves the evaluation, prediction clamped to the cap
    out = run("pixel", [(t(30.0, 2.0), t(20.0, 2.0))])
    assert out["mae"] == 0.0
    out = run("fredsnet", [(t(30.0, 2.0), t(20.0, 2.0))], max_depth=10.0)
    assert out["mae"] == 0.0


def test_bad_protocol_inputs():
    with pytest.raises(ValueError, match="unknown depth protocol 'bifuse'"):
        DepthProtocolMetrics("bifuse")
    with pytest.raises(ValueError, match="averaging='batch'"):
        DepthProtocolMetrics("fredsnet", averaging="batch")
    with pytest.raises(ValueError, match="non-finite"):
        run("fredsnet", [(t(float("nan"), 1.0), t(1.0, 1.0))])
    with pytest.raises(ValueError, match="differ"):
        run("fredsnet", [(t(1.0, 1.0), t(1.0))])
    out = run("fredsnet", [(t(1.0), t(0.0))])
    assert out["skipped_images"] == 1.0
