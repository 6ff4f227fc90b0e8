"""``ProjectedConv2d``: a drop-in ``nn.Conv2d`` whose kernel follows the camera's distortion.

Without a camera the layer is exactly ``nn.Conv2d``. With a camera, for each input size it
meets it samples the input at fixed offsets from :func:`omnidl.nn.offsets.compute_sampling`
(EquiConv for an equirectangular camera, the calibrated convolution for a Kannala–Brandt
fisheye, the same construction for any registered camera). Sampling plans live in a
module-level cache shared by every layer with the same key.
"""
from __future__ import annotations

import threading
from typing import Literal

import torch
from torch import Tensor, nn

from omnidl.cameras.base import Camera
from omnidl.cameras.resolve import resolve_camera

from . import grid_conv, plan_columns, projected_taps, triton_conv
from .fused import fused_conv2d, fused_supported
from .offsets import Pair, compute_sampling
from .sampling import SamplingPlan, build_plan, deform_conv2d_reference, fixed_offset_conv2d
from .tiled import tiled_conv2d, tiled_supported

Backend = Literal["auto", "fast", "torchvision"]

_LOCK = threading.Lock()
_GEOMETRY: dict[tuple, tuple[Tensor, Tensor]] = {}  # key -> (offsets, mask), float64 CPU
_PLANS: dict[tuple, SamplingPlan] = {}  # key + (device, dtype) -> plan
_DEVICE_OFFSETS: dict[tuple, tuple[Tensor, Tensor]] = {}  # key + (device, dtype) -> (offsets, mask)
_GRID_PLANS: dict[tuple, grid_conv.GridPlan | None] = {}  # key + (device, dtype) -> CUDA sampling grid (or None)
_TRITON_PLANS: dict[tuple, triton_conv.TritonPlan] = {}  # key + (device, dtype) -> taps of the fused CUDA kernels


def _geometry_key(camera: Camera, in_hw: Pair, kernel_size: Pair, stride: Pair, padding: Pair, dilation: Pair,
                  wrap: bool, kernel: str, image_padding: Pair) -> tuple:
    return (camera, tuple(in_hw), tuple(kernel_size), tuple(stride), tuple(padding), tuple(dilation), bool(wrap),
            kernel, tuple(image_padding))


def _geometry(key: tuple) -> tuple[Tensor, Tensor]:
    with _LOCK:
        hit = _GEOMETRY.get(key)
    if hit is None:
        camera, in_hw, k, s, p, d, wrap, kernel, image_padding = key
        hit = compute_sampling(camera, in_hw, k, s, p, d, wrap=wrap, kernel=kernel, image_padding=image_padding)
        with _LOCK:
            hit = _GEOMETRY.setdefault(key, hit)
    return hit


