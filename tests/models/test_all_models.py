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


@pytest.mark.parametrize("name", list_models())
def test_training_with_and_without_the_native_batch_norm_agrees(name, monkeypatch):
    """Every model trains its batch norms with omnidl.nn.batch_norm (native on NCHW maps): its modules are that
    class, and a training step's outputs and running statistics equal those of ``nn.BatchNorm2d``'s own forward
    (1e-4 of each tensor's scale: random weights, deep networks, float32). Its parameter gradients are compared as
    one vector (relative L2 distance 1e-2): a ReLU whose input lies within rounding of zero may switch sides and
    route one value's gradient differently (HorizonNet's smoke configuration has one, 9e-7 against 2.5e-7, which
    moves its first tower's weight gradient by 1 % and the whole by 8e-4). The batch norm's own gradients are
    compared element by element in tests/nn/test_batch_norm.py."""
    from omnidl.nn import batch_norm
    torch.manual_seed(0)
    cfg = smoke_config(name)
    model = create_model(name, **cfg["kwargs"])
    norms = [m for m in model.modules() if isinstance(m, torch.nn.BatchNorm2d)]
    assert norms and all(type(m) is batch_norm.BatchNorm2d for m in norms), name
    start = {k: v.clone() for k, v in model.state_dict().items()}
    h, w = cfg["size"]
    x = torch.rand(2, 3, h, w)
    runs = []
    for enabled in (True, False):
        monkeypatch.setattr(batch_norm, "ENABLED", enabled)
        model.load_state_dict(start)
        model.train()
        model.zero_grad(set_to_none=True)
        torch.manual_seed(1)                       # the same dropout masks
        out = model(x)
        sum(v.float().square().mean() for v in out.values()
            if isinstance(v, torch.Tensor) and v.is_floating_point()).backward()
        tensors = {k: v.detach() for k, v in out.items() if isinstance(v, torch.Tensor) and v.is_floating_point()}
        tensors.update((k, v.clone()) for k, v in model.state_dict().items() if "running" in k)
        runs.append((tensors, {n: p.grad for n, p in model.named_parameters() if p.grad is not None},
                     {k: v.clone() for k, v in model.state_dict().items() if "batches" in k}))
    (a, grad_a, count_a), (b, grad_b, count_b) = runs
    assert a.keys() == b.keys() and grad_a.keys() == grad_b.keys() and count_a.keys() == count_b.keys(), name
    for key in b:
        scale = b[key].abs().max().clamp_min(1e-6)
        torch.testing.assert_close(a[key] / scale, b[key] / scale, rtol=0, atol=1e-4, msg=f"{name}: {key}")
    assert all(torch.equal(count_a[k], count_b[k]) for k in count_b), name
    distance = sum(float((grad_a[k] - grad_b[k]).square().sum()) for k in grad_b) ** 0.5
    assert distance <= 1e-2 * sum(float(g.square().sum()) for g in grad_b.values()) ** 0.5, name
