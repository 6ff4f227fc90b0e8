import torch
import torch.nn.functional as F

from omnidl.losses.heatmap import HeatmapLoss, heatmap_bce, resize_target


def test_bce_matches_manual_formula_and_resizes_targets():
    g = torch.Generator().manual_seed(0)
    logits = torch.randn(2, 1, 8, 16, generator=g, dtype=torch.float64)
    target = torch.rand(2, 1, 32, 64, generator=g, dtype=torch.float64)
    t = target.reshape(2, 1, 8, 4, 16, 4).mean(dim=(3, 5))  # 4x4 block means
    assert torch.allclose(resize_target(target, (8, 16)), t)
    p = torch.sigmoid(logits)
    manual = -(3.0 * t * torch.log(p) + (1 - t) * torch.log(1 - p)).mean()
    assert torch.allclose(heatmap_bce(logits, target, pos_weight=3.0), manual)


def test_loss_terms_and_aux_maps_get_gradients():
    g = torch.Generator().manual_seed(1)
    out = {"horizon": torch.randn(2, 1, 16, 32, generator=g, requires_grad=True),
           "vp": torch.randn(2, 1, 16, 32, generator=g, requires_grad=True),
           "aux_4": torch.randn(2, 2, 8, 16, generator=g, requires_grad=True),
           "aux_8": torch.randn(2, 2, 4, 8, generator=g, requires_grad=True)}
    batch = {"horizon_map": torch.rand(2, 1, 32, 64, generator=g), "vp_map": torch.rand(2, 1, 32, 64, generator=g)}
    loss = HeatmapLoss(aux_weight=0.5, pos_weight=1.0)
    total, terms = loss(out, batch)
    expect = (F.binary_cross_entropy_with_logits(out["horizon"], resize_target(batch["horizon_map"], (16, 32)))
              + F.binary_cross_entropy_with_logits(out["vp"], resize_target(batch["vp_map"], (16, 32))))
    aux = 0
    for k in ("aux_4", "aux_8"):
        t = resize_target(torch.cat([batch["horizon_map"], batch["vp_map"]], 1), tuple(out[k].shape[-2:]))
        aux = aux + F.binary_cross_entropy_with_logits(out[k], t, reduction="none").mean(dim=(0, 2, 3)).sum()
    assert torch.allclose(total, expect + 0.5 * aux / 2)
    assert set(terms) >= {"bce_horizon", "bce_vp", "bce_aux_4", "bce_aux_8", "total"}
    total.backward()
    assert all(v.grad is not None and torch.isfinite(v.grad).all() for v in out.values())


def test_missing_keys_have_clear_errors():
    import pytest
    loss = HeatmapLoss()
    with pytest.raises(KeyError, match="horizon_map"):
        loss({"horizon": torch.zeros(1, 1, 4, 8), "vp": torch.zeros(1, 1, 4, 8)}, {})
