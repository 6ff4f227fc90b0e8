"""The taps of the fused CUDA kernels (:mod:`omnidl.nn.triton_plan`): the tap-major plan holds the CPU plan's corners;
its sliced ELL transpose holds every live corner once, at its input pixel, in the plan's order."""
import torch

from omnidl.cameras import Equirectangular
from omnidl.nn import ProjectedConv2d, triton_plan
from omnidl.nn.sampling import build_plan


def _plan(hw=(20, 40)):
    conv = ProjectedConv2d(2, 3, 3, padding=1, camera=Equirectangular(width=hw[1], height=hw[0]))
    off, mask = conv.offsets(hw)
    args = (off, mask, hw, (3, 3), (1, 1), (1, 1), (1, 1))
    return triton_plan.build_plan(*args, wrap=True), build_plan(*args, wrap=True)


def test_the_plan_is_the_cpu_plan_tap_major():
    plan, cpu = _plan()
    K, _, P = plan.idx.shape
    assert plan.idx.dtype == torch.int32 and plan.idx.is_contiguous() and plan.wt.is_contiguous()
    torch.testing.assert_close(plan.idx.permute(2, 0, 1).reshape(P * K, 4), cpu.idx.to(torch.int32), rtol=0, atol=0)
    torch.testing.assert_close(plan.wt.permute(2, 0, 1).reshape(P * K, 4), cpu.weight, rtol=0, atol=0)


def test_transposed_plan_lists_every_live_corner_once():
    """The sliced ELL transpose holds each non-zero corner weight of the plan exactly once, at its input pixel."""
    plan, _ = _plan()
    start, length, rows, vals = plan.transpose()
    K, _, P = plan.idx.shape
    dense = torch.zeros(20 * 40, P * K, dtype=torch.float64)
    for t in range(start.numel()):
        for e in range(int(length[t])):
            sl = slice(int(start[t]) + e * triton_plan.TILE_Q, int(start[t]) + (e + 1) * triton_plan.TILE_Q)
            q = t * triton_plan.TILE_Q + torch.arange(triton_plan.TILE_Q)
            keep = q < 20 * 40
            dense.index_put_((q[keep], rows[sl].long()[keep]), vals[sl][keep], accumulate=True)
    expect = torch.zeros_like(dense)
    r = torch.arange(P * K).view(P, K, 1).expand(P, K, 4).permute(1, 2, 0)
    expect.index_put_((plan.idx.long().reshape(-1), r.reshape(-1)), plan.wt.reshape(-1), accumulate=True)
    torch.testing.assert_close(dense, expect, rtol=0, atol=0)


def test_the_transpose_is_built_once_and_kept():
    plan, _ = _plan((8, 16))
    assert plan.transpose() is plan.transpose()
    assert plan.nbytes() > plan.idx.numel() * 8
