"""``python -m omnidl.apps.cross_camera``: the cross-camera table (a minimal run: two rooms, two steps)."""
from __future__ import annotations

import math

from omnidl.apps import cross_camera


def test_minimal_run_prints_every_method_and_camera(capsys):
    assert cross_camera.main(["--steps", "2", "--train", "1", "--test", "1", "--base-channels", "2",
                              "--batch", "2"]) == 0
    out = capsys.readouterr().out
    for word in ("standard", "projected", "views", "equirect", "kb195", "mei", "noncentral"):
        assert word in out


def test_depth_metrics_and_bad_arguments(capsys):
    import torch
    gt = torch.full((1, 4, 4), 2.0)
    absrel, d1 = cross_camera.depth_metrics(gt * 1.1, gt, torch.ones(1, 4, 4, dtype=torch.bool))
    assert math.isclose(absrel, 0.1, rel_tol=1e-6) and d1 == 1.0
    assert cross_camera.main(["--steps", "0"]) == 2
    assert "--steps must be >= 1" in capsys.readouterr().err
