"""The CPU kernel of ``omnidl::fixed_offset_conv2d``: the native C kernel (``csrc/fixed_offset_conv.c``) for
float32, the PyTorch implementation for other dtypes and where the C kernel cannot be built."""
from __future__ import annotations

import ctypes
from pathlib import Path

import torch
from torch import Tensor

from . import _native
from ._fixed_offset_torch import check_arguments, memory_format, torch_backward, torch_forward

LIBRARY = "fixed_offset_conv"
_SIGNATURES = {
    "omnidl_foc_forward": (_native.INT, [_native.POINTER, _native.INT64, _native.INT, _native.INT, _native.INT,
                                         _native.POINTER, _native.POINTER, _native.INT, _native.INT, _native.INT64,
                                         _native.INT, _native.POINTER, _native.INT, _native.POINTER, _native.POINTER,
                                         _native.INT, _native.INT64, _native.INT]),
    "omnidl_foc_backward": (_native.INT, [_native.POINTER, _native.INT64, _native.INT, _native.INT, _native.INT,
                                          _native.POINTER, _native.POINTER, _native.INT, _native.INT, _native.INT64,
                                          _native.INT, _native.POINTER, _native.INT, _native.POINTER, _native.POINTER,
                                          _native.POINTER, _native.INT, _native.INT64, _native.INT]),
    "omnidl_foc_kernel": (_native.INT, []),
    "omnidl_foc_openmp": (_native.INT, []),
}
#: what ``omnidl_foc_kernel()`` returns, by name
KERNELS = ("blas", "avx2", "avx512")


def native_library() -> ctypes.CDLL | None:
    """The CPU kernel's library (built on first use), or ``None`` where it cannot be built."""
    return _native.load(LIBRARY, ["fixed_offset_conv.c"], _SIGNATURES)


def native_status() -> dict:
    """``{"available", "kernel" ("avx512" | "avx2" | "blas" | None), "openmp", "path", "reason"}``."""
    lib = native_library()
    return {**_native.status(LIBRARY), "kernel": None if lib is None else KERNELS[lib.omnidl_foc_kernel()],
            "openmp": lib is not None and bool(lib.omnidl_foc_openmp())}


def l2_cache_bytes(root: str = "/sys/devices/system/cpu/cpu0/cache") -> int | None:
    """Size of a core's level-2 cache from Linux's sysfs (``None`` where it is not listed)."""
    for d in sorted(Path(root).glob("index*")):
        try:
            level, kind = (d / "level").read_text().strip(), (d / "type").read_text().strip()
            size = (d / "size").read_text().strip().upper()
        except OSError:
            continue
        if level == "2" and kind in ("Unified", "Data") and size[:-1].isdigit() and size[-1] in "KM":
            return int(size[:-1]) * (1024 if size[-1] == "K" else 1024 ** 2)
    return None


