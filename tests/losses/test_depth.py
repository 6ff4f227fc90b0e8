"""Depth losses against hand computations, kornia's Sobel, and the masking / all-invalid contracts."""
import math

import kornia
import pytest
import torch

from omnidl.losses.depth import (DepthLoss, adaptive_berhu_loss, berhu, depth_loss, margin_loss,
                                 neighbourhood_mask, sobel_gradients)


def test_berhu_closed_form_and_continuity():
    e = torch.tensor([-3.0, -1.0, 0.0, 0.5, 1.0, 2.0])
    expect = torch.tensor([(9 + 1) / 2, 1.0, 0.0, 0.5, 1.0, (4 + 1) / 2])
    torch.testing.assert_close(berhu(e, 1.0), expect)
    c = 0.7
    torch.testing.assert_close(berhu(torch.tensor([c + 1e-6]), c), torch.tensor([c]), atol=1e-5, rtol=0)


def test_adaptive_berhu_hand_example():
    pred = torch.tensor([[[[1.1, 3.0, 0.0, 5.0]]]])
    gt = torch.tensor([[[[1.0, 2.0, 2.0, 0.0]]]])        # last pixel invalid (0)
    # errors 0.1, 1, -2 -> c = 0.2 * 2 = 0.4; B = 0.1, (1 + .16)/.8, (4 + .16)/.8
    expect = (0.1 + 1.16 / 0.8 + 4.16 / 0.8) / 3
    assert adaptive_berhu_loss(pred, gt).item() == pytest.approx(expect, rel=1e-6)


def test_sobel_matches_kornia_inside_and_wraps_horizontally():
    torch.manual_seed(0)
    x = torch.randn(2, 1, 7, 9, dtype=torch.float64)
    gx, gy = sobel_gradients(x)
    ref = kornia.filters.spatial_gradient(x, mode="sobel", normalized=False)   # (B, C, 2, H, W)
    torch.testing.assert_close(gx[..., 1:-1, 1:-1], ref[:, :, 0, 1:-1, 1:-1])
    torch.testing.assert_close(gy[..., 1:-1, 1:-1], ref[:, :, 1, 1:-1, 1:-1])
    # horizontal wrap: the seam column equals the interior result on a rolled image
    gx_roll, _ = sobel_gradients(torch.roll(x, 4, -1))
    torch.testing.assert_close(torch.roll(gx, 4, -1), gx_roll)


def test_neighbourhood_mask():
    m = torch.ones(1, 1, 5, 6, dtype=torch.bool)
    m[0, 0, 2, 0] = False
    nm = neighbourhood_mask(m)
    bad = {(1, 5), (1, 0), (1, 1), (2, 5), (2, 0), (2, 1), (3, 5), (3, 0), (3, 1)}   # wraps across the seam
    for i in range(5):
        for j in range(6):
            assert nm[0, 0, i, j].item() == ((i, j) not in bad)


def test_depth_loss_constant_offset_has_no_gradient_term():
    gt = torch.rand(1, 1, 6, 8) + 1.0
    _, _, grad_term = depth_loss(gt + 0.3, gt)
    assert grad_term.item() == pytest.approx(0.0, abs=1e-6)


def test_depth_loss_constant_offset_value():
    gt = torch.rand(1, 1, 6, 8) + 1.0
    _, abs_term, _ = depth_loss(gt + 0.3, gt)
    c = 0.2 * 0.3
    assert abs_term.item() == pytest.approx((0.09 + c * c) / (2 * c), rel=1e-4)


def test_depth_loss_ignores_invalid_pixels():
    torch.manual_seed(1)
    gt = torch.rand(1, 1, 8, 10) + 0.5
    gt[..., 3:5, 4:6] = 0
    pred = torch.rand(1, 1, 8, 10)
    pred2 = pred.clone()
    pred2[..., 3:5, 4:6] += 10.0                       # change predictions only where gt is invalid
    for a, b in zip(depth_loss(pred, gt), depth_loss(pred2, gt)):
        torch.testing.assert_close(a, b)


def test_depth_loss_gradient_term_hand_check():
    # a horizontal ramp prediction vs flat ground truth: Sobel x of a ramp of slope s is 8 s inside
    gt = torch.full((1, 1, 5, 8), 2.0)
    pred = gt.clone()
    pred[..., :, 4] += 1.0                             # a vertical line bump
    _, _, g = depth_loss(pred, gt, wrap=True)
    gx, gy = sobel_gradients(pred - gt)
    ex, ey = gx.flatten(), gy.flatten()
    c2 = 0.2 * max(ex.abs().max(), ey.abs().max())
    expect = berhu(ex, c2).mean() + berhu(ey, c2).mean()
    torch.testing.assert_close(g, expect)


def test_margin_loss_closed_form():
    pred = torch.tensor([[[[1.0, 4.0, 9.0]]], [[[2.0, 3.0, 0.5]]]])
    gt = torch.tensor([[[[2.0, 5.0, 0.0]]], [[[1.0, 3.0, 6.0]]]])
    # valid: pred {1, 4, 2, 3, 0.5}, gt {2, 5, 1, 3, 6}: ((6 - 4)^2 + (1 - 0.5)^2) / 2
    assert margin_loss(pred, gt).item() == pytest.approx((4 + 0.25) / 2)
    per = margin_loss(pred, gt, per_image=True).item()
    assert per == pytest.approx((((5 - 4) ** 2 + (2 - 1) ** 2) / 2 + ((6 - 3) ** 2 + (1 - 0.5) ** 2) / 2) / 2)


def test_all_invalid_batch_gives_zero_and_warning_term():
    pred = torch.rand(2, 1, 4, 8, requires_grad=True)
    loss = DepthLoss(alpha_margin=1.0)
    with pytest.warns(UserWarning, match="valid depth"):
        total, terms = loss({"depth": pred}, {"depth": torch.zeros(2, 1, 4, 8)})
    assert total.item() == 0.0 and terms["no_valid_depth"] == 1.0
    total.backward()
    assert torch.isfinite(pred.grad).all()


def test_depth_loss_module_and_gradcheck():
    torch.manual_seed(2)
    gt = torch.rand(1, 1, 4, 6, dtype=torch.float64) + 1
    pred = (gt + 0.3 * torch.randn_like(gt)).requires_grad_()
    total, terms = DepthLoss()({"depth": pred}, {"depth": gt})
    assert set(terms) >= {"depth", "depth_abs", "depth_grad"} and math.isfinite(terms["depth"])
    total.backward()
    assert torch.isfinite(pred.grad).all()
    # c is a constant of the backward pass: dB/dp = sign(e) / N where |e| <= c, e / (c N) above
    p2 = pred.detach().clone().requires_grad_()
    adaptive_berhu_loss(p2, gt).backward()
    e = (p2 - gt).detach()
    c = 0.2 * e.abs().max()
    expect = torch.where(e.abs() <= c, e.sign(), e / c) / e.numel()
    torch.testing.assert_close(p2.grad, expect)
    with pytest.raises(ValueError, match="shape"):
        DepthLoss()({"depth": pred}, {"depth": gt[..., :3]})
