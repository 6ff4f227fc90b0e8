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


@pytest.mark.parametrize("name", list_models())
def test_eval_outputs_equal_with_and_without_the_packed_inference_convolutions(name, monkeypatch):
    """Eval without autograd folds BatchNorm and runs prepacked oneDNN convolutions (omnidl.nn.inference); the
    outputs must be those of the modules' own composition (1e-4 of each output's scale: random weights, deep
    networks, float32)."""
    import omnidl.nn.inference as inf
    torch.manual_seed(0)
    cfg = smoke_config(name)
    model = create_model(name, **cfg["kwargs"])
    for m in model.modules():                      # non-trivial running statistics
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.2, 0.2)
            m.running_var.uniform_(0.5, 1.5)
    model.eval()
    h, w = cfg["size"]
    x = torch.rand(1, 3, h, w)
    outs = []
    for enabled in (True, False):
        monkeypatch.setattr(inf, "ENABLED", enabled)
        with torch.no_grad():
            outs.append(model(x))
    for key, val in outs[1].items():
        if isinstance(val, torch.Tensor) and val.is_floating_point():
            scale = val.abs().max().clamp_min(1e-6)
            torch.testing.assert_close(outs[0][key] / scale, val / scale, rtol=0, atol=1e-4, msg=f"{name}: {key}")
