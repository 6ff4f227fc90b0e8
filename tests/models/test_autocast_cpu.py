"""Every registered model trains under CPU bfloat16 autocast (``trainer.amp=true`` on the CPU): the loss and every
gradient are finite."""
import pytest
import torch

from omnidl.models import create_model, list_models
from omnidl.models.registry import smoke_config


@pytest.mark.parametrize("name", list_models())
def test_model_trains_under_cpu_bfloat16_autocast(name):
    torch.manual_seed(0)
    cfg = smoke_config(name)
    model = create_model(name, **cfg["kwargs"]).train()
    h, w = cfg["size"]
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = model(torch.rand(2, 3, h, w))
        loss = sum(v.float().mean() for v in out.values() if isinstance(v, torch.Tensor) and v.is_floating_point())
    assert torch.isfinite(loss)
    loss.backward()
    bad = [n for n, p in model.named_parameters() if p.grad is not None and not torch.isfinite(p.grad).all()]
    assert not bad, bad[:5]
