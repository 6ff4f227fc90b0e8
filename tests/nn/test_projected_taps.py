"""Few-output-channel ProjectedConv2d without a graph: the product onto the taps and the sampled sum
(``omnidl.nn.projected_taps``) against the layer's other paths (1e-5 float32, 1e-12 float64), its NaN policy, its
rule's verdicts and its cached indexes."""
from __future__ import annotations

import pytest
import torch

from omnidl.cameras import Equirectangular, get_camera_class
from omnidl.nn import ProjectedConv2d
from omnidl.nn import projected_taps
from omnidl.nn.projected_conv import get_plan

TOL = {torch.float32: 1e-5, torch.float64: 1e-12}


def _camera(name: str):
    return Equirectangular(width=48, height=24) if name == "equirect" else get_camera_class(name).example()


def _pair(layer: ProjectedConv2d, x: torch.Tensor, monkeypatch) -> tuple[torch.Tensor, torch.Tensor]:
    """The layer's output with the taps path and without it (the native kernel or the column path)."""
    with torch.no_grad():
        got = layer(x)
        monkeypatch.setattr(projected_taps, "ENABLED", False)
        expect = layer(x)
        monkeypatch.setattr(projected_taps, "ENABLED", True)
    return got, expect


@pytest.mark.parametrize("camera", ["equirect", "kannala_brandt"])
@pytest.mark.parametrize("k,s,cout", [(3, 1, 2), (3, 2, 1), (5, 1, 1)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("channels_last", [False, True])
def test_equals_the_other_paths(camera, k, s, cout, dtype, channels_last, monkeypatch):
    torch.manual_seed(0)
    cam = _camera(camera)
    C = 2 * cout * k * k
    layer = ProjectedConv2d(C, cout, k, stride=s, padding=k // 2, camera=cam).to(dtype)
    x = torch.randn(2, C, cam.height // 2, cam.width // 2, dtype=dtype)
    if channels_last:
        x = x.contiguous(memory_format=torch.channels_last)
    got, expect = _pair(layer, x, monkeypatch)
    torch.testing.assert_close(got, expect, rtol=0, atol=TOL[dtype] * max(1.0, float(expect.abs().max())))
    assert got.is_contiguous(memory_format=torch.channels_last if channels_last else torch.contiguous_format)


def test_without_bias(monkeypatch):
    layer = ProjectedConv2d(36, 2, 3, padding=1, bias=False, camera=Equirectangular(width=32, height=16))
    got, expect = _pair(layer, torch.randn(1, 36, 16, 32), monkeypatch)
    torch.testing.assert_close(got, expect, rtol=0, atol=1e-5)


def test_a_nan_pixel_reaches_only_the_outputs_that_sample_it(monkeypatch):
    layer = ProjectedConv2d(36, 2, 3, padding=1, camera=Equirectangular(width=32, height=16))
    x = torch.randn(1, 36, 16, 32)
    x[0, :, 8, 5] = float("nan")
    got, expect = _pair(layer, x, monkeypatch)
    assert torch.equal(torch.isnan(got), torch.isnan(expect))
    assert 0 < int(torch.isnan(got[0, 0]).sum()) < 64  # the neighbourhood, not the map (512 outputs)


def _verdict(cout=2, C=64, k=3, dtype=torch.float32, grad=False, device="cpu"):
    layer = ProjectedConv2d(C, cout, k, padding=k // 2, camera=Equirectangular(width=32, height=16)).to(dtype)
    x = torch.zeros(1, C, 16, 32, dtype=dtype, requires_grad=grad)
    plan = get_plan(layer.geometry_key((16, 32)), torch.device(device), dtype)
    if grad:  # a training call: the input and the parameters require grad
        return projected_taps.pays(x, layer.weight, layer.bias, plan)
    with torch.no_grad():
        return projected_taps.pays(x, layer.weight, layer.bias, plan)


@pytest.mark.parametrize("kwargs, verdict", [
    (dict(), True),                                   # 2 * 2 * 9 = 36 <= 64
    (dict(cout=4), False),                            # 72 > 64: the native kernel
    (dict(cout=1, C=18), True),                       # at the bound
    (dict(cout=1, C=17), False),
    (dict(cout=1, k=5, C=50), True),
    (dict(dtype=torch.float64), True),
    (dict(dtype=torch.float16), False),
    (dict(grad=True), False),                         # a graph: embedding_bag's backward is slower
])
def test_rule(kwargs, verdict):
    assert _verdict(**kwargs) is verdict


def test_rule_switch_and_no_grad_mode(monkeypatch):
    with torch.no_grad():
        assert _verdict(grad=True)                    # no graph is built under no_grad
    layer = ProjectedConv2d(36, 2, 3, padding=1, camera=Equirectangular(width=32, height=16)).requires_grad_(False)
    plan = get_plan(layer.geometry_key((16, 32)), torch.device("cpu"), torch.float32)
    assert projected_taps.pays(torch.zeros(1, 36, 16, 32), layer.weight, layer.bias, plan)  # frozen: no graph
    monkeypatch.setattr(projected_taps, "ENABLED", False)
    assert not _verdict()


def test_the_sum_indexes_are_kept_on_the_plan():
    layer = ProjectedConv2d(36, 2, 3, padding=1, camera=Equirectangular(width=32, height=16))
    plan = get_plan(layer.geometry_key((16, 32)), torch.device("cpu"), torch.float32)
    with torch.no_grad():
        layer(torch.randn(1, 36, 16, 32))
        kept = plan.derived["taps"]
        layer(torch.randn(1, 36, 16, 32))
    assert plan.derived["taps"] is kept
    zero_row = 16 * 32 * 9
    assert torch.equal(kept.idx == zero_row, plan.weight == 0)
