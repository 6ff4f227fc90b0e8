"""The tiled oneDNN path (CPU float32) equals the column GEMM path and deform_conv2d at float32 rounding.

The layer takes the tiled path where the native fused kernel is off or cannot be built; these tests turn the
fused path off (``fused.ENABLED``) so that the layer runs the tiled one."""
from __future__ import annotations

import pytest
import torch

from omnidl.cameras import Equirectangular, get_camera_class
from omnidl.nn import ProjectedConv2d, build_plan, deform_conv2d_reference, fixed_offset_conv2d
from omnidl.nn.projected_conv import get_plan
from omnidl.nn.sampling import _FixedOffsetConv
from omnidl.nn import fused as fused_module
from omnidl.nn import tiled as tiled_module
from omnidl.nn.tiled import _TiledConv, tile_rows, tiled_conv2d, tiled_plan, tiled_supported

TOL = 1e-5


@pytest.fixture(autouse=True)
def _no_fused_path(monkeypatch):
    monkeypatch.setattr(fused_module, "ENABLED", False)


def _close(a: torch.Tensor, b: torch.Tensor, name: str) -> None:
    assert a.shape == b.shape, name
    assert (a - b).abs().max() <= TOL * max(1.0, float(b.detach().abs().max())), name


def _camera(name: str):
    return Equirectangular(width=48, height=24) if name == "equirect" else get_camera_class(name).example()


