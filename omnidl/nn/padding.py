"""Panorama-aware padding and a "same"-size convolution factory.

An equirectangular panorama is periodic in longitude only: column ``W`` is column ``0``
again, but the top row (north pole) is *not* the neighbour of the bottom row. So the
padding used here wraps **horizontally** and pads vertically with zeros (or replicates /
reflects). The public FreDSNet code uses ``padding_mode='circular'``, which wraps both
axes (top row sees the bottom row) — a bug that omnidl does not reproduce.

* :func:`pad_panorama` / :class:`PanoramaPad2d` — the functional core and its module.
* :class:`CircularConv2d` — an ``nn.Conv2d`` (same state-dict keys) with horizontal wrap.
* :func:`make_conv2d` — one factory for every "same" convolution of a block:
  standard (zero padding), horizontally circular, or distortion-aware
  (``omnidl.nn.projected_conv.ProjectedConv2d`` when a ``camera`` is given).
"""
from __future__ import annotations

from typing import Any, Callable, Literal

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from . import thin_layout, winograd_train
from .capture import capturing
from .unfold_conv import conv2d

PaddingMode = Literal["zeros", "circular"]
VerticalMode = Literal["zeros", "replicate", "reflect"]


def pad_panorama(x: Tensor, pad_w: int | tuple[int, int], pad_h: int | tuple[int, int] = 0,
                 vertical: VerticalMode = "zeros") -> Tensor:
    """Pad ``x (..., H, W)`` with a horizontal wrap-around and a non-periodic vertical border.

    Args:
        x: ``(B, C, H, W)`` (or any ``(..., H, W)`` with at least 3 dims) feature map.
        pad_w: columns added on the left and right (``int`` or ``(left, right)``), copied
            from the opposite side (longitude wraps).
        pad_h: rows added on the top and bottom (``int`` or ``(top, bottom)``), never wrapped.
        vertical: ``"zeros"`` | ``"replicate"`` | ``"reflect"`` for the rows.

    Returns:
        ``(..., H + top + bottom, W + left + right)``.
    """
    left, right = (pad_w, pad_w) if isinstance(pad_w, int) else pad_w
    top, bottom = (pad_h, pad_h) if isinstance(pad_h, int) else pad_h
    w = x.shape[-1]
    if left > w or right > w:
        raise ValueError(f"pad_panorama: horizontal padding ({left}, {right}) larger than the width {w}")
    if left or right:
        if x.requires_grad and torch.is_grad_enabled() and not capturing():
            x = _WrapColumns.apply(x, left, right)
        else:
            x = _wrap_columns(x, left, right)
    if top or bottom:
        if vertical == "zeros":
            x = F.pad(x, (0, 0, top, bottom))
        elif vertical in ("replicate", "reflect"):
            x = F.pad(x, (0, 0, top, bottom), mode=vertical)
        else:
            raise ValueError(f"pad_panorama: vertical must be 'zeros', 'replicate' or 'reflect', got {vertical!r}")
    return x


def _cat_w(*parts: Tensor | None) -> Tensor:
    """Concatenate the non-``None`` parts along the last (width) axis."""
    return torch.cat([p for p in parts if p is not None], dim=-1)


def _wrap_columns(x: Tensor, left: int, right: int) -> Tensor:
    """``x (..., W)`` -> ``(..., left + W + right)``: the last ``left`` columns, ``x``, the first ``right`` ones."""
    w = x.shape[-1]
    return _cat_w(x[..., w - left:] if left else None, x, x[..., :right] if right else None)


class _WrapColumns(torch.autograd.Function):
    """:func:`_wrap_columns` with a backward of its own: the gradient of ``x`` is written once, the middle columns
    copied and the two wrapped strips added onto the columns they came from. (Autograd's own backward of the
    concatenation gives each strip a zero-filled buffer of the size of ``x`` and adds the three: on FreDSNet's
    full-resolution 128-channel maps that is two more 16.8 MB buffers and three passes over them.)"""

    @staticmethod
    def forward(ctx, x: Tensor, left: int, right: int) -> Tensor:   # type: ignore[override]
        ctx.left, ctx.right = left, right
        return _wrap_columns(x, left, right)

    @staticmethod
    def backward(ctx, g: Tensor) -> tuple[Tensor, None, None]:   # type: ignore[override]
        return thin_layout.unwrap(g, ctx.left, ctx.right), None, None


