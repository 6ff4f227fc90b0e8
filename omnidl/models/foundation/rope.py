"""DINOv3's axial rotary position embedding (RoPE) in plain PyTorch.

As ``RopePositionEmbedding`` of facebookresearch/dinov3 (``dinov3/layers/rope_position_encoding.py``; timm's
``RotaryEmbeddingDinoV3``, transformers' ``DINOv3ViTRopePositionEmbedding``), with ``normalize_coords="separate"``,
the setting of every published DINOv3 ViT::

    patch grid h x w (row-major tokens, h = H/p, w = W/p)
    coordinates  y_i = 2 (i + 0.5) / h - 1,  x_j = 2 (j + 0.5) / w - 1     (patch centres in [-1, 1], each axis
                 normalised by its own length: the same coordinates for a 14 x 14 and a 14 x 56 grid's ends)
    periods      T_k = base ** (4k / d),  k = 0 .. d/4 - 1                  (d: head dim, base 100)
    angles       [2 pi y / T, 2 pi x / T] (d/2 values), tiled twice -> (h*w, d)
    q, k         patch tokens only: t * cos + rotate_half(t) * sin,  rotate_half([a, b]) = [-b, a]
                 (the class and register tokens are not rotated)

The angles are computed in float32 and the rotation is applied in float32 (the official code's "fp32" RoPE dtype
of the published models); the result is cast back to the dtype of ``q``/``k``.

``periods`` is a persistent buffer as in the official code, so that an official checkpoint's stored periods are
used as they are (timm notes that they were saved rounded to bfloat16); converters from timm / transformers, which
recompute them, fill in ``base ** (4k / d)``.

Training-time augmentation: the official models were pre-trained with ``rescale_coords=2`` (coordinates multiplied by
one log-uniform factor in [1/2, 2] per forward in ``train()`` mode; transformers' ``pos_embed_rescale=2.0`` does the
same), timm applies none. omnidl applies none by default (``rescale=None``: the same positions in train and eval);
``rescale=2.0`` restores the pre-training behaviour in ``train()`` mode. Evaluation never augments.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor, nn

torch.fx.wrap("rope_sin_cos")


def rope_periods(head_dim: int, base: float = 100.0) -> Tensor:
    """``(head_dim / 4,)`` float32 periods ``base ** (2k / (head_dim / 2))`` (the official / timm formula)."""
    if head_dim % 4:
        raise ValueError(f"RoPE: the head dimension must be a multiple of 4, got {head_dim}")
    n = head_dim // 4
    return base ** (2 * torch.arange(n, dtype=torch.float32) / (head_dim // 2))


def rope_sin_cos(periods: Tensor, height: int, width: int, rescale: float | None = None) -> tuple[Tensor, Tensor]:
    """``(sin, cos)``, each ``(height * width, 4 * len(periods))`` float32, for a ``height x width`` patch grid
    (row-major); ``rescale``: multiply the coordinates by a random log-uniform factor in ``[1/rescale, rescale]``."""
    dd = {"device": periods.device, "dtype": torch.float32}
    ys = torch.arange(0.5, height, **dd) / height
    xs = torch.arange(0.5, width, **dd) / width
    coords = torch.stack(torch.meshgrid(ys, xs, indexing="ij"), dim=-1).flatten(0, 1)   # (h*w, 2) in [0, 1]
    coords = 2.0 * coords - 1.0
    if rescale is not None:
        r = math.log(rescale)
        coords = coords * torch.empty(1, **dd).uniform_(-r, r).exp()
    angles = 2 * math.pi * coords[:, :, None] / periods.to(torch.float32)[None, None, :]   # (h*w, 2, d/4)
    angles = angles.flatten(1, 2).tile(2)                                                  # (h*w, d)
    return torch.sin(angles), torch.cos(angles)


def rotate_half(x: Tensor) -> Tensor:
    """``[a, b] -> [-b, a]`` on the last dimension (halves)."""
    a, b = x.chunk(2, dim=-1)
    return torch.cat([-b, a], dim=-1)


def apply_rope(x: Tensor, sin: Tensor, cos: Tensor) -> Tensor:
    """Rotate the last ``sin.shape[0]`` tokens of ``x (B, heads, N, d)``; the leading (class / register) tokens
    stay as they are. Computed in float32, returned in ``x.dtype``."""
    prefix = x.shape[-2] - sin.shape[-2]
    head, tail = x[:, :, :prefix], x[:, :, prefix:]
    t = tail.to(torch.float32)
    t = t * cos + rotate_half(t) * sin
    return torch.cat([head, t.to(x.dtype)], dim=-2)


class RopeEmbedding(nn.Module):
    """The RoPE table of a ViT (module docstring): ``forward(height, width) -> (sin, cos)``, each
    ``(height * width, head_dim)`` float32.

    Args:
        head_dim: per-head width ``d`` (a multiple of 4).
        base: period base (100 for DINOv3).
        rescale: training-time coordinate rescaling factor, or ``None`` (default: none).
    """

    def __init__(self, head_dim: int, base: float = 100.0, rescale: float | None = None) -> None:
        super().__init__()
        if rescale is not None and not rescale >= 1:
            raise ValueError(f"RoPE: rescale must be >= 1 or None, got {rescale!r}")
        self.head_dim, self.base, self.rescale = int(head_dim), float(base), rescale
        self.register_buffer("periods", rope_periods(self.head_dim, self.base))

    def forward(self, height: int, width: int) -> tuple[Tensor, Tensor]:
        return rope_sin_cos(self.periods, height, width, self.rescale if self.training else None)

    def extra_repr(self) -> str:
        return f"head_dim={self.head_dim}, base={self.base:g}, rescale={self.rescale}"


__all__ = ["RopeEmbedding", "apply_rope", "rope_periods", "rope_sin_cos", "rotate_half"]
