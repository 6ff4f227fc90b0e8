"""GPU checks of every registered model (``pytest -m cuda``; skipped without a CUDA device): forward and
backward on CUDA match the CPU, and bfloat16 / float16 autocast runs with finite outputs and gradients."""
import pytest
import torch

from omnidl.models import create_model, list_models
from omnidl.models.registry import smoke_config

pytestmark = [pytest.mark.cuda,
              pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA is not available")]
CUDA = torch.device("cuda")


def _loss(out: dict) -> torch.Tensor:
    return sum(v.float().mean() for v in out.values() if isinstance(v, torch.Tensor) and v.is_floating_point())


@pytest.mark.parametrize("name", list_models())
def test_model_forward_backward_cuda_matches_cpu(name):
    torch.manual_seed(0)
    cfg = smoke_config(name)
    model = create_model(name, **cfg["kwargs"]).double().eval()  # eval: no dropout / batch statistics
    h, w = cfg["size"]
    x = torch.rand(2, 3, h, w, dtype=torch.float64)
    out_cpu = model(x)
    _loss(out_cpu).backward()
    grads_cpu = {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}
    model.zero_grad(set_to_none=True)
    model = model.to(CUDA)
    out = model(x.to(CUDA))
    for k, v in out_cpu.items():
        if isinstance(v, torch.Tensor) and v.is_floating_point():
            torch.testing.assert_close(out[k].cpu(), v, rtol=1e-7, atol=1e-7, msg=f"{name}: output {k}")
    _loss(out).backward()
    for n, p in model.named_parameters():
        if n in grads_cpu:
            torch.testing.assert_close(p.grad.cpu(), grads_cpu[n], rtol=1e-6, atol=1e-7, msg=f"{name}: grad {n}")


@pytest.mark.parametrize("dt", [torch.bfloat16, torch.float16])
@pytest.mark.parametrize("name", list_models())
def test_model_autocast_cuda(name, dt):
    torch.manual_seed(0)
    cfg = smoke_config(name)
    model = create_model(name, **cfg["kwargs"]).to(CUDA).train()
    h, w = cfg["size"]
    x = torch.rand(2, 3, h, w, device=CUDA)
    with torch.autocast("cuda", dtype=dt):
        out = model(x)
        loss = _loss(out)
    assert torch.isfinite(loss)
    loss.backward()
    bad = [n for n, p in model.named_parameters() if p.grad is not None and not torch.isfinite(p.grad).all()]
    assert not bad, f"{name}: non-finite gradients under {dt} autocast: {bad[:5]}"
