"""The CUDA sampling of ProjectedConv2d's fast backend (:mod:`omnidl.nn.grid_conv`), run here on the CPU (the same
ops): equal to ``deform_conv2d`` with the same offsets for every example camera (float64 1e-12, float32 1e-5),
strides and dilations, wraps, a non-binary mask; gradcheck; the layer takes it on CUDA only."""
import pytest
import torch

from omnidl.cameras import Equirectangular, get_camera_class, list_cameras
from omnidl.nn import ProjectedConv2d, clear_plan_cache, grid_conv
from omnidl.nn.projected_conv import _geometry
from omnidl.nn.sampling import deform_conv2d_reference

EXAMPLES = {f"{name}-{i}": cam for name in list_cameras() for i, cam in enumerate(get_camera_class(name).examples())}


def _plan_and_reference(conv: ProjectedConv2d, hw):
    key = conv.geometry_key(hw)
    off, mask = _geometry(key)
    _, in_hw, k, s, p, d, wrap, _, _ = key
    plan = grid_conv.build_grid_plan(off, mask, in_hw, k, s, p, d, wrap=wrap)

    def reference(x, weight, bias):
        return deform_conv2d_reference(x, weight, bias, off.to(x.dtype), mask.to(x.dtype), conv.stride,
                                       conv._padding_pair(), conv.dilation, wrap=wrap)
    return plan, reference


@pytest.mark.parametrize("name", sorted(EXAMPLES))
@pytest.mark.parametrize("dt, tol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_equals_deform_conv2d_for_every_camera(name, dt, tol):
    cam = EXAMPLES[name].resized(32, 24) if hasattr(EXAMPLES[name], "resized") else EXAMPLES[name]
    torch.manual_seed(0)
    conv = ProjectedConv2d(5, 4, 3, padding=1, camera=cam).to(dt)
    hw = (cam.height, cam.width)
    plan, reference = _plan_and_reference(conv, hw)
    assert plan is not None
    x = torch.randn(2, 5, *hw, dtype=dt)
    y = grid_conv.grid_conv2d(x, conv.weight, conv.bias, plan.to(dtype=dt))
    ref = reference(x, conv.weight, conv.bias)
    assert y.shape == ref.shape
    torch.testing.assert_close(y, ref, rtol=tol, atol=tol * float(ref.detach().abs().max()))


@pytest.mark.parametrize("kwargs", [dict(kernel_size=3, stride=2, padding=1), dict(kernel_size=3, padding=2, dilation=2),
                                    dict(kernel_size=5, padding=2), dict(kernel_size=(1, 3), padding=(0, 1)),
                                    dict(kernel_size=3, padding=1, bias=False)])
@pytest.mark.parametrize("wrap", [True, False])
def test_strides_dilations_kernels_and_wraps(kwargs, wrap):
    torch.manual_seed(1)
    conv = ProjectedConv2d(3, 6, camera=Equirectangular(width=40, height=20), wrap=wrap, **kwargs).double()
    plan, reference = _plan_and_reference(conv, (20, 40))
    x = torch.randn(1, 3, 20, 40, dtype=torch.float64)
    torch.testing.assert_close(grid_conv.grid_conv2d(x, conv.weight, conv.bias, plan),
                               reference(x, conv.weight, conv.bias), rtol=1e-12, atol=1e-12)


def test_a_non_binary_mask_scales_the_columns():
    torch.manual_seed(2)
    conv = ProjectedConv2d(3, 4, 3, padding=1, camera=Equirectangular(width=24, height=12)).double()
    key = conv.geometry_key((12, 24))
    off, mask = _geometry(key)
    soft = torch.rand_like(mask) * (mask != 0)
    plan = grid_conv.build_grid_plan(off, soft, (12, 24), (3, 3), (1, 1), (1, 1), (1, 1), wrap=True)
    assert plan.scale is not None
    x = torch.randn(2, 3, 12, 24, dtype=torch.float64)
    ref = deform_conv2d_reference(x, conv.weight, conv.bias, off, soft, (1, 1), (1, 1), (1, 1), wrap=True)
    torch.testing.assert_close(grid_conv.grid_conv2d(x, conv.weight, conv.bias, plan), ref, rtol=1e-12, atol=1e-12)


def test_gradcheck():
    torch.manual_seed(3)
    conv = ProjectedConv2d(2, 3, 3, padding=1, camera=Equirectangular(width=12, height=6)).double()
    plan, _ = _plan_and_reference(conv, (6, 12))
    x = torch.randn(1, 2, 6, 12, dtype=torch.float64, requires_grad=True)
    w = conv.weight.detach().clone().requires_grad_(True)
    b = conv.bias.detach().clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x, w, b: grid_conv.grid_conv2d(x, w, b, plan), (x, w, b))


def test_the_layer_takes_it_on_cuda_only(monkeypatch):
    """On the CPU the plan path runs; where :func:`grid_conv.applies` (CUDA) the grid path, same values."""
    clear_plan_cache()
    torch.manual_seed(4)
    conv = ProjectedConv2d(4, 4, 3, padding=1, camera=Equirectangular(width=32, height=16)).double()
    x = torch.randn(1, 4, 16, 32, dtype=torch.float64)
    assert not grid_conv.applies(x)
    plan_path = conv(x)
    monkeypatch.setattr(grid_conv, "applies", lambda x: True)
    torch.testing.assert_close(conv(x), plan_path, rtol=1e-12, atol=1e-12)
    with torch.autocast("cpu", dtype=torch.bfloat16):   # the float32 rule of the fast backend holds on the grid path
        assert conv.float()(x.float()).dtype == torch.bfloat16


def test_bad_operands_are_named_errors():
    conv = ProjectedConv2d(2, 3, 3, padding=1, camera=Equirectangular(width=12, height=6)).double()
    plan, _ = _plan_and_reference(conv, (6, 12))
    with pytest.raises(ValueError, match="does not fit the plan"):
        grid_conv.grid_conv2d(torch.randn(1, 2, 6, 10, dtype=torch.float64), conv.weight, conv.bias, plan)
    with pytest.raises(ValueError, match="input channels"):
        grid_conv.grid_conv2d(torch.randn(1, 3, 6, 12, dtype=torch.float64), conv.weight, conv.bias, plan)


@pytest.mark.parametrize("sample_channels", [1, 4, 6, 1000])
@pytest.mark.parametrize("channels_last", [False, True])
def test_channel_groups_and_memory_formats_give_the_same_result(sample_channels, channels_last, monkeypatch):
    torch.manual_seed(5)
    conv = ProjectedConv2d(12, 5, 3, padding=1, camera=Equirectangular(width=32, height=16)).double()
    plan, reference = _plan_and_reference(conv, (16, 32))
    x = torch.randn(2, 12, 16, 32, dtype=torch.float64)
    ref = reference(x, conv.weight, conv.bias)
    if channels_last:
        x = x.contiguous(memory_format=torch.channels_last)
    monkeypatch.setattr(grid_conv, "SAMPLE_CHANNELS", sample_channels)
    torch.testing.assert_close(grid_conv.grid_conv2d(x, conv.weight, conv.bias, plan), ref, rtol=1e-12, atol=1e-12)
