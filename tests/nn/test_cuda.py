"""GPU checks (``pytest -m cuda``; skipped without a CUDA device): every registered camera and ProjectedConv2d's op
(its CUDA kernel: one grid_sample, one 1x1 convolution) on CUDA, against the CPU and against torchvision's
deform_conv2d on CUDA, under deterministic algorithms, and autocast (bfloat16 / float16)."""
import pytest
import torch

from omnidl.cameras import get_camera_class, list_cameras
from omnidl.nn import ProjectedConv2d, clear_sampling_cache

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
def test_projected_conv_op_cuda_matches_deform_conv2d_cuda_and_cpu(name):
    cam = EXAMPLES[name]
    clear_sampling_cache()
    torch.manual_seed(0)
    fast = ProjectedConv2d(6, 5, 3, padding=1, camera=cam, backend="op").double()
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


def test_projected_conv_cuda_under_deterministic_algorithms():
    """grid_sample's CUDA backward has no deterministic kernel: under torch.use_deterministic_algorithms the op's
    CUDA backward takes its PyTorch implementation (index_add), equal in value and repeatable bit for bit."""
    from omnidl.cameras import Equirectangular
    torch.manual_seed(0)
    conv = ProjectedConv2d(8, 8, 3, padding=1, camera=Equirectangular(width=64, height=32)).double().to(CUDA)
    x = torch.randn(2, 8, 32, 64, device=CUDA, dtype=torch.float64, requires_grad=True)
    conv(x).square().sum().backward()
    ref = x.grad.clone()
    torch.use_deterministic_algorithms(True)
    try:
        grads = []
        for _ in range(2):
            x.grad = None
            conv(x).square().sum().backward()
            grads.append(x.grad.clone())
    finally:
        torch.use_deterministic_algorithms(False)
    assert torch.equal(grads[0], grads[1])
    torch.testing.assert_close(grads[0], ref, rtol=0, atol=1e-10)


@pytest.mark.parametrize("dt", [torch.bfloat16, torch.float16])
@pytest.mark.parametrize("channels_last", [False, True])
def test_projected_conv_autocast_cuda(dt, channels_last):
    """Under autocast the op computes in float32 (as torchvision's deform_conv2d); the layers around it run in the
    autocast dtype."""
    from omnidl.cameras import Equirectangular
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Conv2d(8, 8, 1), ProjectedConv2d(8, 8, 3, padding=1,
                                                                         camera=Equirectangular(width=64, height=32)),
                              torch.nn.Conv2d(8, 4, 1))
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