class PanoramaPad2d(nn.Module):
    """Module form of :func:`pad_panorama` (horizontal wrap, vertical ``zeros``/``replicate``/``reflect``)."""

    def __init__(self, pad_w: int | tuple[int, int], pad_h: int | tuple[int, int] = 0,
                 vertical: VerticalMode = "zeros") -> None:
        super().__init__()
        self.pad_w, self.pad_h, self.vertical = pad_w, pad_h, vertical

    def forward(self, x: Tensor) -> Tensor:
        return pad_panorama(x, self.pad_w, self.pad_h, self.vertical)

    def extra_repr(self) -> str:
        return f"pad_w={self.pad_w}, pad_h={self.pad_h}, vertical={self.vertical!r}"


class CircularConv2d(nn.Conv2d):
    """``nn.Conv2d`` whose horizontal padding wraps around (360° panoramas); vertical padding is zeros.

    Same constructor, parameters and state-dict keys (``weight``, ``bias``) as ``nn.Conv2d``;
    ``padding`` must be an int or ``(pad_h, pad_w)`` tuple (``"same"`` is resolved for odd kernels).
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int | tuple[int, int],
                 stride: int | tuple[int, int] = 1, padding: int | tuple[int, int] | str = 0,
                 dilation: int | tuple[int, int] = 1, groups: int = 1, bias: bool = True,
                 device: Any = None, dtype: Any = None) -> None:
        super().__init__(in_channels, out_channels, kernel_size, stride, 0, dilation, groups, bias,
                         device=device, dtype=dtype)
        kh, kw = self.kernel_size
        dh, dw = self.dilation
        if padding == "same":
            if kh % 2 == 0 or kw % 2 == 0:
                raise ValueError(f"CircularConv2d: padding='same' needs an odd kernel, got {self.kernel_size}")
            padding = (dh * (kh - 1) // 2, dw * (kw - 1) // 2)
        elif isinstance(padding, str):
            raise ValueError(f"CircularConv2d: padding must be an int, a (pad_h, pad_w) tuple or 'same', got {padding!r}")
        self.wrap_padding = (padding, padding) if isinstance(padding, int) else tuple(padding)

    def _conv_forward(self, x: Tensor, weight: Tensor, bias: Tensor | None) -> Tensor:
        """The convolution with the given ``weight``/``bias`` (``nn.Conv2d.forward`` calls this with its own;
        :class:`omnidl.nn.wconv.ConvNormAct` with BatchNorm folded in)."""
        ph, pw = self.wrap_padding
        path = self._path(x, weight)
        if path == "strips":
            return wrapped_conv2d(x, weight, bias, (ph, pw), self.dilation, self.groups)
        if path == "winograd":
            return winograd_train.conv2d(x, weight, bias, wrap=1)          # a 3x3 layer in training, wrapped
        if path == "channels-last":                                      # a thin head: wrapped into channels-last
            return self._conv_wrapped(thin_layout.to_channels_last(x, pw, pw), weight, bias)
        if pw:
            x = pad_panorama(x, pw)
        return conv2d(x, weight, bias, self.stride, (ph, 0), self.dilation, self.groups)

    def _path(self, x: Tensor, weight: Tensor) -> str:
        """How :meth:`_conv_forward` convolves ``x``: ``"strips"`` (no autograd, a large map: zero padding, then the
        border columns again from a thin wrapped strip), ``"winograd"`` (a 3x3 layer in training), ``"channels-last"``
        (a thin head in training: on a wrapped channels-last copy) or ``"padded"`` (on a wrapped copy)."""
        ph, pw = self.wrap_padding
        if (pw and self.stride == (1, 1) and 2 * pw == self.dilation[1] * (self.kernel_size[1] - 1)
                and x.shape[-1] >= 4 * pw and x.numel() >= BORDER_FIX_NUMEL and not torch.is_grad_enabled()):
            return "strips"
        if (pw, ph) == (1, 1) and winograd_train.applies(x, weight, self.stride, 1, self.dilation, self.groups):
            return "winograd"
        if pw and pw <= x.shape[-1] and thin_layout.pays(x, weight):
            return "channels-last"
        return "padded"

    def channels_last_wrap(self, x: Tensor) -> int:
        """The columns on each side by which this convolution wraps ``x`` into channels-last memory (its thin-head
        path), or 0 where it takes another path. A caller that computes ``x`` itself can write it that way at once
        (e.g. :func:`omnidl.nn.fusion.upsample_sum` with ``wrap``) and call :meth:`conv_wrapped`."""
        return self.wrap_padding[1] if self._path(x, self.weight) == "channels-last" else 0

    def conv_wrapped(self, xp: Tensor) -> Tensor:
        """The convolution of a map given already wrapped: ``xp (B, C, H, pw + W + pw)`` channels-last, with ``pw``
        from :meth:`channels_last_wrap` -> ``(B, Cout, Ho, Wo)`` contiguous, equal to ``self(x)``."""
        return self._conv_wrapped(xp, self.weight, self.bias)

    def _conv_wrapped(self, xp: Tensor, weight: Tensor, bias: Tensor | None) -> Tensor:
        ph = self.wrap_padding[0]
        return F.conv2d(xp, weight, bias, self.stride, (ph, 0), self.dilation, self.groups).contiguous()

    def extra_repr(self) -> str:
        return super().extra_repr() + f", wrap_padding={self.wrap_padding} (horizontal wrap)"


#: inputs with at least this many elements skip the wrapped copy of the whole map when no gradient is recorded
#: (see :func:`wrapped_conv2d`; with autograd the copy is cheaper: the strips' backward writes full-size buffers)
BORDER_FIX_NUMEL = 1 << 20


def wrapped_conv2d(x: Tensor, weight: Tensor, bias: Tensor | None, padding: tuple[int, int],
                  dilation: tuple[int, int], groups: int) -> Tensor:
    """Stride-1 "same" convolution with a horizontal wrap (``pw`` columns) and ``ph`` zero rows, without
    copying ``x`` into a padded buffer (``x`` at least ``4 pw`` columns wide).

    The convolution runs zero-padded (no copy: oneDNN pads internally); then only the ``pw`` border
    columns on each side, the ones that should have seen the other side of the panorama, are recomputed
    from one thin wrapped strip (columns ``W-2pw .. W-1`` then ``0 .. 2pw-1``) and written over. Same
    result as padding first; on large maps this saves a full copy (and its page faults) per convolution.
    """
    ph, pw = padding
    return border_strip_conv(x, pw, lambda t, p: F.conv2d(t, weight, bias, 1, (ph, p), dilation, groups))


def border_strip_conv(x: Tensor, pw: int, conv: Callable[[Tensor, int], Tensor]) -> Tensor:
    """``conv(x, pw)`` (the map convolved with ``pw`` zero columns on each side, no copy) with its ``pw`` border
    columns on each side replaced by ``conv(strip, 0)`` of the wrapped strip of columns ``W-2pw .. W-1, 0 .. 2pw-1``:
    a horizontally wrapping convolution whose kernel spans ``2 pw + 1`` columns at width stride 1 (``x`` at least
    ``4 pw`` columns wide). ``conv(t, p)`` convolves ``t`` with ``p`` zero columns each side; it is called on the strip
    second (its output: the right border's columns, then the left border's)."""
    y = conv(x, pw)
    s = conv(torch.cat([x[..., -2 * pw:], x[..., :2 * pw]], dim=-1), 0)
    y[..., :pw] = s[..., pw:]
    y[..., -pw:] = s[..., :pw]
    return y


def make_conv2d(in_channels: int, out_channels: int, kernel_size: int = 3, *, stride: int = 1,
                dilation: int = 1, bias: bool = True, padding: PaddingMode = "zeros", camera: Any = None,
                conv_layer: Callable[..., nn.Module] | None = None) -> nn.Module:
    """A "same"-padded convolution (output size = input size / stride).

    Args:
        padding: ``"zeros"`` (``nn.Conv2d``) or ``"circular"`` (:class:`CircularConv2d`, horizontal wrap).
            Ignored for distortion-aware convolutions, which take the wrap from the camera.
        camera: a :class:`omnidl.cameras.Camera` (or camera config mapping). When given and
            ``kernel_size > 1``, the convolution is ``ProjectedConv2d(..., camera=camera)``
            (EquiConv for an equirectangular camera). ``None``: a standard convolution.
        conv_layer: overrides the class used for ``kernel_size > 1`` (called with ``nn.Conv2d``'s
            arguments, plus ``camera=`` when a camera is given).

    1x1 convolutions are always plain ``nn.Conv2d`` (there is nothing to deform).
    """
    pad = dilation * (kernel_size - 1) // 2
    kw = dict(stride=stride, padding=pad, dilation=dilation, bias=bias)
    if kernel_size == 1:
        return nn.Conv2d(in_channels, out_channels, 1, stride=stride, bias=bias)
    if conv_layer is not None:
        if camera is not None:
            return conv_layer(in_channels, out_channels, kernel_size, camera=camera, **kw)
        return conv_layer(in_channels, out_channels, kernel_size, **kw)
    if camera is not None:
        from omnidl.nn.projected_conv import ProjectedConv2d
        return ProjectedConv2d(in_channels, out_channels, kernel_size, camera=camera, **kw)
    if padding == "circular":
        return CircularConv2d(in_channels, out_channels, kernel_size, **kw)
    if padding == "zeros":
        return nn.Conv2d(in_channels, out_channels, kernel_size, **kw)
    raise ValueError(f"make_conv2d: padding must be 'zeros' or 'circular', got {padding!r}")
