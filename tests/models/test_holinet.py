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
    with pytest.raises(ValueError, match="not divisible by the network stride 32"):
        m(torch.rand(1, 3, 40, 80))
    with pytest.raises(ValueError, match="conv"):
        create_model("holinet", conv="deform")


@pytest.mark.parametrize("conv", ["standard", "projected"])
def test_channels_last_matches_contiguous(conv):
    """channels_last=True gives the contiguous model's outputs and gradients."""
    torch.manual_seed(0)
    fast = create_model("holinet", backbone="resnet18", width=0.125, conv=conv, channels_last=True).eval()
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
