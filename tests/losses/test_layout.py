"""Layout loss: closed-form L1/BCE values, units, masks and gradients."""
import math

import pytest
import torch
import torch.nn.functional as F

from omnidl.geometry.boundary import rows_to_angles
from omnidl.losses.layout import LayoutLoss


def test_values_and_units():
    H, W = 32, 16
    pred_b = torch.zeros(1, 2, W, requires_grad=True)
    rows = torch.full((1, 2, W), H / 2 + H / 8)             # angle = pi / 8
    logits = torch.zeros(1, 1, W, requires_grad=True)
    heat = torch.rand(1, 1, W)
    batch = {"image": torch.zeros(1, 3, H, W), "boundary": rows, "corner_heat": heat}
    total, terms = LayoutLoss()({"boundary": pred_b, "corner": logits}, batch)
    assert terms["boundary"] == pytest.approx(math.pi / 8, rel=1e-6)
    assert terms["corner"] == pytest.approx(float(F.binary_cross_entropy_with_logits(logits.detach(), heat)), rel=1e-6)
    total.backward()
    assert pred_b.grad is not None and torch.isfinite(pred_b.grad).all()
    t2, terms2 = LayoutLoss(target_units="radians", corner_weight=0)({"boundary": pred_b.detach(), "corner": logits.detach()},
                                                                       {**batch, "boundary": torch.full((1, 2, W), 0.25)})
    assert terms2["boundary"] == pytest.approx(0.25) and t2.item() == pytest.approx(0.25)


def test_invalid_columns_are_ignored_and_errors_are_clear():
    H, W = 32, 16
    pred = torch.zeros(1, 2, W)
    rows = torch.full((1, 2, W), H / 2.0)
    rows[..., :4] = -1.0                                      # engine's "no boundary" marker
    valid = torch.ones(1, 2, W, dtype=torch.bool)
    valid[..., :4] = False
    batch = {"image": torch.zeros(1, 3, H, W), "boundary": rows, "boundary_valid": valid,
             "corner_heat": torch.zeros(1, 1, W)}
    _, terms = LayoutLoss()({"boundary": pred, "corner": torch.zeros(1, 1, W)}, batch)
    assert terms["boundary"] == pytest.approx(0.0, abs=1e-7)
    with pytest.raises(KeyError):
        LayoutLoss()({"boundary": pred}, batch)
    with pytest.raises(ValueError):
        LayoutLoss()({"boundary": torch.zeros(1, 2, 8), "corner": torch.zeros(1, 1, 8)}, batch)
    assert rows_to_angles(torch.tensor(0.0), 10) == pytest.approx(-math.pi / 2)
