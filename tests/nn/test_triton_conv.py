"""ProjectedConv2d's fused CUDA backend (:mod:`omnidl.nn.triton_conv`), its kernels run here by Triton's interpreter:
forward and the three gradients equal to ``deform_conv2d`` with the same offsets (float64 reference; float32 to 1e-5
of the largest value) for example cameras of every kind of plan, strides, dilations, kernels, wraps, a non-binary
mask, memory formats, channel counts across block edges, bias or none, a frozen weight; deterministic; named errors.

Triton picks its interpreter when it is imported (``TRITON_INTERPRET=1``), so the cases run in one child process
(this file as a script) and each test reads its case's result."""
import json
import os
import subprocess
import sys

import pytest
import torch

from omnidl.cameras import Equirectangular, get_camera_class, list_cameras
from omnidl.nn import ProjectedConv2d, triton_conv

pytest.importorskip("triton")

EXAMPLES = {f"{name}-{i}": cam for name in list_cameras() for i, cam in enumerate(get_camera_class(name).examples())}
TOL = 1e-5
# name -> case: camera (example name or "equirect"), image (H, W), channels (C, N), conv kwargs, batch, options
# the kernels see a camera only through its plan: a panorama (wrap), fisheyes and catadioptric cameras with masked
# taps, a non-central one, a pinhole (every camera: tests/nn/test_cuda.py, on a GPU)
CAMERAS = ("equirect-0", "noncentral_pano-0", "fisheye-0", "double_sphere-0", "woodscape-0", "catadioptric-0",
           "scaramuzza-0", "pinhole-0")
CASES = {f"camera {name}": dict(camera=name, hw=(12, 16), ch=(5, 4), conv=dict(kernel_size=3, padding=1), batch=1)
         for name in CAMERAS}
CASES.update({
    "stride 2": dict(hw=(8, 16), ch=(3, 6), conv=dict(kernel_size=3, stride=2, padding=1)),
    "dilation 2": dict(hw=(8, 16), ch=(3, 6), conv=dict(kernel_size=3, padding=2, dilation=2)),
    "kernel 5": dict(hw=(8, 16), ch=(3, 6), conv=dict(kernel_size=5, padding=2)),
    "kernel 1x3": dict(hw=(8, 16), ch=(3, 6), conv=dict(kernel_size=(1, 3), padding=(0, 1))),
    "no wrap": dict(hw=(8, 16), ch=(3, 6), conv=dict(kernel_size=3, padding=1, wrap=False)),
    "no bias": dict(hw=(8, 16), ch=(3, 6), conv=dict(kernel_size=3, padding=1, bias=False)),
    "soft mask": dict(hw=(8, 16), ch=(3, 4), conv=dict(kernel_size=3, padding=1), soft_mask=True),
    "channels-last input": dict(hw=(8, 16), ch=(6, 5), conv=dict(kernel_size=3, padding=1), channels_last=True),
    "channels-last weight": dict(hw=(8, 16), ch=(6, 5), conv=dict(kernel_size=3, padding=1), weight_cl=True),
    "channels across blocks": dict(hw=(8, 16), ch=(40, 70), conv=dict(kernel_size=3, padding=1), batch=1),
    "channels across blocks, channels-last": dict(hw=(8, 16), ch=(40, 70), conv=dict(kernel_size=3, padding=1),
                                                  batch=1, channels_last=True),
    "channel slice of a channels-last map": dict(hw=(8, 16), ch=(5, 4), conv=dict(kernel_size=3, padding=1),
                                                 slice_of=9, channels_last=True),
    "channel slice of an NCHW map": dict(hw=(8, 16), ch=(5, 4), conv=dict(kernel_size=3, padding=1), slice_of=9),
    "one channel": dict(hw=(8, 16), ch=(1, 1), conv=dict(kernel_size=3, padding=1)),
    "batch 3, expanded gradient": dict(hw=(8, 16), ch=(4, 3), conv=dict(kernel_size=3, padding=1), batch=3,
                                       sum_backward=True),
    "frozen weight": dict(hw=(8, 16), ch=(4, 3), conv=dict(kernel_size=3, padding=1), frozen_weight=True),
    "deterministic": dict(hw=(8, 16), ch=(4, 3), conv=dict(kernel_size=3, padding=1), repeat=True),
    "no second derivative": dict(hw=(8, 16), ch=(2, 3), conv=dict(kernel_size=3, padding=1), double_backward=True),
})


