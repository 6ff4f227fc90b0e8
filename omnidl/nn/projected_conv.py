"""``ProjectedConv2d``: a drop-in ``nn.Conv2d`` whose kernel follows the camera's distortion.

Without a camera the layer is exactly ``nn.Conv2d``. With a camera, on an input of size ``H x W`` its taps sample the
input at the fixed positions :func:`omnidl.nn.offsets.compute_sampling` derives from ``camera.resized(W, H)`` (EquiConv
for an equirectangular camera, the calibrated convolution for a fisheye, the same construction for any registered
camera), through one call of the registered op :func:`omnidl.ops.fixed_offset_conv2d`.

The sample positions come from a second registered op, ``omnidl::projected_sampling(geometry, height, width,
device)``: ``geometry`` is a JSON string naming the camera (its config) and the kernel, stride, padding, dilation,
wrap and kernel mode, so a traced or exported graph holds a self-describing call that computes (or finds in this
process's cache) the positions for the input size it meets, symbolic sizes included. Each geometry is computed once
per device and shared by every layer with that geometry.
"""
from __future__ import annotations

import json
from typing import Literal

import torch
from torch import Tensor, nn

from omnidl.cameras.base import Camera
from omnidl.cameras.resolve import resolve_camera
from omnidl.ops import fixed_offset_conv2d

from .offsets import Pair, compute_sampling
from .sampling import deform_conv2d_reference, sample_positions

Backend = Literal["auto", "op", "torchvision"]

#: geometry string -> its fields (camera, kernel_size, stride, padding, dilation, wrap, kernel, image_padding)
_FIELDS: dict[str, tuple] = {}
#: (geometry string, (H, W)) -> (offsets (1, 2K, Ho, Wo), mask (1, K, Ho, Wo)), float64 on the CPU
_GEOMETRY: dict[tuple, tuple[Tensor, Tensor]] = {}
#: (geometry string, (H, W), device) -> (positions (Ho, Wo, K, 2), mask (Ho, Wo, K)), float64 on that device
_TAPS: dict[tuple, tuple[Tensor, Tensor]] = {}


def geometry_string(camera: Camera, kernel_size: Pair, stride: Pair, padding: Pair, dilation: Pair, wrap: bool,
                    kernel: str, image_padding: Pair) -> str:
    """The JSON string that names a projected convolution's geometry (everything but the input size)."""
    return json.dumps({"camera": camera.to_config(), "kernel_size": list(kernel_size), "stride": list(stride),
                       "padding": list(padding), "dilation": list(dilation), "wrap": bool(wrap), "kernel": kernel,
                       "image_padding": list(image_padding)}, sort_keys=True)


def _fields(geometry: str) -> tuple:
    hit = _FIELDS.get(geometry)
    if hit is None:
        g = json.loads(geometry)
        hit = _FIELDS.setdefault(geometry, (resolve_camera(g["camera"], default=None, allow_files=False),
                                            *(tuple(g[k]) for k in ("kernel_size", "stride", "padding", "dilation")),
                                            bool(g["wrap"]), g["kernel"], tuple(g["image_padding"])))
    return hit


def offsets_and_mask(geometry: str, in_hw: Pair) -> tuple[Tensor, Tensor]:
    """``(offsets (1, 2K, Ho, Wo), mask (1, K, Ho, Wo))`` of a geometry on an ``in_hw`` input, float64 CPU, cached."""
    key = (geometry, (int(in_hw[0]), int(in_hw[1])))
    hit = _GEOMETRY.get(key)
    if hit is None:
        camera, k, s, p, d, wrap, kernel, image_padding = _fields(geometry)
        hit = _GEOMETRY.setdefault(key, compute_sampling(camera, key[1], k, s, p, d, wrap=wrap, kernel=kernel,
                                                         image_padding=image_padding))
    return hit


