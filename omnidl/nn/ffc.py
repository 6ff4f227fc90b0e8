"""Fast Fourier Convolution (Chi et al., NeurIPS 2020) and FreDSNet's Fourier block (thesis §4.3.1).

An FFC splits the channels into a *local* part (ordinary 3x3 convolutions) and a *global*
part whose global→global path is a :class:`SpectralTransform`: a 1x1 convolution applied to
the 2D real FFT of the feature map, i.e. an image-wide receptive field in one layer.

Layers (functional pieces are plain tensor code inside ``forward``):

* :class:`FourierUnit` — ``rfft2`` → 1x1 conv + BN + activation on (Re, Im) → ``irfft2``.
* :class:`SpectralTransform` — 1x1 reduce → ``x + FourierUnit(x)`` → 1x1 expand.
* :class:`FFC` — the four paths l→l, l→g, g→l (3x3 convs) and g→g (spectral), channel split
  ``ratio_gin`` / ``ratio_gout``; takes a tensor (split: local = first channels, global = last)
  or a ``(x_local, x_global)`` tuple and returns a tuple (``None`` for an empty part).
* :class:`FourierBlock` — FFC + BatchNorm + activation per part + identity residual, tensor in
  and out: the block FreDSNet uses in every encoder/decoder stage.

Defaults follow the public FreDSNet code; LaMa's FFC (Suvorov et al. 2022) differs in:

============================  ================================  ==================================
choice                        FreDSNet (default here)           LaMa
============================  ================================  ==================================
activation                    PReLU (per channel)               ReLU
FFT normalisation             ``fft_norm="backward"``           ``"ortho"``
Re/Im layout for the 1x1 conv ``spectrum_layout="width"``:      ``"channels"``: Re/Im interleaved
                              Re and Im side by side along      on channels, a 2C→2C conv that
                              width, one real C→C conv applied  mixes them
                              to both (a complex-linear map)
conv biases                   ``bias=True``                     ``bias=False``
residual                      identity inside the block         in ``FFCResnetBlock`` (2 FFCs)
local 3x3 padding             zeros (``padding="zeros"``)       reflect
local Fourier unit (LFU)      not used                          optional (not implemented here)
============================  ================================  ==================================

Two deliberate departures from the public FreDSNet code: (1) its spectral skip is
``copy.copy(x)``, which cuts the autograd graph (the reduce conv learns only through the FFT
path) — here the skip is ``x`` and gradients reach every parameter; (2) ``irfft2`` gets the
output size ``s=(H, W)``, so odd feature-map widths work (the public code needs W % 64 == 0).
Under autocast the FFT runs in float32 (cuFFT half precision only supports powers of two).
"""
from __future__ import annotations

from typing import Any, Callable, Literal

import torch
import torch.nn as nn
from torch import Tensor

from .padding import PaddingMode, make_conv2d
from .wconv import Activation, make_activation

FFTNorm = Literal["backward", "ortho", "forward"]
SpectrumLayout = Literal["width", "channels"]


class FourierUnit(nn.Module):
    """Pointwise convolution in the frequency domain: ``(B, C_in, H, W) -> (B, C_out, H, W)``.

    ``X = rfft2(x)`` (``(B, C, H, W//2+1)`` complex) → Re/Im arranged per ``spectrum_layout`` →
    1x1 conv → BN → activation → back to complex → ``irfft2(s=(H, W))``.

    Args:
        fft_norm: ``torch.fft`` normalisation (``"backward"``: FreDSNet, ``"ortho"``: LaMa).
        spectrum_layout: ``"width"`` (FreDSNet: Re | Im concatenated along width, a C_in→C_out conv)
            or ``"channels"`` (LaMa: (Re, Im) interleaved per channel, a 2C_in→2C_out conv).
    """

    def __init__(self, in_channels: int, out_channels: int, *, fft_norm: FFTNorm = "backward",
                 spectrum_layout: SpectrumLayout = "width", activation: Activation = "prelu",
                 bias: bool = True, norm: bool = True) -> None:
        super().__init__()
        if spectrum_layout not in ("width", "channels"):
            raise ValueError(f"spectrum_layout must be 'width' or 'channels', got {spectrum_layout!r}")
        if fft_norm not in ("backward", "ortho", "forward"):
            raise ValueError(f"fft_norm must be 'backward', 'ortho' or 'forward', got {fft_norm!r}")
        self.fft_norm, self.spectrum_layout = fft_norm, spectrum_layout
        k = 1 if spectrum_layout == "width" else 2
        self.conv = nn.Conv2d(k * in_channels, k * out_channels, 1, bias=bias)
        self.norm = nn.BatchNorm2d(k * out_channels) if norm else nn.Identity()
        self.act = make_activation(activation, k * out_channels)

    def forward(self, x: Tensor) -> Tensor:
        b, c, h, w = x.shape
        xf = x.to(torch.promote_types(x.dtype, torch.float32))            # half-precision FFTs: powers of 2 only
        spec = torch.fft.rfft2(xf, norm=self.fft_norm)                     # (B, C, H, Wf)
        wf = spec.shape[-1]
        if self.spectrum_layout == "width":
            z = torch.cat([spec.real, spec.imag], dim=-1)                  # (B, C, H, 2Wf)
        else:
            z = torch.stack([spec.real, spec.imag], dim=2).reshape(b, 2 * c, h, wf)
        z = self.act(self.norm(self.conv(z))).to(xf.dtype)
        if self.spectrum_layout == "width":
            spec = torch.complex(z[..., :wf], z[..., wf:])
        else:
            z = z.reshape(b, -1, 2, h, wf)
            spec = torch.complex(z[:, :, 0], z[:, :, 1])
        y = torch.fft.irfft2(spec, s=(h, w), norm=self.fft_norm)
        return y.to(x.dtype)


