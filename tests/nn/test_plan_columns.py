"""Weight-heavy projected convolutions in training (gathered columns + the unfolded product) equal deform_conv2d
and the fused kernel at float32 rounding, for both weight layouts, both input layouts and several threads; their
weight gradient comes back in the weight's own layout; the rule sends only weight-heavy training to them."""
from __future__ import annotations

import pytest
import torch

from omnidl.cameras import Equirectangular, get_camera_class
from omnidl.nn import ProjectedConv2d, native, plan_columns
from omnidl.nn.fused import _FusedConv
from omnidl.nn.projected_conv import get_plan

from .conftest import close_to_scale

pytestmark = pytest.mark.skipif(native.library() is None, reason="the native kernel cannot be built here: "
                                f"{native.status()['reason']}")


def _run(m: ProjectedConv2d, x: torch.Tensor):
    """Output and the gradients of input, weight and bias for a fixed output gradient; the graph's node names."""
    xi = x.detach().clone().requires_grad_(True)
    y = m(xi)
    nodes, seen, todo = set(), set(), [y.grad_fn]
    while todo:
        f = todo.pop()
        if f is not None and id(f) not in seen:
            seen.add(id(f))
            nodes.add(type(f).__name__)
            todo.extend(n for n, _ in f.next_functions)
    g = torch.linspace(-1, 1, y.numel()).view_as(y)
    m.zero_grad(set_to_none=True)
    y.backward(g)
    return (y.detach(), xi.grad, m.weight.grad, m.bias.grad), nodes


# (camera, input H x W, C, Cout, kernel, stride, dilation, batch): Cout >= RATIO * B * Ho * Wo in every row;
# channel counts off the 16-float vector steps
CASES = [("equirect", (4, 8), 20, 64, 3, 1, 1, 1),
         ("equirect", (4, 8), 16, 136, 3, 1, 1, 2),
         ("equirect", (6, 12), 5, 40, 5, 2, 1, 1),
         ("equirect", (4, 8), 33, 70, 3, 1, 2, 1),
         ("kannala_brandt", (5, 5), 7, 52, 3, 1, 1, 1)]


def _case_id(c) -> str:
    return f"{c[0]}-{c[1][0]}x{c[1][1]}-{c[2]}to{c[3]}-k{c[4]}s{c[5]}d{c[6]}-B{c[7]}"


