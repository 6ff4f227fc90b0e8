"""convert_conv2d: every k>=min_kernel nn.Conv2d of a network becomes a ProjectedConv2d with the same weights."""
from __future__ import annotations

import torch
import torchvision
from torch import nn

from omnidl.cameras import Equirectangular, Pinhole
from omnidl.nn import CircularConv2d, ProjectedConv2d, convert_conv2d


class TinyUNet(nn.Module):
    """A two-level U-Net (conv blocks, max-pool, transposed-conv upsampling, skip concatenation)."""

    def __init__(self, c: int = 4) -> None:
        super().__init__()
        self.enc1 = nn.Sequential(nn.Conv2d(3, c, 3, padding=1), nn.BatchNorm2d(c), nn.ReLU())
        self.enc2 = nn.Sequential(nn.MaxPool2d(2), nn.Conv2d(c, 2 * c, 3, padding=1), nn.ReLU())
        self.up = nn.ConvTranspose2d(2 * c, c, 2, stride=2)
        self.dec = nn.Sequential(nn.Conv2d(2 * c, c, 3, padding=1), nn.ReLU(), nn.Conv2d(c, 2, 1))
        self.wrap = CircularConv2d(2, 2, 3, padding=1)  # a Conv2d subclass: left alone

    def forward(self, x):
        e1 = self.enc1(x)
        e2 = self.enc2(e1)
        return self.wrap(self.dec(torch.cat([e1, self.up(e2)], 1)))


def _count(model: nn.Module, cls) -> int:
    return sum(type(m) is cls for m in model.modules())


def test_unet_conversion_keeps_weights_and_runs():
    torch.manual_seed(0)
    net = TinyUNet()
    before = {k: v.clone() for k, v in net.state_dict().items()}
    cam = Equirectangular(width=64, height=32)
    out = convert_conv2d(net, cam)
    assert out is net
    assert _count(net, ProjectedConv2d) == 3  # the 3x3 convs; the 1x1, the transposed and the circular stay
    assert _count(net, nn.Conv2d) == 1 and _count(net, CircularConv2d) == 1
    after = net.state_dict()
    assert list(after) == list(before)
    assert all(torch.equal(before[k], after[k]) for k in before)
    x = torch.randn(1, 3, 32, 64, requires_grad=True)
    y = net(x)
    assert y.shape == (1, 2, 32, 64)
    y.square().mean().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in net.parameters())


def test_min_kernel_and_parameter_sharing():
    net = nn.Sequential(nn.Conv2d(3, 4, 3, padding=1), nn.Conv2d(4, 4, 5, padding=2), nn.Conv2d(4, 4, 1))
    w = net[1].weight
    convert_conv2d(net, Equirectangular(width=32, height=16), min_kernel=5)
    assert type(net[0]) is nn.Conv2d and isinstance(net[1], ProjectedConv2d) and type(net[2]) is nn.Conv2d
    assert net[1].weight is w  # the very same Parameter (optimisers keep working)
    net[1].camera = None  # a converted layer without camera is the original conv again
    x = torch.randn(1, 4, 8, 16)
    assert torch.equal(net[1](x), nn.functional.conv2d(x, w, net[1].bias, padding=2))


def test_resnet18_converted_forward_backward():
    torch.manual_seed(0)
    net = torchvision.models.resnet18(num_classes=5)
    n3 = sum(isinstance(m, nn.Conv2d) and max(m.kernel_size) >= 3 for m in net.modules())
    convert_conv2d(net, Equirectangular(width=64, height=32))
    assert _count(net, ProjectedConv2d) == n3 == 17  # conv1 (7x7) and sixteen 3x3
    y = net(torch.randn(1, 3, 32, 64))
    assert y.shape == (1, 5) and torch.isfinite(y).all()
    y.sum().backward()
    assert all(p.grad is not None for p in net.parameters())


def test_converted_resnet_with_narrow_pinhole_matches_original():
    """A narrow-FOV pinhole barely bends the kernels: the converted network ~ the original one."""
    torch.manual_seed(0)
    net = torchvision.models.resnet18(num_classes=4).eval().double()
    x = torch.randn(1, 3, 32, 48, dtype=torch.float64)
    y0 = net(x)
    convert_conv2d(net, Pinhole(width=48, height=32, fx=5000.0, fy=5000.0, cx=24.0, cy=16.0))
    assert (net(x) - y0).abs().max() < 1e-2 * y0.abs().max()


def test_camera_config_mapping():
    net = convert_conv2d(nn.Sequential(nn.Conv2d(3, 4, 3, padding=1)), {"type": "equirect", "width": 32,
                                                                          "height": 16})
    assert isinstance(net[0].camera, Equirectangular)