def _run_case(case: dict) -> dict:
    """Relative errors of the Triton kernels against deform_conv2d (float64) for one case (in the child)."""
    from omnidl.nn.projected_conv import _geometry
    from omnidl.nn.sampling import deform_conv2d_reference
    torch.manual_seed(0)
    cam = EXAMPLES[case["camera"]] if "camera" in case else Equirectangular(width=case["hw"][1], height=case["hw"][0])
    H, W = case["hw"]
    cam = cam.resized(W, H)
    C, N = case["ch"]
    conv = ProjectedConv2d(C, N, camera=cam, **case["conv"])
    key = conv.geometry_key((H, W))
    off, mask = _geometry(key)
    if case.get("soft_mask"):
        mask = torch.rand(mask.shape, dtype=mask.dtype) * (mask != 0)
    _, in_hw, k, s, p, d, wrap, _, _ = key
    plan = triton_conv.build_plan(off, mask, in_hw, k, s, p, d, wrap=wrap).to(dtype=torch.float32)
    x = torch.randn(case.get("batch", 2), C, H, W)
    weight = conv.weight.detach().clone()
    bias = None if conv.bias is None else conv.bias.detach().clone()
    xt = (x.contiguous(memory_format=torch.channels_last) if case.get("channels_last") else x.clone())
    if case.get("slice_of"):        # the channels [2, 2 + C) of a wider map (as the FFC's split gives them)
        wide = torch.randn(x.shape[0], case["slice_of"], H, W)
        wide = wide.contiguous(memory_format=torch.channels_last) if case.get("channels_last") else wide
        wide[:, 2:2 + C] = x
        xt = wide[:, 2:2 + C]
    xt.requires_grad_(True)
    wt = (weight.contiguous(memory_format=torch.channels_last) if case.get("weight_cl") else weight.clone())
    wt.requires_grad_(not case.get("frozen_weight"))
    bt = None if bias is None else bias.clone().requires_grad_(True)
    y = triton_conv.triton_conv2d(xt, wt, bt, plan)
    x64 = x.double().requires_grad_(True)
    w64 = weight.double().requires_grad_(True)
    b64 = None if bias is None else bias.double().requires_grad_(True)
    ref = deform_conv2d_reference(x64, w64, b64, off, mask, conv.stride, conv._padding_pair(), conv.dilation,
                                  wrap=wrap)
    go = torch.ones_like(y).expand_as(y) if case.get("sum_backward") else torch.randn_like(y)
    if case.get("sum_backward"):
        y.sum().backward()
    else:
        y.backward(go)
    ref.backward(go.double())

    def rel(a, b):
        return float((a.double() - b).abs().max() / b.abs().max().clamp_min(1e-30))
    out = {"y": rel(y.detach(), ref.detach()), "gx": rel(xt.grad, x64.grad),
           "gw": None if wt.grad is None else rel(wt.grad, w64.grad),
           "gb": None if bt is None else rel(bt.grad, b64.grad),
           "y_channels_last": bool(y.is_contiguous(memory_format=torch.channels_last) and not y.is_contiguous()),
           # (a slice is not dense: autograd's layout rule makes its .grad contiguous whatever the backward returns)
           "gx_strides_like_x": xt.grad.stride() == xt.stride() or bool(case.get("slice_of")),
           "shape_ok": tuple(y.shape) == tuple(ref.shape)}
    if case.get("double_backward"):      # the backward is once-differentiable: a second derivative must raise
        g, = torch.autograd.grad(triton_conv.triton_conv2d(xt, wt, bt, plan).square().sum(), xt, create_graph=True)
        try:
            g.sum().backward()
            out["second_derivative_raised"] = False
        except RuntimeError:
            out["second_derivative_raised"] = True
    if case.get("repeat"):
        gx1, gw1 = xt.grad.clone(), wt.grad.clone()
        xt.grad = wt.grad = None
        triton_conv.triton_conv2d(xt, wt, bt, plan).backward(go)
        out["bitwise_repeat"] = bool(torch.equal(gx1, xt.grad) and torch.equal(gw1, wt.grad))
    return out