class SpectralTransform(nn.Module):
    """Global path of an FFC: ``(B, C_in, H, W) -> (B, C_out, H/stride, W/stride)``.

    ``x = act(BN(conv1x1(x)))`` (``C_in -> hidden``, default ``C_out // 2``), then
    ``conv1x1(x + FourierUnit(x))`` (``hidden -> C_out``). ``stride=2`` average-pools first.
    The skip ``x`` keeps its gradient (unlike the public FreDSNet code).
    """

    def __init__(self, in_channels: int, out_channels: int, *, hidden: int | None = None, stride: int = 1,
                 activation: Activation = "prelu", bias: bool = True, fft_norm: FFTNorm = "backward",
                 spectrum_layout: SpectrumLayout = "width") -> None:
        super().__init__()
        if stride not in (1, 2):
            raise ValueError(f"SpectralTransform: stride must be 1 or 2, got {stride}")
        hidden = max(1, out_channels // 2) if hidden is None else int(hidden)
        self.downsample = nn.AvgPool2d(2, 2) if stride == 2 else nn.Identity()
        self.conv_in = nn.Sequential(nn.Conv2d(in_channels, hidden, 1, bias=bias), nn.BatchNorm2d(hidden),
                                     make_activation(activation, hidden))
        self.fourier = FourierUnit(hidden, hidden, fft_norm=fft_norm, spectrum_layout=spectrum_layout,
                                   activation=activation, bias=bias)
        self.conv_out = nn.Conv2d(hidden, out_channels, 1, bias=bias)

    def forward(self, x: Tensor) -> Tensor:
        conv, norm, act = self.conv_in
        x = self.downsample(x)
        x = act(norm(conv(x)))
        return self.conv_out(x + self.fourier(x))


def check_channels(x: Tensor, channels: int) -> None:
    """Raise a ``ValueError`` unless ``x`` has ``channels`` channels."""
    if x.shape[1] != channels:
        raise ValueError(f"FFC expects {channels} input channels, got shape {tuple(x.shape)}")


torch.fx.wrap("check_channels")   # torch.fx.symbolic_trace records the check as one call


def split_channels(channels: int, ratio_global: float) -> tuple[int, int]:
    """``(local, global)`` channel counts: ``global = int(channels * ratio_global)``."""
    if not 0.0 <= ratio_global <= 1.0:
        raise ValueError(f"global channel ratio must lie in [0, 1], got {ratio_global}")
    g = int(channels * ratio_global)
    return channels - g, g


class FFC(nn.Module):
    """Fast Fourier Convolution with a local/global channel split.

    Args:
        in_channels, out_channels: total widths; ``ratio_gin`` / ``ratio_gout`` of them are global.
        kernel_size, stride, dilation: of the three spatial paths (l→l, l→g, g→l).
        spectral: ``True``: g→g is a :class:`SpectralTransform` (ablation code "F");
            ``False``: an ordinary ``kernel_size`` convolution (ablation code "X").
        padding: ``"zeros"`` (FreDSNet) or ``"circular"`` (horizontal wrap) for the spatial paths.
        camera: makes the spatial paths distortion-aware ``ProjectedConv2d`` ("Equi"); ``None``: "Std".
        conv_layer: custom class for the spatial paths (see :func:`omnidl.nn.padding.make_conv2d`).
        activation, bias, fft_norm, spectrum_layout: of the spectral path (see :class:`FourierUnit`).

    ``forward(x)`` takes ``(B, C_in, H, W)`` (local = first ``C_in - int(C_in*ratio_gin)`` channels,
    global = the rest) or a ``(x_local, x_global)`` tuple, and returns ``(y_local, y_global)``;
    a part with zero channels is ``None``.
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int = 3, ratio_gin: float = 0.5,
                 ratio_gout: float = 0.5, *, stride: int = 1, dilation: int = 1, bias: bool = True,
                 spectral: bool = True, padding: PaddingMode = "zeros", camera: Any = None,
                 conv_layer: Callable[..., nn.Module] | None = None, activation: Activation = "prelu",
                 fft_norm: FFTNorm = "backward", spectrum_layout: SpectrumLayout = "width") -> None:
        super().__init__()
        self.in_cl, self.in_cg = split_channels(in_channels, ratio_gin)
        self.out_cl, self.out_cg = split_channels(out_channels, ratio_gout)

        def spatial(cin: int, cout: int) -> nn.Module | None:
            if cin == 0 or cout == 0:
                return None
            return make_conv2d(cin, cout, kernel_size, stride=stride, dilation=dilation, bias=bias,
                               padding=padding, camera=camera, conv_layer=conv_layer)

        self.conv_l2l = spatial(self.in_cl, self.out_cl)
        self.conv_l2g = spatial(self.in_cl, self.out_cg)
        self.conv_g2l = spatial(self.in_cg, self.out_cl)
        if self.in_cg == 0 or self.out_cg == 0:
            self.conv_g2g = None
        elif spectral:
            self.conv_g2g = SpectralTransform(self.in_cg, self.out_cg, stride=stride, activation=activation,
                                              bias=bias, fft_norm=fft_norm, spectrum_layout=spectrum_layout)
        else:
            self.conv_g2g = spatial(self.in_cg, self.out_cg)

    def split(self, x: Tensor | tuple[Tensor | None, Tensor | None]) -> tuple[Tensor | None, Tensor | None]:
        """``(B, C, H, W)`` → ``(x_local, x_global)`` (``None`` for an empty part); tuples pass through."""
        if isinstance(x, (tuple, list)):
            return x[0], x[1]
        check_channels(x, self.in_cl + self.in_cg)
        return (x[:, :self.in_cl] if self.in_cl else None), (x[:, self.in_cl:] if self.in_cg else None)

    def forward(self, x: Tensor | tuple[Tensor | None, Tensor | None]) -> tuple[Tensor | None, Tensor | None]:
        x_l, x_g = self.split(x)
        y_l = _add(self.conv_l2l(x_l) if self.conv_l2l is not None else None,
                   self.conv_g2l(x_g) if self.conv_g2l is not None else None)
        y_g = _add(self.conv_l2g(x_l) if self.conv_l2g is not None else None,
                   self.conv_g2g(x_g) if self.conv_g2g is not None else None)
        return y_l, y_g


def _add(a: Tensor | None, b: Tensor | None) -> Tensor | None:
    if a is None:
        return b
    return a if b is None else a + b


class FourierBlock(nn.Module):
    """FreDSNet's Fourier block: ``(B, C, H, W) -> (B, C, H, W)``.

    ``y_l, y_g = FFC(x)``; ``out_l = act(BN(y_l)) + x_l``; ``out_g = act(BN(y_g)) + x_g``;
    returns ``cat([out_l, out_g], 1)`` (local channels first). FreDSNet uses ``ratio=0.5``
    and PReLU. Keyword arguments go to :class:`FFC` (``spectral``, ``padding``, ``camera``,
    ``conv_layer``, ``fft_norm``, ``spectrum_layout``, ``bias``).
    """

    def __init__(self, channels: int, *, ratio: float = 0.5, activation: Activation = "prelu",
                 residual: bool = True, **ffc_kwargs: Any) -> None:
        super().__init__()
        self.ffc = FFC(channels, channels, 3, ratio, ratio, activation=activation, **ffc_kwargs)
        cl, cg = self.ffc.out_cl, self.ffc.out_cg
        self.norm_l = nn.BatchNorm2d(cl) if cl else None
        self.act_l = make_activation(activation, cl) if cl else None
        self.norm_g = nn.BatchNorm2d(cg) if cg else None
        self.act_g = make_activation(activation, cg) if cg else None
        self.residual = residual

    def forward(self, x: Tensor) -> Tensor:
        x_l, x_g = self.ffc.split(x)
        y_l, y_g = self.ffc((x_l, x_g))
        parts = []
        for y, res, norm, act in ((y_l, x_l, self.norm_l, self.act_l), (y_g, x_g, self.norm_g, self.act_g)):
            if y is not None:
                y = act(norm(y))
                parts.append(y + res if self.residual else y)
        return torch.cat(parts, dim=1) if len(parts) > 1 else parts[0]
