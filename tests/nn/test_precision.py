"""ProjectedConv2d under autocast and in half precision on the CPU: under autocast its op computes in float32 (as
torchvision's deform_conv2d) and the layers around it in the autocast dtype; a half-precision module runs in its
own dtype."""
import pytest
import torch

from omnidl.cameras import Equirectangular
from omnidl.nn import ProjectedConv2d


def _net():
    torch.manual_seed(0)
    return torch.nn.Sequential(torch.nn.Conv2d(4, 6, 1),
                               ProjectedConv2d(6, 5, 3, padding=1, camera=Equirectangular(width=32, height=16)),
                               torch.nn.Conv2d(5, 3, 1))


@pytest.mark.parametrize("dt", [torch.bfloat16, torch.float16])
def test_autocast_cpu_runs_forward_backward_in_the_autocast_dtype(dt):
    net = _net()
    x = torch.randn(2, 4, 16, 32, requires_grad=True)
    ref = net(x)
    with torch.autocast("cpu", dtype=dt):
        assert net[1](net[0](x)).dtype == torch.float32
        y = net(x)
    assert y.dtype == dt
    torch.testing.assert_close(y.float(), ref, rtol=0, atol=0.03 * float(ref.detach().abs().max()))
    y.float().sum().backward()
    assert torch.isfinite(x.grad).all() and torch.isfinite(net[1].weight.grad).all()


@pytest.mark.parametrize("dt", [torch.bfloat16, torch.float16])
def test_half_precision_module(dt):
    net = _net()
    x = torch.randn(1, 4, 16, 32)
    ref = net(x)
    net = net.to(dt)
    xh = x.to(dt).requires_grad_(True)
    y = net(xh)
    assert y.dtype == dt
    torch.testing.assert_close(y.float(), ref, rtol=0, atol=0.03 * float(ref.detach().abs().max()))
    y.float().sum().backward()
    assert xh.grad.dtype == dt and net[1].weight.grad.dtype == dt