def _through_the_layer() -> dict:
    """ProjectedConv2d with :func:`triton_conv.applies` saying yes (the dispatch, the plan cache): output and
    gradients against the layer's CPU path (in the child)."""
    from unittest import mock
    torch.manual_seed(1)
    conv = ProjectedConv2d(4, 3, 3, padding=1, camera=Equirectangular(width=16, height=8))
    x = torch.randn(2, 4, 8, 16, requires_grad=True)
    ref = conv(x)
    go = torch.randn_like(ref)
    gx_ref, gw_ref = torch.autograd.grad(ref, (x, conv.weight), go)
    calls = []
    real = triton_conv.triton_conv2d
    with mock.patch.object(triton_conv, "applies", lambda x, w: True), \
            mock.patch.object(triton_conv, "triton_conv2d", lambda *a: calls.append(1) or real(*a)):
        y = conv(x)
    gx, gw = torch.autograd.grad(y, (x, conv.weight), go)

    def rel(a, b):
        return float((a - b).abs().max() / b.abs().max())
    return {"calls": len(calls), "y": rel(y.detach(), ref.detach()), "gx": rel(gx, gx_ref), "gw": rel(gw, gw_ref)}


@pytest.fixture(scope="module")
def interpreted() -> dict:
    env = dict(os.environ, TRITON_INTERPRET="1")
    proc = subprocess.run([sys.executable, __file__], env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(CASES))
def test_interpreted_kernels_equal_deform_conv2d(interpreted, name):
    r = interpreted[name]
    assert "error" not in r, r.get("error")
    assert r["shape_ok"]
    for grad in ("y", "gx", "gw", "gb"):
        assert r[grad] is None or r[grad] <= TOL, (grad, r)
    case = CASES[name]
    assert r["y_channels_last"] == bool(case.get("channels_last"))
    assert r["gx_strides_like_x"]
    assert (r["gw"] is None) == bool(case.get("frozen_weight"))
    assert (r["gb"] is None) == (case["conv"].get("bias") is False)
    if case.get("repeat"):
        assert r["bitwise_repeat"]
    if case.get("double_backward"):
        assert r["second_derivative_raised"]


@pytest.mark.slow
def test_the_self_check_passes_in_the_interpreter(interpreted):
    assert interpreted["self check"] <= 1e-5


@pytest.mark.slow
def test_the_layer_dispatches_to_the_kernels_where_they_apply(interpreted):
    r = interpreted["through the layer"]
    assert r["calls"] == 1
    assert max(r["y"], r["gx"], r["gw"]) <= TOL, r


@pytest.mark.parametrize("outcome, usable", [(1e-7, True), (0.5, False), (RuntimeError("no compiler"), False)])
def test_a_failed_self_check_warns_once_and_turns_the_kernels_off(monkeypatch, outcome, usable):
    def check(device):
        if isinstance(outcome, Exception):
            raise outcome
        return outcome
    monkeypatch.setattr(triton_conv, "_self_check", check)
    monkeypatch.setattr(triton_conv, "_USABLE", {})
    dev = torch.device("meta")
    if usable:
        assert triton_conv.usable(dev)
    else:
        with pytest.warns(RuntimeWarning, match="failed their self-check on meta"):
            assert not triton_conv.usable(dev)
    monkeypatch.setattr(triton_conv, "_self_check", lambda device: pytest.fail("checked twice"))
    assert triton_conv.usable(dev) is usable


