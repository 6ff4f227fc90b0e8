"""GPU checks (``pytest -m cuda``; skipped without a CUDA device): every registered camera and the
ProjectedConv2d fast backend on CUDA, against the CPU and against torchvision's deform_conv2d on CUDA,
and autocast (bfloat16 / float16)."""
import pytest
import torch

from omnidl.cameras import get_camera_class, list_cameras
from omnidl.nn import ProjectedConv2d, clear_plan_cache

pytestmark = [pytest.mark.cuda,
              pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA is not available")]

EXAMPLES = {f"{name}-{i}": cam for name in list_cameras() for i, cam in enumerate(get_camera_class(name).examples())}
CUDA = torch.device("cuda")


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_camera_project_unproject_on_cuda_match_cpu(name):
    cam = EXAMPLES[name]
    g = torch.Generator().manual_seed(0)
    uv = torch.rand(500, 2, generator=g, dtype=torch.float64) * torch.tensor([cam.width, cam.height],
                                                                                dtype=torch.float64)
    rays_cpu = cam.unproject(uv)
    rays = cam.unproject(uv.to(CUDA))
    assert rays.direction.device.type == "cuda"
    torch.testing.assert_close(rays.direction.cpu(), rays_cpu.direction, rtol=0, atol=1e-9)
    assert torch.equal(rays.valid.cpu(), rays_cpu.valid)
    pts = (rays_cpu.origin + 2.0 * rays_cpu.direction)[rays_cpu.valid]
    pc = pts.to(CUDA).requires_grad_(True)
    uv_gpu, ok = cam.project(pc)
    uv_cpu, ok_cpu = cam.project(pts)
    assert torch.equal(ok.cpu(), ok_cpu)
    torch.testing.assert_close(uv_gpu.detach().cpu()[ok_cpu], uv_cpu[ok_cpu], rtol=0, atol=1e-6)
    uv_gpu[ok].sum().backward()
    assert torch.isfinite(pc.grad).all()


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_projected_conv_fast_cuda_matches_deform_conv2d_cuda_and_cpu(name):
    cam = EXAMPLES[name]
    clear_plan_cache()
    torch.manual_seed(0)
    fast = ProjectedConv2d(6, 5, 3, padding=1, camera=cam, backend="fast").double()
    tv = ProjectedConv2d(6, 5, 3, padding=1, camera=cam, backend="torchvision").double()
    tv.load_state_dict(fast.state_dict())
    x = torch.randn(2, 6, 24, 32, dtype=torch.float64)
    y_cpu = fast(x)
    fast, tv = fast.to(CUDA), tv.to(CUDA)
    xg = x.to(CUDA).requires_grad_(True)
    xr = x.to(CUDA).requires_grad_(True)
    y, yr = fast(xg), tv(xr)
    torch.testing.assert_close(y, yr, rtol=0, atol=1e-10)
    torch.testing.assert_close(y.cpu(), y_cpu, rtol=0, atol=1e-10)
    go = torch.randn_like(y)
    y.backward(go)
    yr.backward(go)
    torch.testing.assert_close(xg.grad, xr.grad, rtol=0, atol=1e-10)
    torch.testing.assert_close(fast.weight.grad, tv.weight.grad, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("dt", [torch.bfloat16, torch.float16])
@pytest.mark.parametrize("channels_last", [False, True])
def test_projected_conv_autocast_cuda(dt, channels_last):
    from omnidl.cameras import Equirectangular
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Conv2d(8, 8, 1), ProjectedConv2d(8, 8, 3, padding=1,
                                                                         camera=Equirectangular(width=64, height=32)))
    net = net.to(CUDA)
    x = torch.randn(2, 8, 32, 64, device=CUDA)
    if channels_last:
        x = x.contiguous(memory_format=torch.channels_last)
    ref = net(x)
    x.requires_grad_(True)
    with torch.autocast("cuda", dtype=dt):
        y = net(x)
    assert y.dtype == dt
    torch.testing.assert_close(y.float(), ref, rtol=0, atol=0.03 * float(ref.detach().abs().max()))
    y.float().sum().backward()
    assert torch.isfinite(x.grad).all()


def _rel(a, b):
    return float((a.detach().double() - b.detach().double()).abs().max() / b.detach().double().abs().max())


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_projected_conv_fused_triton_float32_matches_deform_conv2d_cuda(name, monkeypatch):
    """Float32 on CUDA with the fused Triton kernels on (omnidl.nn.triton_conv): forward and the three gradients
    equal to deform_conv2d in float64 on CUDA (TF32 off: 1e-5 of the largest value)."""
    pytest.importorskip("triton")
    from omnidl.nn import triton_conv
    monkeypatch.setattr(triton_conv, "ENABLED", True)
    cam = EXAMPLES[name]
    clear_plan_cache()
    torch.manual_seed(0)
    fast = ProjectedConv2d(6, 5, 3, padding=1, camera=cam, backend="fast").to(CUDA)
    tv = ProjectedConv2d(6, 5, 3, padding=1, camera=cam, backend="torchvision").double().to(CUDA)
    tv.load_state_dict(fast.state_dict())
    x = torch.randn(2, 6, 24, 32, device=CUDA)
    assert triton_conv.applies(x, fast.weight)
    xg = x.clone().requires_grad_(True)
    xr = x.double().requires_grad_(True)
    with torch.backends.cudnn.flags(enabled=True, benchmark=False, deterministic=False, allow_tf32=False):
        y = fast(xg)
        yr = tv(xr)
        go = torch.randn_like(y)
        y.backward(go)
        yr.backward(go.double())
    assert _rel(y, yr) <= 1e-5
    assert _rel(xg.grad, xr.grad) <= 1e-5
    assert _rel(fast.weight.grad, tv.weight.grad) <= 1e-5
    assert _rel(fast.bias.grad, tv.bias.grad) <= 1e-5


@pytest.mark.parametrize("channels_last", [False, True])
@pytest.mark.parametrize("C, N, hw", [(64, 64, (32, 64)), (40, 70, (17, 35)), (3, 1, (16, 32))])
def test_projected_conv_fused_triton_tf32_and_layouts(C, N, hw, channels_last, monkeypatch):
    """Under PyTorch's default TF32 policy (as cuDNN's convolution) the fused kernels stay within TF32's rounding
    of deform_conv2d; channels-last in, channels-last out; repeated backward passes are bitwise equal
    (no atomics), also under torch.use_deterministic_algorithms."""
    pytest.importorskip("triton")
    from omnidl.cameras import Equirectangular
    from omnidl.nn import triton_conv
    monkeypatch.setattr(triton_conv, "ENABLED", True)
    torch.manual_seed(0)
    fast = ProjectedConv2d(C, N, 3, padding=1, camera=Equirectangular(width=hw[1], height=hw[0])).to(CUDA)
    tv = ProjectedConv2d(C, N, 3, padding=1, camera=Equirectangular(width=hw[1], height=hw[0]),
                         backend="torchvision").double().to(CUDA)
    tv.load_state_dict(fast.state_dict())
    x = torch.randn(2, C, *hw, device=CUDA)
    if channels_last:
        x = x.contiguous(memory_format=torch.channels_last)
    xg = x.clone().requires_grad_(True)
    assert triton_conv.applies(x, fast.weight)
    y = fast(xg)
    yr = tv(x.double())
    assert y.is_contiguous(memory_format=torch.channels_last if channels_last and C > 1 else torch.contiguous_format)
    assert _rel(y, yr) <= 5e-3
    go = torch.randn_like(y)
    y.backward(go)
    g1 = (xg.grad.clone(), fast.weight.grad.clone())
    torch.use_deterministic_algorithms(True)
    try:
        xg.grad = None
        fast.zero_grad()
        fast(xg).backward(go)
    finally:
        torch.use_deterministic_algorithms(False)
    assert torch.equal(g1[0], xg.grad) and torch.equal(g1[1], fast.weight.grad)
