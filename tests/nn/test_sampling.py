"""ProjectedConv2d's op (torch.ops.omnidl.fixed_offset_conv2d) equals torchvision's deform_conv2d with the same
offsets (float64, 1e-10) for every camera family, outputs and gradients."""
from __future__ import annotations

import pytest
import torch

from omnidl.cameras import Equirectangular, get_camera_class
from omnidl.nn import (ProjectedConv2d, compute_sampling, deform_conv2d_reference, fixed_offset_conv2d,
                       sample_positions)

TOL = 1e-10


def _camera(name: str):
    if name == "equirect":
        return Equirectangular(width=48, height=24)
    return get_camera_class(name).example()


def _input_hw(cam) -> tuple[int, int]:
    return (12, 24) if cam.width >= 2 * cam.height else (14, 14)


def _compare(cam, k: int, s: int, d: int, wrap, dtype=torch.float64, batch: int = 2, tol: float = TOL):
    torch.manual_seed(k * 100 + s * 10 + d)
    H, W = _input_hw(cam)
    fast = ProjectedConv2d(3, 4, k, stride=s, padding=d * (k // 2), dilation=d, camera=cam, wrap=wrap,
                           backend="op").to(dtype)
    ref = ProjectedConv2d(3, 4, k, stride=s, padding=d * (k // 2), dilation=d, camera=cam, wrap=wrap,
                          backend="torchvision").to(dtype)
    ref.load_state_dict(fast.state_dict())
    x = torch.randn(batch, 3, H, W, dtype=dtype, requires_grad=True)
    y = fast(x)
    g = torch.randn_like(y)
    grads = torch.autograd.grad(y, [x, fast.weight, fast.bias], g)
    y_ref = ref(x)
    grads_ref = torch.autograd.grad(y_ref, [x, ref.weight, ref.bias], g)
    assert y.shape == y_ref.shape
    assert (y - y_ref).abs().max() < tol * max(1.0, y_ref.abs().max())
    for a, b, name in zip(grads, grads_ref, ("input", "weight", "bias")):
        assert (a - b).abs().max() < tol * max(1.0, b.abs().max()), name
    return y


@pytest.mark.parametrize("camera", ["equirect", "kannala_brandt", "scaramuzza", "catadioptric"])
@pytest.mark.parametrize("k", [3, 5, 7])
@pytest.mark.parametrize("s", [1, 2])
@pytest.mark.parametrize("d", [1, 2])
def test_op_equals_deform_conv2d(camera, k, s, d):
    cam = _camera(camera)
    _compare(cam, k, s, d, wrap="auto")


@pytest.mark.parametrize("k,s,d", [(3, 1, 1), (3, 2, 2), (7, 2, 1)])
def test_equirect_without_wrap_equals_deform_conv2d(k, s, d):
    _compare(Equirectangular(width=48, height=24), k, s, d, wrap=False)


def test_wrap_reference_is_circular_padding():
    """With wrap, the reference convolves a circularly padded panorama: the seam column sees the other side."""
    cam = Equirectangular(width=48, height=24)
    x = torch.randn(1, 2, 12, 24, dtype=torch.float64)
    conv_w = ProjectedConv2d(2, 1, 3, padding=1, camera=cam, wrap=True, bias=False).double()
    conv_n = ProjectedConv2d(2, 1, 3, padding=1, camera=cam, wrap=False, bias=False).double()
    conv_n.load_state_dict(conv_w.state_dict())
    yw, yn = conv_w(x), conv_n(x)
    # away from the seam and the poles (where taps cross over the pole) both are the same
    assert (yw[..., 3:-3, 3:-3] - yn[..., 3:-3, 3:-3]).abs().max() < 1e-12
    assert (yw[..., 0] - yn[..., 0]).abs().max() > 1e-3  # seam: wrap reads the last column
    # rolling the panorama by one column rolls the wrapped output (no seam anywhere)
    yr = conv_w(torch.roll(x, 5, dims=-1))
    assert (yr - torch.roll(yw, 5, dims=-1)).abs().max() < 1e-12


def test_batch():
    y = _compare(get_camera_class("kannala_brandt").example(), 3, 1, 1, wrap="auto", batch=3)
    assert y.shape == (3, 4, 14, 14)


def test_float32_close_to_reference():
    _compare(Equirectangular(width=48, height=24), 3, 2, 1, wrap="auto", dtype=torch.float32, tol=1e-5)


def test_gradcheck_tiny():
    cam = Equirectangular(width=16, height=8)
    off, mask = compute_sampling(cam, (4, 8), 3, 2, 1, 1)
    pos, m = sample_positions(off, mask, (4, 8), (3, 3), (2, 2), (1, 1), (1, 1))
    x = torch.randn(2, 2, 4, 8, dtype=torch.float64, requires_grad=True)
    w = torch.randn(2, 2, 3, 3, dtype=torch.float64, requires_grad=True)
    b = torch.randn(2, dtype=torch.float64, requires_grad=True)
    f = lambda x, w, b: fixed_offset_conv2d(x, w, b, pos, m, True)   # noqa: E731
    assert torch.autograd.gradcheck(f, (x, w, b))
    assert torch.autograd.gradgradcheck(f, (x, w, b))


def test_random_offsets_equal_deform_conv2d():
    """The op reproduces deform_conv2d's zero padding for arbitrary offsets and a soft mask."""
    torch.manual_seed(3)
    off = 3 * torch.randn(1, 18, 6, 9, dtype=torch.float64)
    mask = torch.rand(1, 9, 6, 9, dtype=torch.float64)
    x = torch.randn(2, 3, 6, 9, dtype=torch.float64, requires_grad=True)
    w = torch.randn(4, 3, 3, 3, dtype=torch.float64, requires_grad=True)
    pos, m = sample_positions(off, mask, (6, 9), (3, 3), (1, 1), (1, 1), (1, 1))
    y = fixed_offset_conv2d(x, w, None, pos, m, False)
    y_ref = deform_conv2d_reference(x, w, None, off, mask, (1, 1), (1, 1), (1, 1))
    g = torch.randn_like(y)
    ga = torch.autograd.grad(y, [x, w], g)
    gb = torch.autograd.grad(y_ref, [x, w], g)
    assert (y - y_ref).abs().max() < TOL
    assert all((a - b).abs().max() < TOL for a, b in zip(ga, gb))


def test_positions_check_shapes():
    cam = Equirectangular(width=16, height=8)
    off, mask = compute_sampling(cam, (4, 8), 3, 1, 1, 1)
    with pytest.raises(ValueError, match="offsets have spatial size"):
        sample_positions(off, mask, (4, 8), (3, 3), (2, 2), (1, 1), (1, 1))
    with pytest.raises(ValueError, match="2\\*kh\\*kw"):
        sample_positions(off, mask, (4, 8), (5, 5), (1, 1), (2, 2), (1, 1))