def test_it_applies_to_cuda_float32_only(monkeypatch):
    w = torch.randn(4, 3, 3, 3)
    assert not triton_conv.applies(torch.randn(1, 3, 8, 16), w)              # CPU
    monkeypatch.setattr(triton_conv, "ENABLED", False)
    assert not triton_conv.applies(torch.randn(1, 3, 8, 16), w)


def test_cpu_tensors_without_the_interpreter_are_a_named_error():
    if os.environ.get("TRITON_INTERPRET") == "1":
        pytest.skip("the interpreter is on in this process")
    conv = ProjectedConv2d(3, 4, 3, padding=1, camera=Equirectangular(width=16, height=8))
    off, mask = conv.offsets((8, 16))
    plan = triton_conv.build_plan(off, mask, (8, 16), (3, 3), (1, 1), (1, 1), (1, 1), wrap=True).to(dtype=torch.float32)
    with pytest.raises(RuntimeError, match="TRITON_INTERPRET=1"):
        triton_conv.triton_conv2d(torch.randn(1, 3, 8, 16), conv.weight, conv.bias, plan)


def test_bad_operands_are_named_errors():
    conv = ProjectedConv2d(2, 3, 3, padding=1, camera=Equirectangular(width=12, height=6))
    off, mask = conv.offsets((6, 12))
    plan = triton_conv.build_plan(off, mask, (6, 12), (3, 3), (1, 1), (1, 1), (1, 1), wrap=True).to(dtype=torch.float32)
    with pytest.raises(ValueError, match="does not fit the plan"):
        triton_conv.triton_conv2d(torch.randn(1, 2, 6, 10), conv.weight, conv.bias, plan)
    with pytest.raises(ValueError, match="input channels"):
        triton_conv.triton_conv2d(torch.randn(1, 3, 6, 12), conv.weight, conv.bias, plan)
    with pytest.raises(TypeError, match="float32"):
        triton_conv.triton_conv2d(torch.randn(1, 2, 6, 12, dtype=torch.float64), conv.weight.double(), None, plan)


# -- the sm_90 build, without a GPU: Triton compiles for a named target and its bundled ptxas reports registers --
_PTRS = {"fwd": dict(x="*fp32", w="*fp32", bias="*fp32", idx="*i32", wt="*fp32", y="*fp32"),
         "gcols": dict(gy="*fp32", w="*fp32", out="*fp32"),
         "sell": dict(g="*fp32", rows="*i32", vals="*fp32", tile_start="*i32", tile_len="*i32", gx="*fp32"),
         "wgrad": dict(x="*fp32", idx="*i32", wt="*fp32", gy="*fp32", part="*fp32")}
# integer arguments equal to 1 at a launch (Triton specialises them), per memory format of the input / gradient
_UNIT = {("fwd", True): ("sxc", "syn"), ("fwd", False): ("sxp", "syp"), ("gcols", True): ("sgn",),
         ("gcols", False): ("sgp",), ("sell", True): ("sgxc",), ("sell", False): ("sgxq",),
         ("wgrad", True): ("sxc", "sgn"), ("wgrad", False): ("sxp", "sgp")}