def get_offsets(key: tuple, device: torch.device, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """Cached ``(offsets, mask)`` of a geometry key on ``device``/``dtype``."""
    full = key + (str(device), dtype)
    with _LOCK:
        hit = _DEVICE_OFFSETS.get(full)
    if hit is None:
        off, mask = _geometry(key)
        hit = (off.to(device=device, dtype=dtype), mask.to(device=device, dtype=dtype))
        with _LOCK:
            hit = _DEVICE_OFFSETS.setdefault(full, hit)
    return hit


def _per_device(table: dict, key: tuple, device: torch.device, dtype: torch.dtype, build):
    """``table``'s entry for a geometry key on ``device``/``dtype``, made once by ``build(offsets, mask, in_hw, k, s,
    p, d, wrap=)`` (float64; ``None``: does not apply) and moved there."""
    full = key + (str(device), dtype)
    with _LOCK:
        if full in table:
            return table[full]
    off, mask = _geometry(key)
    _, in_hw, k, s, p, d, wrap, _, _ = key
    hit = build(off, mask, in_hw, k, s, p, d, wrap=wrap)
    hit = None if hit is None else hit.to(device=device, dtype=dtype)
    with _LOCK:
        return table.setdefault(full, hit)


def get_plan(key: tuple, device: torch.device, dtype: torch.dtype) -> SamplingPlan:
    """Cached :class:`SamplingPlan` of a geometry key, built once per device/dtype."""
    return _per_device(_PLANS, key, device, dtype, build_plan)


def get_grid_plan(key: tuple, device: torch.device, dtype: torch.dtype) -> grid_conv.GridPlan | None:
    """Cached :class:`~omnidl.nn.grid_conv.GridPlan` of a geometry key (``None``: the grid path does not apply)."""
    return _per_device(_GRID_PLANS, key, device, dtype, grid_conv.build_grid_plan)


def get_triton_plan(key: tuple, device: torch.device, dtype: torch.dtype) -> triton_conv.TritonPlan:
    """Cached :class:`~omnidl.nn.triton_conv.TritonPlan` of a geometry key."""
    return _per_device(_TRITON_PLANS, key, device, dtype, triton_conv.build_plan)


def clear_plan_cache() -> None:
    """Forget every cached offset map and sampling plan."""
    with _LOCK:
        _GEOMETRY.clear()
        _PLANS.clear()
        _DEVICE_OFFSETS.clear()
        _GRID_PLANS.clear()
        _TRITON_PLANS.clear()


def plan_cache_info() -> dict[str, int]:
    """Number of cached geometries/plans and the bytes held by the plans and offset maps."""
    with _LOCK:
        plan_bytes = sum(p.nbytes() for p in _PLANS.values()) + sum(
            g.grid.numel() * g.grid.element_size() for g in _GRID_PLANS.values() if g is not None) + sum(
            t.nbytes() for t in _TRITON_PLANS.values())
        off_bytes = sum(o.numel() * o.element_size() + m.numel() * m.element_size()
                        for o, m in list(_GEOMETRY.values()) + list(_DEVICE_OFFSETS.values()))
        return {"geometries": len(_GEOMETRY), "plans": len(_PLANS), "device_offsets": len(_DEVICE_OFFSETS),
                "plan_bytes": plan_bytes, "offset_bytes": off_bytes}


def _pair(v) -> Pair:
    return (v, v) if isinstance(v, int) else (int(v[0]), int(v[1]))


class ProjectedConv2d(nn.Conv2d):
    """``nn.Conv2d`` with a distortion-aware kernel built from ``camera`` (drop-in; same state-dict keys).

    Args:
        in_channels ... padding_mode: as ``nn.Conv2d``. With a camera, ``padding_mode`` must
            be ``"zeros"`` (360° wrap is ``wrap``, never top/bottom) and string padding only
            ``"valid"`` or ``"same"`` (odd kernels, stride 1).
        camera: a :class:`~omnidl.cameras.Camera` (or a camera config mapping) of the network's
            INPUT image, or ``None``: plain ``nn.Conv2d``. Each input size ``H x W`` uses ``camera.resized(W, H,
            *image_padding)``.
        backend: ``"fast"`` (precomputed bilinear taps, custom autograd; groups=1),
            ``"torchvision"`` (``deform_conv2d`` with the same offsets; reference) or
            ``"auto"`` (fast when groups=1, else torchvision).
        wrap: ``"auto"`` (= ``camera.wraps_horizontally``), ``True`` or ``False``.
        kernel: ``"grid"`` or ``"tangent"``, see :mod:`omnidl.nn.offsets` (kernel-pitch rule:
            at the camera's reference pixel — principal point, or the panorama centre on
            the equator — the taps are exactly ``dilation`` pixels apart).
        image_padding: ``(pad_right, pad_bottom)`` of the calibrated image before the network.
        chunk_positions: output positions per chunk of the fast path's column GEMM (``None``: automatic,
            about ``sampling.CHUNK_BYTES`` of columns per chunk; on CPU float32 ``None`` runs the tiled
            oneDNN path of :mod:`omnidl.nn.tiled` instead of the GEMM).

    Input ``(B, C, H, W)``; output ``(B, Cout, Ho, Wo)`` (channels-last strides on the CPU's fast path).
    Under autocast, or with float16/bfloat16 tensors, the fast backend computes in float32 and returns the
    autocast dtype (or the input's): its sparse transposes have no half-precision kernels.
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size, stride=1, padding=0, dilation=1,
                 groups: int = 1, bias: bool = True, padding_mode: str = "zeros", device=None, dtype=None, *,
                 camera: Camera | None = None, backend: Backend = "auto", wrap: bool | str = "auto",
                 kernel: str = "grid", image_padding: Pair = (0, 0), chunk_positions: int | None = None) -> None:
        super().__init__(in_channels, out_channels, kernel_size, stride=stride, padding=padding, dilation=dilation,
                         groups=groups, bias=bias, padding_mode=padding_mode, device=device, dtype=dtype)
        if backend not in ("auto", "fast", "torchvision"):
            raise ValueError(f"backend must be 'auto', 'fast' or 'torchvision', got {backend!r}")
        if wrap not in ("auto", True, False):
            raise ValueError(f"wrap must be 'auto', True or False, got {wrap!r}")
        if kernel not in ("grid", "tangent"):
            raise ValueError(f"kernel must be 'grid' or 'tangent', got {kernel!r}")
        if backend == "fast" and groups != 1:
            raise NotImplementedError(f"backend='fast' supports groups=1 only (got groups={groups}); "
                                      "use backend='torchvision' or 'auto'")
        self.backend = backend
        self.wrap = wrap
        self.kernel = kernel
        self.image_padding = _pair(image_padding)
        self.chunk_positions = chunk_positions
        self.camera = camera  # validated below via the property setter

    # camera is a plain attribute (not a buffer): cameras are hashable value objects
    @property
    def camera(self) -> Camera | None:
        return self._camera

    @camera.setter
    def camera(self, camera: Camera | None) -> None:
        camera = resolve_camera(camera, default=None, allow_files=False)
        if camera is not None:
            if self.padding_mode != "zeros":
                raise ValueError(f"ProjectedConv2d with a camera needs padding_mode='zeros' (got "
                                 f"{self.padding_mode!r}); 360° cameras wrap horizontally through wrap=")
            if isinstance(self.padding, str) and self.padding == "same":
                if any(k % 2 == 0 for k in self.kernel_size) or any(s != 1 for s in self.stride):
                    raise ValueError("padding='same' with a camera needs odd kernels and stride 1")
            if self.wrap is True and not camera.wraps_horizontally:
                raise ValueError(f"wrap=True needs a camera covering 360° horizontally; {camera!r} does not")
        object.__setattr__(self, "_camera", camera)

    def _padding_pair(self) -> Pair:
        if isinstance(self.padding, str):
            if self.padding == "valid":
                return (0, 0)
            return tuple(d * (k - 1) // 2 for k, d in zip(self.kernel_size, self.dilation))  # type: ignore
        return tuple(self.padding)  # type: ignore[return-value]

    def geometry_key(self, in_hw: Pair) -> tuple:
        """Cache key of this layer on an input of size ``in_hw = (H, W)``."""
        wrap = self.camera.wraps_horizontally if self.wrap == "auto" else bool(self.wrap)
        return _geometry_key(self.camera, tuple(in_hw), self.kernel_size, self.stride, self._padding_pair(),
                             self.dilation, wrap, self.kernel, self.image_padding)

    def offsets(self, in_hw: Pair, device=None, dtype=torch.float64) -> tuple[Tensor, Tensor]:
        """``(offsets (1, 2K, Ho, Wo), mask (1, K, Ho, Wo))`` used on an input of size ``in_hw``."""
        if self.camera is None:
            raise ValueError("this ProjectedConv2d has no camera: it is a plain nn.Conv2d")
        return get_offsets(self.geometry_key(in_hw), torch.device(device or "cpu"), dtype)

    def resolved_backend(self) -> str:
        if self.backend == "auto":
            return "fast" if self.groups == 1 else "torchvision"
        return self.backend

    def _conv_forward(self, x: Tensor, weight: Tensor, bias: Tensor | None) -> Tensor:
        """The projected convolution of ``x`` with the given ``weight``/``bias`` (``forward`` passes its own;
        :class:`omnidl.nn.wconv.ConvNormAct` passes them with BatchNorm folded in)."""
        if self.camera is None:
            return super()._conv_forward(x, weight, bias)
        if x.dim() != 4 or x.shape[1] != self.in_channels:
            raise ValueError(f"ProjectedConv2d expects (B, {self.in_channels}, H, W) input, got {tuple(x.shape)}")
        key = self.geometry_key(tuple(x.shape[-2:]))
        if self.resolved_backend() == "fast":
            dev = x.device.type
            autocast = torch.is_autocast_enabled(dev) if dev in ("cpu", "cuda") else False
            if autocast or x.dtype not in (torch.float32, torch.float64) or weight.dtype != x.dtype:
                # mixed/low precision: the sampling plan's sparse transposes have no half/bfloat16 kernels
                # (MKL), so the fast backend computes in float32 and returns the autocast (or input) dtype
                out_dtype = torch.get_autocast_dtype(dev) if autocast else x.dtype
                with torch.autocast(dev, enabled=False):
                    y = self._fast(x.float(), weight.float(), None if bias is None else bias.float(), key)
                return y.to(out_dtype)
            return self._fast(x, weight, bias, key)
        off, mask = get_offsets(key, x.device, x.dtype)
        return deform_conv2d_reference(x, weight, bias, off, mask, self.stride, self._padding_pair(),
                                       self.dilation, wrap=key[6])

    def _fast(self, x: Tensor, weight: Tensor, bias: Tensor | None, key: tuple) -> Tensor:
        """The fast backend on CPU float32: with few output channels and no autograd graph the product onto the taps
        and a sampled sum (:mod:`.projected_taps`, CPU float32/float64), else the native fused gather+product kernel
        (:mod:`.fused`; a weight-heavy layer in training: gathered columns and the unfolded product,
        :mod:`.plan_columns`), else (no C compiler) oneDNN convolution of gathered tiles (:mod:`.tiled`); elsewhere, and
        whenever ``chunk_positions`` is given, the column GEMM (:func:`fixed_offset_conv2d`). On CUDA (without
        ``chunk_positions``) float32 the fused Triton kernels (:mod:`.triton_conv`), else one ``grid_sample`` of all
        taps and one product (:mod:`.grid_conv`)."""
        if self.chunk_positions is None and triton_conv.applies(x, weight):   # CUDA float32: implicit GEMM
            return triton_conv.triton_conv2d(x, weight, bias, get_triton_plan(key, x.device, x.dtype))
        if self.chunk_positions is None and grid_conv.applies(x):      # CUDA: one grid_sample, one product
            grid = get_grid_plan(key, x.device, x.dtype)
            if grid is not None:
                return grid_conv.grid_conv2d(x, weight, bias, grid)
        plan = get_plan(key, x.device, x.dtype)
        if self.chunk_positions is None:
            if projected_taps.pays(x, weight, bias, plan):
                return projected_taps.projected_taps_conv2d(x, weight, bias, plan)
            if fused_supported(x, weight, plan):
                if plan_columns.pays(x, weight, plan):    # weight-heavy layer in training: columns + product
                    return plan_columns.columns_conv2d(x, weight, bias, plan)
                return fused_conv2d(x, weight, bias, plan)
            if tiled_supported(x, weight):
                return tiled_conv2d(x, weight, bias, plan)
        return fixed_offset_conv2d(x, weight, bias, plan, positions=self.chunk_positions)

    def extra_repr(self) -> str:
        s = super().extra_repr()
        if self.camera is not None:
            s += f", camera={type(self.camera).__name__}({self.camera.width}x{self.camera.height})"
            s += f", backend={self.backend}, wrap={self.wrap}"
        return s