@torch.library.custom_op("omnidl::projected_sampling", mutates_args=())
def projected_sampling(geometry: str, height: int, width: int, device: torch.device) -> tuple[Tensor, Tensor]:
    """``(positions (Ho, Wo, K, 2), mask (Ho, Wo, K))`` (float64 on ``device``) where the taps of a projected
    convolution of ``geometry`` (:func:`geometry_string`) sample an ``height x width`` input: the arguments of
    :func:`omnidl.ops.fixed_offset_conv2d`. Cached per geometry, size and device; the tensors returned are the
    cached ones (read them, never write them)."""
    key = (geometry, (int(height), int(width)), str(device))
    hit = _TAPS.get(key)
    if hit is None:
        _, k, s, p, d, *_ = _fields(geometry)
        pos, mask = sample_positions(*offsets_and_mask(geometry, key[1]), key[1], k, s, p, d)
        hit = _TAPS.setdefault(key, (pos.to(device), mask.to(device)))
    return hit


@projected_sampling.register_fake
def _projected_sampling_fake(geometry, height, width, device):
    g = json.loads(geometry)
    (kh, kw), (sh, sw), (ph, pw), (dh, dw) = (g[k] for k in ("kernel_size", "stride", "padding", "dilation"))
    Ho = (height + 2 * ph - dh * (kh - 1) - 1) // sh + 1
    Wo = (width + 2 * pw - dw * (kw - 1) - 1) // sw + 1
    return (torch.empty(Ho, Wo, kh * kw, 2, dtype=torch.float64, device=device),
            torch.empty(Ho, Wo, kh * kw, dtype=torch.float64, device=device))


def clear_sampling_cache() -> None:
    """Forget every cached geometry."""
    _GEOMETRY.clear()
    _TAPS.clear()


def sampling_cache_info() -> dict[str, int]:
    """Number of cached geometries and sample-position sets, and the bytes they hold."""
    tensors = [t for pair in list(_GEOMETRY.values()) + list(_TAPS.values()) for t in pair]
    return {"geometries": len(_GEOMETRY), "taps": len(_TAPS),
            "bytes": sum(t.numel() * t.element_size() for t in tensors)}


def check_input(x: Tensor, channels: int) -> None:
    """Raise a ``ValueError`` unless ``x`` is ``(B, channels, H, W)``."""
    if x.dim() != 4 or x.shape[1] != channels:
        raise ValueError(f"ProjectedConv2d expects (B, {channels}, H, W) input, got {tuple(x.shape)}")


torch.fx.wrap("check_input")   # torch.fx.symbolic_trace records the check as one call (it branches on the shape)


def _pair(v) -> Pair:
    return (v, v) if isinstance(v, int) else (int(v[0]), int(v[1]))