def sm90_build(kernel: str, channels_last: bool, cfg: dict, prec: str = "tf32", **constexprs) -> dict:
    """Compile ``kernel`` with the block sizes ``cfg`` and products in ``prec`` for sm_90 as a launch at channel counts
    divisible by 16 would (pointers and sizes 16-divisible, unit strides specialised): registers, spilled bytes,
    shared memory."""
    import re
    import tempfile
    from pathlib import Path

    import triton
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    from omnidl.nn import triton_kernels
    fn = getattr(triton_kernels, kernel)
    options = {k: cfg[k] for k in ("num_warps", "num_stages") if k in cfg}
    consts = {k: v for k, v in cfg.items() if k not in options}
    consts.update(constexprs)
    consts.update({name: 1 for name in _UNIT[(kernel, channels_last)]})
    if kernel in ("fwd", "wgrad"):
        consts["CL"] = channels_last
    if kernel != "sell":
        consts["PREC"] = prec
    if kernel == "sell":
        consts["BLOCK_Q"] = triton_conv.TILE_Q
    names = fn.arg_names
    signature = {n: _PTRS[kernel].get(n, "constexpr" if n in consts else "i32") for n in names}
    attrs = {(i,): [["tt.divisibility", 16]] for i, n in enumerate(names) if signature[n] != "constexpr"
             and n not in ("K", "CB", "tile_start", "tile_len")}
    compiled = triton.compile(ASTSource(fn=fn, signature=signature, constexprs=consts, attrs=attrs),
                              target=GPUTarget("cuda", 90, 32), options=options)
    ptxas = Path(triton.__file__).parent / "backends" / "nvidia" / "bin" / "ptxas"
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "k.ptx"
        src.write_text(compiled.asm["ptx"])
        out = subprocess.run([str(ptxas), "-v", "--gpu-name=sm_90a", str(src), "-o", str(Path(tmp) / "k.cubin")],
                             capture_output=True, text=True, check=True).stderr
    return {"registers": int(re.search(r"Used (\d+) registers", out).group(1)),
            "spilled": int(re.search(r"(\d+) bytes spill stores", out).group(1)), "shared": compiled.metadata.shared}


@pytest.mark.parametrize("channels_last", [False, True])
@pytest.mark.parametrize("kernel", ["fwd", "gcols", "sell", "wgrad"])
@pytest.mark.parametrize("C, N, hw", [(64, 64, (128, 256)), (256, 256, (64, 128))])
def test_default_blocks_build_for_sm90_without_register_spills(kernel, channels_last, C, N, hw):
    """The block sizes :func:`triton_conv._config` picks for the benchmark's two layers compile for an H100/H200
    (sm_90) with no register spills, within the 228 KB of shared memory, in no more than 255 registers."""
    pytest.importorskip("triton.backends.nvidia")
    x = torch.empty(1, C, *hw, device="meta")
    cfg = triton_conv._config(kernel, x, 1, hw[0] * hw[1], C, N, 9)
    try:
        r = sm90_build(kernel, channels_last, cfg, **({"HAS_BIAS": True} if kernel in ("fwd", "wgrad") else {}))
    except FileNotFoundError as e:
        pytest.skip(f"Triton's ptxas is missing: {e}")
    assert r["spilled"] == 0, r
    assert r["shared"] <= 228 * 1024, r


@pytest.mark.parametrize("kernel", ["fwd", "gcols", "wgrad"])
def test_float32_products_build_for_sm90(kernel):
    """With TF32 off (``torch.backends.cudnn.allow_tf32 = False``, and the self-check) the products are exact float32
    ``tl.dot``: they compile for sm_90 too (a few spilled bytes are allowed: this is the slow, exact mode)."""
    pytest.importorskip("triton.backends.nvidia")
    x = torch.empty(1, 64, 8, 16, device="meta")
    for channels_last in (False, True):
        cfg = triton_conv._config(kernel, x, 1, 128, 64, 64, 9)
        try:
            r = sm90_build(kernel, channels_last, cfg, "ieee", **({"HAS_BIAS": True} if kernel != "gcols" else {}))
        except FileNotFoundError as e:
            pytest.skip(f"Triton's ptxas is missing: {e}")
        assert r["shared"] <= 228 * 1024, r


if __name__ == "__main__":          # the child process of ``interpreted``: TRITON_INTERPRET=1 set by the parent
    results = {}
    for name, case in CASES.items():
        try:
            results[name] = _run_case(case)
        except Exception as e:  # noqa: BLE001 -- reported per case by the tests
            results[name] = {"error": f"{type(e).__name__}: {e}"}
    results["self check"] = triton_conv._self_check(torch.device("cpu"))
    results["through the layer"] = _through_the_layer()
    print(json.dumps(results))