@pytest.mark.parametrize("case", CASES, ids=_case_id)
@pytest.mark.parametrize("weight_cl", [False, True], ids=["weight-nchw", "weight-cl"])
@pytest.mark.parametrize("input_cl", [False, True], ids=["input-nchw", "input-cl"])
def test_columns_equal_deform_conv2d_and_the_fused_kernel(case, weight_cl, input_cl, monkeypatch):
    name, (H, W), C, Cout, k, s, d, B = case
    torch.manual_seed(Cout + k)
    cam = Equirectangular(width=2 * W, height=2 * H) if name == "equirect" else get_camera_class(name).example()
    pad = d * (k // 2)
    m = ProjectedConv2d(C, Cout, k, stride=s, padding=pad, dilation=d, camera=cam)
    ref = ProjectedConv2d(C, Cout, k, stride=s, padding=pad, dilation=d, camera=cam, backend="torchvision")
    ref.load_state_dict(m.state_dict())
    if weight_cl:
        m = m.to(memory_format=torch.channels_last)
    x = torch.randn(B, C, H, W)
    if input_cl:
        x = x.contiguous(memory_format=torch.channels_last)
    plan = get_plan(m.geometry_key((H, W)), torch.device("cpu"), torch.float32)
    assert plan_columns.pays(x, m.weight, plan)
    cols, nodes = _run(m, x)
    assert "_ColumnsBackward" in nodes and not any(n.startswith(_FusedConv.__name__) for n in nodes)
    monkeypatch.setattr(plan_columns, "ENABLED", False)
    fused, nodes = _run(m, x)
    assert any(n.startswith(_FusedConv.__name__) for n in nodes)
    want, _ = _run(ref, x)
    for label, a, b, c in zip(("output", "input grad", "weight grad", "bias grad"), cols, fused, want):
        close_to_scale(a, c, label + " vs deform_conv2d")
        close_to_scale(a, b, label + " vs fused")
    assert cols[0].is_contiguous(memory_format=torch.channels_last) == input_cl
    assert cols[1].stride() == x.stride()
    assert cols[2].stride() == m.weight.stride() == fused[2].stride()  # the weight's own layout, on both paths


def test_several_threads_equal_one():
    """The gather splits positions, the scatter channels (73: a partial last vector step in one thread's share)."""
    torch.manual_seed(0)
    m = ProjectedConv2d(73, 96, 3, padding=1, camera=Equirectangular(width=16, height=8))
    x = torch.randn(1, 73, 4, 8)
    threads = torch.get_num_threads()
    runs = []
    try:
        for n in (1, 2, 3):
            torch.set_num_threads(n)
            runs.append(_run(m, x))
    finally:
        torch.set_num_threads(threads)
    for (outs, nodes) in runs:
        assert "_ColumnsBackward" in nodes
        for label, a, b in zip(("output", "input grad", "weight grad", "bias grad"), outs, runs[0][0]):
            close_to_scale(a, b, label)


@pytest.mark.parametrize("what,expected", [
    ("weight-heavy training", True),
    ("inference (no_grad)", False),
    ("frozen weight", False),
    ("below the ratio", False),
    ("disabled", False),
])
def test_the_rule(what, expected, monkeypatch):
    cam = Equirectangular(width=16, height=8)
    cout = 64 if what != "below the ratio" else 63                        # 4x8 map: 2 * 32 = 64
    m = ProjectedConv2d(8, cout, 3, padding=1, camera=cam)
    plan = get_plan(m.geometry_key((4, 8)), torch.device("cpu"), torch.float32)
    x = torch.randn(1, 8, 4, 8)
    if what == "frozen weight":
        m.weight.requires_grad_(False)
    if what == "disabled":
        monkeypatch.setattr(plan_columns, "ENABLED", False)
    with torch.set_grad_enabled(what != "inference (no_grad)"):
        assert plan_columns.pays(x, m.weight, plan) is expected
        y = m(x.requires_grad_(what == "frozen weight"))
    on_columns = y.grad_fn is not None and type(y.grad_fn).__name__ != _FusedConv.__name__ + "Backward"
    if y.grad_fn is not None:
        assert on_columns is expected


@pytest.mark.parametrize("build,kernel", [("avx2_build", "avx2"), ("generic_x86_build", "blas")])
def test_the_other_builds(build, kernel, request):
    """The AVX2 build's and the plain x86-64 build's gather and scatter (scalar loops; the latter's products are
    PyTorch's) give the same results."""
    request.getfixturevalue(build)
    assert native.status()["kernel"] == kernel
    torch.manual_seed(4)
    cam = Equirectangular(width=16, height=8)
    m = ProjectedConv2d(21, 80, 3, padding=1, camera=cam).to(memory_format=torch.channels_last)
    ref = ProjectedConv2d(21, 80, 3, padding=1, camera=cam, backend="torchvision")
    ref.load_state_dict(m.state_dict())
    x = torch.randn(1, 21, 4, 8)
    got, nodes = _run(m, x)
    want, _ = _run(ref, x)
    assert "_ColumnsBackward" in nodes
    for label, a, b in zip(("output", "input grad", "weight grad", "bias grad"), got, want):
        close_to_scale(a, b, label)


def test_an_input_without_gradient(monkeypatch):
    """A first layer (the input needs no gradient): the columns path gives the weight's and bias's gradients and
    never scatters."""
    torch.manual_seed(2)
    m = ProjectedConv2d(6, 64, 3, padding=1, camera=Equirectangular(width=16, height=8))
    x = torch.randn(1, 6, 4, 8)
    y = m(x)
    assert type(y.grad_fn).__name__ != _FusedConv.__name__ + "Backward"
    g = torch.randn_like(y)
    got = torch.autograd.grad(y, [m.weight, m.bias], g)
    monkeypatch.setattr(plan_columns, "ENABLED", False)
    want = torch.autograd.grad(m(x), [m.weight, m.bias], g)
    for label, a, b in zip(("weight grad", "bias grad"), got, want):
        close_to_scale(a, b, label)
