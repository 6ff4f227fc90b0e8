"""ProjectedConv2d as a layer: drop-in for nn.Conv2d, shared sample positions, backends, compile/export, errors."""
from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from omnidl.cameras import Equirectangular, Pinhole, get_camera_class
from omnidl.nn import ProjectedConv2d, clear_sampling_cache, sampling_cache_info
from omnidl.nn.projected_conv import projected_sampling


@pytest.mark.parametrize("kwargs", [dict(kernel_size=3, padding=1), dict(kernel_size=5, stride=2, padding=2),
                                    dict(kernel_size=3, padding="same", dilation=2), dict(kernel_size=1),
                                    dict(kernel_size=3, padding=1, groups=2)])
def test_without_camera_is_nn_conv2d(kwargs):
    torch.manual_seed(0)
    ref = nn.Conv2d(4, 6, **kwargs)
    conv = ProjectedConv2d(4, 6, **kwargs)
    conv.load_state_dict(ref.state_dict())  # same keys and shapes
    assert list(conv.state_dict()) == list(ref.state_dict())
    x = torch.randn(2, 4, 9, 13)
    assert torch.equal(conv(x), ref(x))


def test_state_dict_loads_from_conv2d_with_camera():
    ref = nn.Conv2d(3, 5, 3, padding=1)
    conv = ProjectedConv2d(3, 5, 3, padding=1, camera=Equirectangular(width=32, height=16))
    conv.load_state_dict(ref.state_dict())
    assert torch.equal(conv.weight, ref.weight) and torch.equal(conv.bias, ref.bias)
    assert isinstance(conv, nn.Conv2d)


def test_camera_config_mapping_and_repr():
    conv = ProjectedConv2d(3, 5, 3, padding=1, camera={"type": "equirect", "width": 32, "height": 16})
    assert isinstance(conv.camera, Equirectangular)
    assert "Equirectangular(32x16)" in repr(conv)


def test_far_pinhole_is_close_to_conv2d():
    """A pinhole with a tiny field of view barely distorts the kernel: output ~ nn.Conv2d."""
    torch.manual_seed(0)
    cam = Pinhole(width=24, height=16, fx=2000.0, fy=2000.0, cx=12.0, cy=8.0)
    ref = nn.Conv2d(3, 4, 3, padding=1).double()
    conv = ProjectedConv2d(3, 4, 3, padding=1, camera=cam).double()
    conv.load_state_dict(ref.state_dict())
    x = torch.randn(1, 3, 16, 24, dtype=torch.float64)
    assert (conv(x) - ref(x)).abs().max() < 1e-3


def test_sample_positions_are_shared_by_geometry():
    clear_sampling_cache()
    cam = Equirectangular(width=32, height=16)
    a = ProjectedConv2d(3, 4, 3, padding=1, camera=cam)
    b = ProjectedConv2d(5, 2, 3, padding=1, camera=Equirectangular(width=32, height=16))  # equal camera
    x3, x5 = torch.randn(1, 3, 8, 16), torch.randn(2, 5, 8, 16)
    a(x3)
    b(x5)
    info = sampling_cache_info()
    assert info["taps"] == 1 and info["geometries"] == 1
    assert a.geometry == b.geometry
    assert projected_sampling(a.geometry, 8, 16, x3.device)[0] is projected_sampling(b.geometry, 8, 16, x3.device)[0]
    a(torch.randn(1, 3, 16, 32))  # a new input size: new positions
    ProjectedConv2d(3, 4, 3, stride=2, padding=1, camera=cam)(x3)  # a new stride: new positions
    a.double()(x3.double())  # another dtype: the same positions (float64)
    info = sampling_cache_info()
    assert info["geometries"] == 3 and info["taps"] == 3 and info["bytes"] > 0


