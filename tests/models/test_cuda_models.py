"""GPU checks of every registered model (``pytest -m cuda``; skipped without a CUDA device): forward and
backward on CUDA match the CPU, and bfloat16 / float16 autocast runs with finite outputs and gradients."""
import pytest
import torch

from omnidl.models import create_model, list_models
from omnidl.models.registry import smoke_config

from .test_all_models import IDS, VARIANTS, build

pytestmark = [pytest.mark.cuda,
              pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA is not available")]
CUDA = torch.device("cuda")


def _loss(out: dict) -> torch.Tensor:
    return sum(v.float().mean() for v in out.values() if isinstance(v, torch.Tensor) and v.is_floating_point())


@pytest.mark.parametrize("name,conv", VARIANTS, ids=IDS)
def test_model_forward_backward_cuda_matches_cpu(name, conv):
    model, x = build(name, conv)
    model, x = model.double().eval(), x.double()  # eval: no dropout / batch statistics
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


def _cpu_and_cuda_eval(model, x):
    """``model(x)`` without autograd on the CPU, then on CUDA with TF32 off (both float32 arithmetic)."""
    tf32 = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False
    try:
        with torch.no_grad():
            ref = model(x)
            return ref, model.to(CUDA)(x.to(CUDA))
    finally:
        torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = tf32


@pytest.mark.parametrize("name", list_models())
def test_model_eval_float32_cuda_matches_cpu(name):
    """Eval float32 on the CPU and on CUDA agree (cuDNN's TF32 is switched off so that both are float32
    arithmetic)."""
    torch.manual_seed(0)
    cfg = smoke_config(name)
    model = create_model(name, **cfg["kwargs"]).eval()
    h, w = cfg["size"]
    x = torch.rand(1, 3, h, w)
    ref, out = _cpu_and_cuda_eval(model, x)
    for k, v in ref.items():
        if isinstance(v, torch.Tensor) and v.is_floating_point():
            scale = float(v.abs().max()) + 1e-6
            torch.testing.assert_close(out[k].cpu(), v, rtol=1e-4, atol=1e-4 * scale, msg=f"{name}: output {k}")


def test_fredsnet_resnet50_eval_cuda_matches_cpu():
    """The thesis model (ResNet-50, width 1) at 256x128."""
    torch.manual_seed(0)
    model = create_model("fredsnet", backbone="resnet50", width=1.0).eval()
    x = torch.rand(1, 3, 128, 256)
    ref, out = _cpu_and_cuda_eval(model, x)
    for k in ("depth", "semantic"):
        scale = float(ref[k].abs().max())
        torch.testing.assert_close(out[k].cpu(), ref[k], rtol=1e-4, atol=1e-4 * scale, msg=k)


@pytest.mark.parametrize("name,conv", VARIANTS, ids=IDS)
def test_model_eval_forward_replays_from_a_cuda_graph(name, conv):
    """Batch-1 inference is launch-bound on a GPU; a CUDA graph (``torch.compile(mode="reduce-overhead")``) removes
    the launch gaps. That needs a forward without host syncs or host-to-device copies: captured once, the graph
    replays on new input what the eager forward computes."""
    model, x = build(name, conv)
    model, x = model.to(CUDA).eval(), x[:1].to(CUDA)
    with torch.no_grad():
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):                     # warm-up: plans, caches, cuDNN's choices
            for _ in range(2):
                model(x)
        torch.cuda.current_stream().wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            out = model(x)
        x.copy_(torch.rand_like(x))
        graph.replay()
        eager = model(x)
    for k, v in eager.items():
        if isinstance(v, torch.Tensor) and v.is_floating_point():
            torch.testing.assert_close(out[k], v, rtol=1e-5, atol=1e-5 * (float(v.abs().max()) + 1e-6), msg=k)