#: bytes of one block of gathered taps, kept in a core's L2 cache while the weight's panels stream past it
BLOCK_BYTES = max(224 * 1024, (l2_cache_bytes() or 0) // 3)
#: a weight larger than this is streamed from memory once per block: its blocks take every position (up to
#: BIG_BLOCK_BYTES of taps), so that it is read once per call
BIG_WEIGHT_BYTES = BIG_BLOCK_BYTES = 8 << 20


def block_positions(channels: int, taps: int, out_channels: int, positions: int) -> int:
    """Output positions per block of the native kernel: a multiple of 12 (both register kernels' tile rows) with
    the block's taps about :data:`BLOCK_BYTES`, at least 24."""
    row = 4 * taps * channels
    block = max(24, BLOCK_BYTES // row // 12 * 12)
    if row * out_channels > BIG_WEIGHT_BYTES:
        block = max(block, min(-(-positions // 12) * 12, max(12, BIG_BLOCK_BYTES // row // 12 * 12)))
    return block


def _native_arguments(input: Tensor, weight: Tensor, positions: Tensor, mask: Tensor):
    B, C, H, W = input.shape
    Cout, K = weight.shape[0], weight.shape[2] * weight.shape[3]
    P = positions.shape[0] * positions.shape[1]
    xr = _rows(input)                                         # (B, H, W, C): no copy for a channels-last input
    wt = weight.permute(0, 2, 3, 1).reshape(Cout, K * C).contiguous()          # no copy for a channels-last weight
    pos = positions.detach().to(torch.float64).contiguous()
    m = mask.detach().to(torch.float64).contiguous()
    return xr, wt, pos, m, (B, C, H, W, Cout, K, P, block_positions(C, K, Cout, B * P))


def _rows(t: Tensor) -> Tensor:
    """``t (B, C, H, W)`` as channels-last rows ``(B, H, W, C)``, contiguous: no copy for a channels-last tensor
    (PyTorch's conversion to channels-last memory is about twice as fast as a copy of the permuted view)."""
    return t.contiguous(memory_format=torch.channels_last).permute(0, 2, 3, 1)


def _native_call(rc: int, what: str) -> None:
    if rc:
        raise MemoryError(f"fixed_offset_conv2d ({what}): the native kernel could not allocate its buffers")


def _uses_native(*tensors: Tensor) -> bool:
    return all(t.dtype == torch.float32 for t in tensors) and native_library() is not None


def cpu_forward(input, weight, bias, positions, mask, wrap):
    check_arguments(input, weight, bias, positions, mask)
    if not _uses_native(input, weight):
        return torch_forward(input, weight, bias, positions, mask, wrap)
    xr, wt, pos, m, (B, C, H, W, Cout, K, P, block) = _native_arguments(input, weight, positions, mask)
    b = None if bias is None else bias.contiguous()
    fmt = memory_format(input)                     # the kernel writes the output in the input's layout
    out = torch.empty(B, Cout, *positions.shape[:2], dtype=input.dtype, memory_format=fmt)
    _native_call(native_library().omnidl_foc_forward(
        xr.data_ptr(), H * W * C, C, H, W, pos.data_ptr(), m.data_ptr(), int(wrap), K, P, B, wt.data_ptr(), Cout,
        _native.pointer(b), out.data_ptr(), int(fmt != torch.channels_last), block, torch.get_num_threads()),
        "forward")
    return out


def cpu_backward(grad, input, weight, positions, mask, wrap, input_grad, weight_grad):
    if not _uses_native(grad, input, weight):
        return torch_backward(grad, input, weight, positions, mask, wrap, input_grad, weight_grad)
    xr, wt, pos, m, (B, C, H, W, Cout, K, P, block) = _native_arguments(input, weight, positions, mask)
    fmt = memory_format(input)                     # gx in the input's layout; grad read in that layout too
    planes = fmt != torch.channels_last
    g = grad.contiguous() if planes else _rows(grad)
    if input_grad:
        gx = torch.empty(B, C, H, W, dtype=input.dtype) if planes else torch.zeros(B, H, W, C, dtype=input.dtype)
    else:
        gx = None
    gwm = torch.zeros(K * C, Cout, dtype=weight.dtype) if weight_grad else None
    _native_call(native_library().omnidl_foc_backward(
        xr.data_ptr(), H * W * C, C, H, W, pos.data_ptr(), m.data_ptr(), int(wrap), K, P, B, wt.data_ptr(), Cout,
        g.data_ptr(), _native.pointer(gx), _native.pointer(gwm), int(planes), block, torch.get_num_threads()),
        "backward")
    if gx is None:
        gx = input.new_empty(0)
    elif not planes:
        gx = gx.permute(0, 3, 1, 2)
    kh, kw = weight.shape[2:]
    gw = gwm.reshape(kh, kw, C, Cout).permute(3, 2, 0, 1).contiguous() if weight_grad else weight.new_empty(0)
    return gx, gw
