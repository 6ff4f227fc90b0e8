"""Contract tests run automatically on every registered model (timm-style)."""
import pytest
import torch

from omnidl.models import create_model, list_models
from omnidl.models.registry import smoke_config


@pytest.mark.parametrize("name", list_models())
def test_forward_backward_every_parameter_gets_gradient(name):
    torch.manual_seed(0)
    cfg = smoke_config(name)
    model = create_model(name, **cfg["kwargs"])
    model.train()
    h, w = cfg["size"]
    x = torch.rand(2, 3, h, w)
    out = model(x)
    assert isinstance(out, dict) and out, "forward must return a non-empty dict of named outputs"
    total = 0
    for key, val in out.items():
        if not isinstance(val, torch.Tensor) or not val.is_floating_point():
            continue
        assert torch.isfinite(val).all(), f"{name}: output {key!r} has non-finite values"
        total = total + val.float().mean()
    total.backward()
    missing = [n for n, p in model.named_parameters() if p.requires_grad and (p.grad is None or not torch.isfinite(p.grad).all())]
    assert not missing, f"{name}: parameters without a finite gradient: {missing[:10]}"