def test_changing_a_geometry_attribute_changes_the_geometry():
    cam = Equirectangular(width=32, height=16)
    conv = ProjectedConv2d(3, 4, 3, padding=1, camera=cam).double()
    x = torch.randn(1, 3, 8, 16, dtype=torch.float64)
    before, y = conv.geometry, conv(x)
    conv.wrap = False
    assert conv.geometry != before and not (conv(x) - y).abs().max() < 1e-9       # the seam columns change
    conv.wrap = "auto"
    assert conv.geometry == before and torch.equal(conv(x), y)
    conv.camera = Equirectangular(width=32, height=16, lat_min=-1.2, lat_max=1.2)
    assert conv.geometry != before


def test_backends_agree_and_output_size():
    torch.manual_seed(1)
    cam = get_camera_class("kannala_brandt").example()
    fast = ProjectedConv2d(3, 4, 3, stride=2, padding=1, camera=cam, backend="op").double()
    tv = ProjectedConv2d(3, 4, 3, stride=2, padding=1, camera=cam, backend="torchvision").double()
    tv.load_state_dict(fast.state_dict())
    x = torch.randn(2, 3, 15, 17, dtype=torch.float64)
    y = fast(x)
    assert y.shape == nn.Conv2d(3, 4, 3, stride=2, padding=1)(x.float()).shape
    assert (y - tv(x)).abs().max() < 1e-10


def test_grouped_conv_uses_torchvision_in_auto():
    torch.manual_seed(2)
    cam = Equirectangular(width=32, height=16)
    conv = ProjectedConv2d(4, 6, 3, padding=1, groups=2, camera=cam).double()
    assert conv.resolved_backend() == "torchvision"
    x = torch.randn(1, 4, 8, 16, dtype=torch.float64)
    # each group equals its own ungrouped projected conv
    y = conv(x)
    for gi in range(2):
        part = ProjectedConv2d(2, 3, 3, padding=1, camera=cam, backend="op").double()
        part.weight.data.copy_(conv.weight[3 * gi:3 * gi + 3])
        part.bias.data.copy_(conv.bias[3 * gi:3 * gi + 3])
        assert (part(x[:, 2 * gi:2 * gi + 2]) - y[:, 3 * gi:3 * gi + 3]).abs().max() < 1e-10
    with pytest.raises(ValueError, match="groups=1"):
        ProjectedConv2d(4, 6, 3, groups=2, camera=cam, backend="op")


def test_invalid_samples_read_zero():
    KB = get_camera_class("kannala_brandt")
    cam = KB(width=32, height=32, fx=8.0, fy=8.0, cx=16.0, cy=16.0, max_fov=math.radians(150))
    conv = ProjectedConv2d(1, 1, 3, padding=1, camera=cam, bias=False)
    nn.init.constant_(conv.weight, 1.0)
    y = conv(torch.ones(1, 1, 32, 32)).detach()  # the path that records a gradient; a plain number to compare
    assert y[0, 0, 0, 0] == 0  # the corner sees nothing
    assert abs(float(y[0, 0, 16, 16]) - 9) < 1e-4  # the centre sees 9 valid samples of 1


def test_batch_equals_per_image_and_channels_last_input():
    torch.manual_seed(3)
    conv = ProjectedConv2d(3, 4, 3, padding=1, camera=Equirectangular(width=32, height=16)).double()
    x = torch.randn(3, 3, 8, 16, dtype=torch.float64)
    y = conv(x)
    assert torch.allclose(y[1:2], conv(x[1:2]), atol=1e-12)
    xc = x.to(memory_format=torch.channels_last).requires_grad_(True)
    yc = conv(xc)
    assert torch.allclose(yc, y, atol=1e-12)
    yc.sum().backward()
    xn = x.clone().requires_grad_(True)
    conv(xn).sum().backward()
    assert torch.allclose(xn.grad, xc.grad, atol=1e-12)
    wide = torch.cat([x, x], 1).to(memory_format=torch.channels_last)   # a channel slice of a channels-last map
    assert torch.allclose(conv(wide[:, 3:]), y, atol=1e-12)


