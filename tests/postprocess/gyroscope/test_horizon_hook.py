import math

import pytest
import torch

from omnidl.data.horizon import horizon_heatmaps
from omnidl.geometry.horizon import fit_horizon
from omnidl.geometry.rotations import random_tilt_rotation, up_from_rotation
from omnidl.metrics.rotation import horizon_normal_error
from omnidl.postprocess import get_hook


def test_hook_from_logits_and_empty_maps():
    R = random_tilt_rotation(2, math.radians(60), generator=torch.Generator().manual_seed(3))
    hl, vp = horizon_heatmaps(R, 32, 64)
    logit = lambda p: torch.logit(p.clamp(1e-4, 1 - 1e-4))
    out = get_hook("horizon")({"horizon": logit(hl), "vp": logit(vp)}, {})
    assert set(out) == {"horizon_normal", "roll", "pitch", "horizon_valid"}
    assert horizon_normal_error(out["horizon_normal"], up_from_rotation(R)).max() < 0.5
    empty = fit_horizon(torch.zeros(1, 1, 16, 32), torch.zeros(1, 1, 16, 32))
    assert not empty["valid"][0] and torch.isfinite(empty["up"]).all()
    with pytest.raises(KeyError, match="vp"):
        get_hook("horizon")({"horizon": hl}, {})
    with pytest.raises(ValueError, match="same shape"):
        fit_horizon(hl, vp[..., :10])
    with pytest.raises(ValueError, match="coherence"):
        fit_horizon(hl, vp, coherence="strict")