class ProjectedConv2d(nn.Conv2d):
    """``nn.Conv2d`` with a distortion-aware kernel built from ``camera`` (drop-in; same state-dict keys).

    Args:
        in_channels ... padding_mode: as ``nn.Conv2d``. With a camera, ``padding_mode`` must be ``"zeros"`` (360° wrap
            is ``wrap``, never top/bottom) and string padding only ``"valid"`` or ``"same"`` (odd kernels, stride 1).
        camera: a :class:`~omnidl.cameras.Camera` (or a camera config mapping) of the network's INPUT image, or
            ``None``: plain ``nn.Conv2d``. Each input size ``H x W`` uses ``camera.resized(W, H, *image_padding)``.
        backend: ``"op"`` (:func:`omnidl.ops.fixed_offset_conv2d`; groups=1), ``"torchvision"``
            (``torchvision.ops.deform_conv2d`` with the same offsets: the reference) or ``"auto"`` (the op when
            groups=1, else torchvision).
        wrap: ``"auto"`` (= ``camera.wraps_horizontally``), ``True`` or ``False``.
        kernel: ``"grid"`` or ``"tangent"``, see :mod:`omnidl.nn.offsets` (kernel-pitch rule: at the camera's
            reference pixel - principal point, or the panorama centre on the equator - the taps are exactly
            ``dilation`` pixels apart).
        image_padding: ``(pad_right, pad_bottom)`` of the calibrated image before the network.

    Input ``(B, C, H, W)``; output ``(B, Cout, Ho, Wo)``, of ``nn.Conv2d``'s size. Gradients of any order flow to
    the input, weight and bias (the sample positions are fixed). Under autocast the op computes in float32.
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size, stride=1, padding=0, dilation=1,
                 groups: int = 1, bias: bool = True, padding_mode: str = "zeros", device=None, dtype=None, *,
                 camera: Camera | None = None, backend: Backend = "auto", wrap: bool | str = "auto",
                 kernel: str = "grid", image_padding: Pair = (0, 0)) -> None:
        super().__init__(in_channels, out_channels, kernel_size, stride=stride, padding=padding, dilation=dilation,
                         groups=groups, bias=bias, padding_mode=padding_mode, device=device, dtype=dtype)
        if backend not in ("auto", "op", "torchvision"):
            raise ValueError(f"backend must be 'auto', 'op' or 'torchvision', got {backend!r}")
        if wrap not in ("auto", True, False):
            raise ValueError(f"wrap must be 'auto', True or False, got {wrap!r}")
        if kernel not in ("grid", "tangent"):
            raise ValueError(f"kernel must be 'grid' or 'tangent', got {kernel!r}")
        if backend == "op" and groups != 1:
            raise ValueError(f"backend='op' supports groups=1 only (got groups={groups}); use backend='torchvision' "
                             "or 'auto'")
        self.backend = backend
        self.wrap = wrap
        self.kernel = kernel
        self.image_padding = _pair(image_padding)
        self.camera = camera  # validated by the property setter

    #: attributes that define the geometry: setting one re-derives the layer's geometry number
    _GEOMETRY_ATTRS = frozenset({"wrap", "kernel", "image_padding", "kernel_size", "stride", "padding", "dilation"})

    def __setattr__(self, name: str, value) -> None:
        super().__setattr__(name, value)
        if name in self._GEOMETRY_ATTRS and "_camera" in self.__dict__:
            self._refresh_geometry()

    def _refresh_geometry(self) -> None:
        geometry = None
        if self.camera is not None:
            geometry = geometry_string(self.camera, self.kernel_size, self.stride, self._padding_pair(),
                                       self.dilation, self.wraps, self.kernel, self.image_padding)
        object.__setattr__(self, "geometry", geometry)

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
        self._refresh_geometry()

    def _padding_pair(self) -> Pair:
        if isinstance(self.padding, str):
            if self.padding == "valid":
                return (0, 0)
            return tuple(d * (k - 1) // 2 for k, d in zip(self.kernel_size, self.dilation))  # type: ignore
        return tuple(self.padding)  # type: ignore[return-value]

    @property
    def wraps(self) -> bool:
        """Whether the taps wrap around the left/right border (with a camera)."""
        return self.camera.wraps_horizontally if self.wrap == "auto" else bool(self.wrap)

    def offsets(self, in_hw: Pair, device=None, dtype=torch.float64) -> tuple[Tensor, Tensor]:
        """``(offsets (1, 2K, Ho, Wo), mask (1, K, Ho, Wo))`` used on an input of size ``in_hw``."""
        if self.camera is None:
            raise ValueError("this ProjectedConv2d has no camera: it is a plain nn.Conv2d")
        off, mask = offsets_and_mask(self.geometry, in_hw)
        return off.to(device=device or "cpu", dtype=dtype), mask.to(device=device or "cpu", dtype=dtype)

    def resolved_backend(self) -> str:
        if self.backend == "auto":
            return "op" if self.groups == 1 else "torchvision"
        return self.backend

    def _conv_forward(self, x: Tensor, weight: Tensor, bias: Tensor | None) -> Tensor:
        if self.camera is None:
            return super()._conv_forward(x, weight, bias)
        check_input(x, self.in_channels)
        if self.resolved_backend() == "torchvision":
            off, mask = offsets_and_mask(self.geometry, tuple(x.shape[-2:]))
            return deform_conv2d_reference(x, weight, bias, off.to(x.device), mask.to(x.device), self.stride,
                                           self._padding_pair(), self.dilation, wrap=self.wraps)
        positions, mask = projected_sampling(self.geometry, x.shape[-2], x.shape[-1], x.device)
        return fixed_offset_conv2d(x, weight, bias, positions, mask, self.wraps)

    def extra_repr(self) -> str:
        s = super().extra_repr()
        if self.camera is not None:
            s += f", camera={type(self.camera).__name__}({self.camera.width}x{self.camera.height})"
            s += f", backend={self.backend}, wrap={self.wrap}"
        return s