def test_compile_fullgraph_and_export_on_a_cold_cache_and_new_sizes():
    """The sample positions are a registered op of the graph: compile and export need no warm cache, and a
    compiled layer meets a new input size (its own positions) with dynamic shapes too."""
    torch._dynamo.reset()
    torch.manual_seed(4)
    conv = ProjectedConv2d(4, 5, 3, padding=1, camera=Equirectangular(width=64, height=32))
    x, x2 = torch.randn(2, 4, 32, 64), torch.randn(1, 4, 16, 32)
    ref, ref2 = conv(x), conv(x2)
    clear_sampling_cache()
    compiled = torch.compile(conv, fullgraph=True, backend="aot_eager")
    torch.testing.assert_close(compiled(x), ref)
    torch.testing.assert_close(compiled(x2), ref2)                 # recompiled: dynamic sizes
    clear_sampling_cache()
    ep = torch.export.export(conv, (x,))
    torch.testing.assert_close(ep.module()(x), ref)
    targets = {str(n.target) for n in ep.graph.nodes if n.op == "call_function"}
    assert {"omnidl.projected_sampling.default", "omnidl.fixed_offset_conv2d.default"} <= targets


def test_fx_symbolic_trace():
    conv = ProjectedConv2d(4, 5, 3, padding=1, camera=Equirectangular(width=64, height=32))
    x = torch.randn(2, 4, 32, 64)
    torch.testing.assert_close(torch.fx.symbolic_trace(conv)(x), conv(x))


def test_double_backward():
    """Gradients of gradients flow through the layer (the op's backward is itself differentiable)."""
    torch.manual_seed(5)
    conv = ProjectedConv2d(2, 3, 3, padding=1, camera=Equirectangular(width=16, height=8)).double()
    x = torch.randn(1, 2, 8, 16, dtype=torch.float64, requires_grad=True)
    (gx,) = torch.autograd.grad(conv(x).square().sum(), x, create_graph=True)
    gx.square().sum().backward()
    assert conv.weight.grad is not None and torch.isfinite(conv.weight.grad).all()
    assert torch.autograd.gradgradcheck(lambda x, w: conv._conv_forward(x, w, None), (x, conv.weight))


def test_configuration_errors():
    cam = Equirectangular(width=32, height=16)
    with pytest.raises(ValueError, match="padding_mode"):
        ProjectedConv2d(3, 4, 3, padding=1, padding_mode="reflect", camera=cam)
    with pytest.raises(ValueError, match="backend"):
        ProjectedConv2d(3, 4, 3, camera=cam, backend="cuda")
    with pytest.raises(ValueError, match="wrap=True"):
        ProjectedConv2d(3, 4, 3, camera=Pinhole.example(), wrap=True)
    with pytest.raises(TypeError, match="camera"):
        ProjectedConv2d(3, 4, 3, camera="equirect")
    with pytest.raises(ValueError, match=r"\(B, 3, H, W\)"):
        ProjectedConv2d(3, 4, 3, camera=cam)(torch.randn(1, 2, 8, 8))
    with pytest.raises(ValueError, match="groups=1"):
        ProjectedConv2d(4, 4, 3, groups=2, camera=cam, backend="op")


@pytest.mark.parametrize("channels_last", [False, True])
def test_inplace_activation_after_the_op(channels_last):
    """The op's output is a tensor of its own: ReLU(inplace=True) right after it works with autograd."""
    conv = ProjectedConv2d(3, 4, 3, padding=1, camera=Equirectangular(width=32, height=16))
    x = torch.rand(2, 3, 16, 32, requires_grad=True)
    if channels_last:
        x = x.detach().to(memory_format=torch.channels_last).requires_grad_(True)
    y = torch.nn.functional.relu(conv(x), inplace=True)
    y.sum().backward()
    assert x.grad is not None and torch.isfinite(x.grad).all()
    assert conv.weight.grad is not None


def test_opcheck_projected_sampling():
    conv = ProjectedConv2d(4, 5, 3, stride=2, padding=1, camera=Equirectangular(width=64, height=32))
    pos, mask = projected_sampling(conv.geometry, 32, 64, torch.device("cpu"))
    assert pos.shape == (16, 32, 9, 2) and mask.shape == (16, 32, 9) and pos.dtype == torch.float64
    torch.library.opcheck(torch.ops.omnidl.projected_sampling.default, (conv.geometry, 32, 64, torch.device("cpu")))
