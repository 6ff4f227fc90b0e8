import pytest
import torch

from omnidl.models import create_model
from omnidl.nn import ProjectedConv2d


@pytest.mark.parametrize("conv", ["standard", "projected"])
def test_output_shapes_and_names(conv):
    torch.manual_seed(0)
    m = create_model("holinet", backbone="resnet18", width=0.125, conv=conv).eval()
    with torch.no_grad():
        out = m(torch.rand(1, 3, 32, 64))
    assert out["horizon"].shape == (1, 1, 16, 32) and out["vp"].shape == (1, 1, 16, 32)
    assert out["aux_16"].shape == (1, 2, 2, 4) and out["aux_8"].shape == (1, 2, 4, 8)
    assert out["aux_4"].shape == (1, 2, 8, 16)
    assert all(torch.isfinite(v).all() for v in out.values())
    n_proj = sum(isinstance(x, ProjectedConv2d) and x.camera is not None for x in m.modules())
    big = [x for x in m.modules() if isinstance(x, torch.nn.Conv2d) and max(x.kernel_size) > 1]
    assert n_proj == (len(big) if conv == "projected" else 0)


def test_bad_inputs_and_options():
    m = create_model("holinet", backbone="resnet18", width=0.125, conv="standard")
    with pytest.raises(ValueError, match="multiples of 32"):
        m(torch.rand(1, 3, 40, 80))
    with pytest.raises(ValueError, match="conv"):
        create_model("holinet", conv="deform")


@pytest.mark.parametrize("conv", ["standard", "projected"])
def test_channels_last_matches_contiguous(conv):
    """The channels-last fast path (default) gives the contiguous path's outputs and gradients."""
    torch.manual_seed(0)
    fast = create_model("holinet", backbone="resnet18", width=0.125, conv=conv).eval()
    slow = create_model("holinet", backbone="resnet18", width=0.125, conv=conv, channels_last=False).eval()
    slow.load_state_dict(fast.state_dict())
    x = torch.rand(1, 3, 32, 64)
    xf, xs = x.clone().requires_grad_(True), x.clone().requires_grad_(True)
    of, os_ = fast(xf), slow(xs)
    for k in of:
        assert of[k].is_contiguous()
        torch.testing.assert_close(of[k], os_[k], rtol=1e-5, atol=1e-5)
    sum(v.sum() for v in of.values()).backward()
    sum(v.sum() for v in os_.values()).backward()
    torch.testing.assert_close(xf.grad, xs.grad, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("channels_last", [True, False])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fused_decoder_wrap_matches_the_modules(channels_last, dtype):
    """conv='standard': the concatenation + longitude wrap written into one buffer (fuse_wrap, default) gives
    the modules' own torch.cat + F.pad outputs and gradients (the same values, copied once): 1e-5 relative
    in float32 (backward rounding), 1e-12 in float64."""
    torch.manual_seed(0)
    m = create_model("holinet", backbone="resnet18", width=0.125, conv="standard", channels_last=channels_last)
    m = m.to(dtype)
    assert m.fuse_wrap
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    x = torch.rand(2, 3, 32, 64, dtype=dtype)
    outs, grads = [], []
    for fuse in (True, False):
        m.fuse_wrap = fuse
        xi = x.clone().requires_grad_(True)
        o = m(xi)
        sum((v * torch.linspace(0, 1, v.numel(), dtype=dtype).view_as(v)).sum() for v in o.values()).backward()
        outs.append(o)
        grads.append(xi.grad)
    for k in outs[0]:
        torch.testing.assert_close(outs[0][k], outs[1][k], rtol=0, atol=tol)
    scale = grads[1].abs().max()
    torch.testing.assert_close(grads[0] / scale, grads[1] / scale, rtol=0, atol=tol)