@pytest.mark.parametrize("camera", ["equirect", "kannala_brandt", "scaramuzza"])
@pytest.mark.parametrize("k,s,d", [(3, 1, 1), (3, 2, 1), (5, 1, 2), (7, 2, 1), (2, 1, 1)])
@pytest.mark.parametrize("channels_last", [False, True])
@pytest.mark.parametrize("backward", ["tiles", "columns"])
def test_tiled_equals_columns_and_deform_conv2d(camera, k, s, d, channels_last, backward, monkeypatch):
    monkeypatch.setattr(tiled_module, "BACKWARD", backward)
    torch.manual_seed(k * 10 + s + d)
    cam = _camera(camera)
    H, W = (12, 24) if cam.width >= 2 * cam.height else (14, 14)
    pad = d * (k // 2)
    tiled = ProjectedConv2d(3, 5, k, stride=s, padding=pad, dilation=d, camera=cam, backend="fast")
    cols = ProjectedConv2d(3, 5, k, stride=s, padding=pad, dilation=d, camera=cam, backend="fast",
                           chunk_positions=7)  # an explicit chunk length keeps the column GEMM path
    ref = ProjectedConv2d(3, 5, k, stride=s, padding=pad, dilation=d, camera=cam, backend="torchvision")
    cols.load_state_dict(tiled.state_dict())
    ref.load_state_dict(tiled.state_dict())
    x = torch.randn(2, 3, H, W)
    if channels_last:
        x = x.contiguous(memory_format=torch.channels_last)
    outs = []
    for m in (tiled, cols, ref):
        xi = x.clone().requires_grad_(True)
        y = m(xi)
        g = torch.linspace(-1, 1, y.numel()).view_as(y)
        outs.append((y, *torch.autograd.grad(y, [xi, m.weight, m.bias], g)))
    for name, a, b, c in zip(("output", "input grad", "weight grad", "bias grad"), *outs):
        _close(a, b, name + " vs columns")
        _close(a, c, name + " vs deform_conv2d")
    # same memory format as the column path: channels-last in, channels-last out
    assert outs[0][0].is_contiguous(memory_format=torch.channels_last) == channels_last
    assert outs[0][1].stride() == outs[1][1].stride()


@pytest.mark.parametrize("rows", [1, 2, 5, 100])
def test_any_tile_height_gives_the_same_result(rows):
    """Tiles of 1 row, of rows that do not divide the height (last tile shorter) and of the whole image."""
    torch.manual_seed(rows)
    cam = Equirectangular(width=48, height=24)
    m = ProjectedConv2d(4, 6, 3, padding=1, camera=cam)
    plan = get_plan(m.geometry_key((12, 24)), torch.device("cpu"), torch.float32)
    x = torch.randn(3, 4, 12, 24)
    y = tiled_conv2d(x, m.weight, m.bias, plan, rows=rows)
    y_cols = fixed_offset_conv2d(x, m.weight, m.bias, plan)
    _close(y, y_cols, f"rows={rows}")


def test_tiled_plan_is_a_reordering_cached_on_the_plan():
    cam = Equirectangular(width=32, height=16)
    off, mask = ProjectedConv2d(2, 2, 3, padding=1, camera=cam).offsets((8, 16))
    plan = build_plan(off, mask, (8, 16), (3, 3), (1, 1), (1, 1), (1, 1), wrap=True)
    tp = tiled_plan(plan)
    assert tiled_plan(plan) is tp
    # row (oy, i, ox, j) of the tiled plan is row (oy, ox, i, j) of the plan
    a = plan.idx.view(8, 16, 3, 3, 4)
    b = tp.idx.view(8, 3, 16, 3, 4)
    assert torch.equal(a[5, 7, 2, 1], b[5, 2, 7, 1])
    assert sorted(plan.idx.flatten().tolist()) == sorted(tp.idx.flatten().tolist())
    assert plan.nbytes() >= 2 * (plan.idx.numel() * 4 + plan.weight.numel() * 8)


def test_tile_rows_targets_a_few_megabytes_and_stays_in_range():
    cam = Equirectangular(width=512, height=256)
    m = ProjectedConv2d(64, 64, 3, padding=1, camera=cam)
    plan = get_plan(m.geometry_key((128, 256)), torch.device("cpu"), torch.float32)
    assert 1 <= tile_rows(plan, 64, 4) <= 128
    assert tile_rows(plan, 100_000, 4) == 1
    assert tile_rows(plan, 1, 4) == 128
    # a wide layer's weight (re-laid out by oneDNN on every call) is amortised over taller tiles
    assert tile_rows(plan, 256, 4, weight_numel=256 * 256 * 9) > tile_rows(plan, 256, 4)


def test_layer_dispatch():
    """Without the fused path, CPU float32 without chunk_positions runs the tiled path; float64 and explicit
    chunks the column path."""
    x32 = torch.randn(1, 2, 4, 8)
    w32 = torch.randn(3, 2, 3, 3)
    assert tiled_supported(x32, w32)
    assert not tiled_supported(x32.double(), w32.double())
    cam = Equirectangular(width=16, height=8)
    seen = []
    for dtype, chunk in ((torch.float32, None), (torch.float32, 5), (torch.float64, None)):
        m = ProjectedConv2d(2, 3, 3, padding=1, camera=cam, chunk_positions=chunk).to(dtype)
        y = m(torch.randn(1, 2, 4, 8, dtype=dtype, requires_grad=True))
        seen.append(type(y.grad_fn).__name__)
    assert seen[0].startswith(_TiledConv.__name__)
    assert seen[1].startswith(_FixedOffsetConv.__name__) and seen[2].startswith(_FixedOffsetConv.__name__)


@pytest.mark.parametrize("backward", ["tiles", "columns"])
def test_tiled_path_in_float64_equals_deform_conv2d(backward, monkeypatch):
    """The tile layout is dtype-agnostic: run in float64 (slow non-oneDNN kernels) the tiled forward and both
    backward modes equal deform_conv2d at 1e-12, batch 2, tiles of 3 rows (the last one shorter)."""
    monkeypatch.setattr(tiled_module, "BACKWARD", backward)
    cam = Equirectangular(width=32, height=16)
    m = ProjectedConv2d(3, 4, 3, padding=1, camera=cam).double()
    off, mask = m.offsets((8, 16))
    plan = build_plan(off, mask, (8, 16), (3, 3), (1, 1), (1, 1), (1, 1), wrap=True)
    x = torch.randn(2, 3, 8, 16, dtype=torch.float64, requires_grad=True)
    y = _TiledConv.apply(x, m.weight, m.bias, plan, 3)
    y_ref = deform_conv2d_reference(x, m.weight, m.bias, off, mask, (1, 1), (1, 1), (1, 1), wrap=True)
    assert (y - y_ref).abs().max() < 1e-12
    g = torch.randn_like(y)
    for a, b in zip(torch.autograd.grad(y, [x, m.weight, m.bias], g),
                    torch.autograd.grad(y_ref, [x, m.weight, m.bias], g)):
        assert (a - b).abs().max() < 1e-12


def test_worker_pool_split_equals_one_worker():
    """Tiles split among 2 workers (private gradient accumulators, summed) equal one worker's result."""
    torch.manual_seed(5)
    cam = Equirectangular(width=48, height=24)
    m = ProjectedConv2d(4, 6, 3, padding=1, camera=cam)
    plan = get_plan(m.geometry_key((12, 24)), torch.device("cpu"), torch.float32)
    x = torch.randn(2, 4, 12, 24)
    g = torch.randn(2, 6, 12, 24)
    runs = []
    threads = torch.get_num_threads()
    try:
        for n in (1, 2):
            torch.set_num_threads(n)
            xi = x.clone().requires_grad_(True)
            y = tiled_conv2d(xi, m.weight, m.bias, plan, rows=2)
            runs.append((y, *torch.autograd.grad(y, [xi, m.weight], g)))
    finally:
        torch.set_num_threads(threads)
    for a, b, name in zip(*runs, ("output", "input grad", "weight grad")):
        _close(a, b, name)
