"""A DINOv2 vision transformer in plain PyTorch, with the parameter names of DINOv2 / timm.

Architecture (Oquab et al., "DINOv2", TMLR 2024; the ``dinov2`` code that Depth-Anything-V2 ships, and timm's
``vit_*_patch14_dinov2``)::

    image (B, 3, H, W), ImageNet-normalised, H and W multiples of the patch size p (14)
    patch_embed.proj   Conv2d(3, D, p, stride p) -> (B, h*w, D) tokens, row-major (h = H/p, w = W/p)
    cls_token          (1, 1, D) prepended;  pos_embed (1, 1 + g*g, D) added (g = img_size / p, resampled to h x w)
    blocks.i           x = x + ls1(attn(norm1(x)));  x = x + ls2(mlp(norm2(x)))   (LayerNorm eps 1e-6)
                       attn: qkv Linear(D, 3D), softmax(q k^T / sqrt(D/heads)) v, proj Linear(D, D)
                       mlp: fc1 Linear(D, 4D), GELU (erf), fc2 Linear(4D, D)  — or SwiGLU (ViT-g): fc1 (D, 2F),
                       silu(x1) * x2, fc2 (F, D)
    norm               final LayerNorm, applied to every intermediate output that is returned

Sizes (:data:`VIT_SIZES`): ``vits`` 384/12/6, ``vitb`` 768/12/12, ``vitl`` 1024/24/16, ``vitg`` 1536/40/24 (SwiGLU).

The position embedding is resampled to the token grid exactly as the implementation whose weights are loaded does it
(``pos_interp``), since the three references differ in their last digits:

* ``"dinov2"`` (the DINOv2 / Depth-Anything-V2 code): bicubic with ``scale_factor = (h + 0.1) / g`` (and ``w``),
  no anti-aliasing; unchanged when ``h * w == g * g`` and ``H == W``.
* ``"hf"`` (transformers' ``Dinov2Model``): bicubic to ``size = (h, w)``, no anti-aliasing; same early exit.
* ``"timm"`` (``resample_abs_pos_embed``): bicubic to ``size = (h, w)`` with ``antialias=True``; unchanged when
  ``(h, w) == (g, g)``.

Register tokens (``*_reg4_dinov2``) and DINOv3 (RoPE) are not implemented; their checkpoints are refused by name in
:mod:`omnidl.models.foundation.convert`.
"""
from __future__ import annotations

import math
from typing import Sequence

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

#: name -> (embed_dim, depth, num_heads, ffn)
VIT_SIZES = {"vits": (384, 12, 6, "mlp"), "vitb": (768, 12, 12, "mlp"), "vitl": (1024, 24, 16, "mlp"),
             "vitg": (1536, 40, 24, "swiglu")}
POS_INTERP = ("dinov2", "hf", "timm")

torch.fx.wrap("resample_pos_embed")


def resample_pos_embed(pos_embed: Tensor, height: int, width: int, patch: int, mode: str) -> Tensor:
    """``pos_embed (1, 1 + g*g, D)`` for an ``height x width`` input: ``(1, 1 + h*w, D)`` (``mode``: module doc)."""
    n = pos_embed.shape[1] - 1
    g = math.sqrt(n)
    gh, gw = height // patch, width // patch
    if mode == "timm":
        same = gh == int(g) and gw == int(g)
    else:
        same = gh * gw == n and height == width
    if same:
        return pos_embed
    dim = pos_embed.shape[-1]
    cls, grid = pos_embed[:, :1], pos_embed[:, 1:]
    dtype = grid.dtype
    work = torch.float32 if dtype in (torch.float16, torch.bfloat16) else dtype
    grid = grid.to(work).reshape(1, int(g), int(g), dim).permute(0, 3, 1, 2)
    if mode == "dinov2":
        grid = F.interpolate(grid, scale_factor=((gh + 0.1) / g, (gw + 0.1) / g), mode="bicubic", antialias=False)
    elif mode == "hf":
        grid = F.interpolate(grid, size=(gh, gw), mode="bicubic", align_corners=False)
    elif mode == "timm":
        grid = F.interpolate(grid, size=(gh, gw), mode="bicubic", antialias=True)
    else:
        raise ValueError(f"pos_interp must be one of {POS_INTERP}, got {mode!r}")
    grid = grid.permute(0, 2, 3, 1).reshape(1, gh * gw, dim).to(dtype)
    return torch.cat([cls, grid], dim=1)


class PatchEmbed(nn.Module):
    """``Conv2d(3, D, p, stride p)``: ``(B, 3, H, W) -> (B, H/p * W/p, D)``."""

    def __init__(self, patch_size: int, embed_dim: int, in_chans: int = 3) -> None:
        super().__init__()
        self.patch_size = int(patch_size)
        self.proj = nn.Conv2d(in_chans, embed_dim, self.patch_size, stride=self.patch_size)

    def forward(self, x: Tensor) -> Tensor:
        return self.proj(x).flatten(2).transpose(1, 2)


class Attention(nn.Module):
    """Multi-head self-attention with a fused ``qkv`` projection (DINOv2 / timm layout)."""

    def __init__(self, dim: int, num_heads: int, qkv_bias: bool = True) -> None:
        super().__init__()
        if dim % num_heads:
            raise ValueError(f"ViT: embed_dim {dim} is not divisible by num_heads {num_heads}")
        self.num_heads = int(num_heads)
        self.qkv = nn.Linear(dim, 3 * dim, bias=qkv_bias)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: Tensor) -> Tensor:
        b, n, c = x.shape
        qkv = self.qkv(x).reshape(b, n, 3, self.num_heads, c // self.num_heads).permute(2, 0, 3, 1, 4)
        y = F.scaled_dot_product_attention(qkv[0], qkv[1], qkv[2])
        return self.proj(y.transpose(1, 2).reshape(b, n, c))


class LayerScale(nn.Module):
    """``x * gamma`` (per channel)."""

    def __init__(self, dim: int, init: float = 1.0) -> None:
        super().__init__()
        self.gamma = nn.Parameter(torch.full((dim,), float(init)))

    def forward(self, x: Tensor) -> Tensor:
        return x * self.gamma


class Mlp(nn.Module):
    """``fc2(GELU(fc1(x)))``."""

    def __init__(self, dim: int, hidden: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: Tensor) -> Tensor:
        return self.fc2(self.act(self.fc1(x)))


class SwiGLU(nn.Module):
    """``fc2(silu(x1) * x2)`` with ``(x1, x2) = fc1(x).chunk(2)`` (DINOv2's ``SwiGLUFFNFused``, timm's
    ``SwiGLUPacked``); hidden width ``F = 8 * ceil((2/3 * 4D) / 8)`` as DINOv2."""

    def __init__(self, dim: int, hidden: int) -> None:
        super().__init__()
        hidden = (int(hidden * 2 / 3) + 7) // 8 * 8
        self.fc1 = nn.Linear(dim, 2 * hidden)
        self.act = nn.SiLU()
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: Tensor) -> Tensor:
        x1, x2 = self.fc1(x).chunk(2, dim=-1)
        return self.fc2(self.act(x1) * x2)


class Block(nn.Module):
    """Pre-norm transformer block with layer scale."""

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float = 4.0, ffn: str = "mlp",
                 layer_scale: float | None = 1.0, eps: float = 1e-6) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=eps)
        self.attn = Attention(dim, num_heads)
        self.ls1 = LayerScale(dim, layer_scale) if layer_scale is not None else nn.Identity()
        self.norm2 = nn.LayerNorm(dim, eps=eps)
        hidden = int(dim * mlp_ratio)
        if ffn == "mlp":
            self.mlp: nn.Module = Mlp(dim, hidden)
        elif ffn == "swiglu":
            self.mlp = SwiGLU(dim, hidden)
        else:
            raise ValueError(f"ViT: ffn must be 'mlp' or 'swiglu', got {ffn!r}")
        self.ls2 = LayerScale(dim, layer_scale) if layer_scale is not None else nn.Identity()

    def forward(self, x: Tensor) -> Tensor:
        x = x + self.ls1(self.attn(self.norm1(x)))
        return x + self.ls2(self.mlp(self.norm2(x)))


class VisionTransformer(nn.Module):
    """DINOv2 ViT (see the module docstring). Input: ImageNet-normalised ``(B, 3, H, W)``, sides multiples of
    ``patch_size``; :meth:`intermediate` returns normalised token maps of chosen blocks.

    Args:
        size: ``"vits"``/``"vitb"``/``"vitl"``/``"vitg"``, or ``None`` with ``embed_dim``/``depth``/``num_heads``
            given (tiny test configurations).
        patch_size: 14 for DINOv2.
        img_size: the pre-training size setting the position-embedding grid (518 -> 37 x 37).
        pos_interp: ``"dinov2"``, ``"hf"`` or ``"timm"`` (how ``pos_embed`` is resampled).
    """

    def __init__(self, size: str | None = "vits", *, embed_dim: int | None = None, depth: int | None = None,
                 num_heads: int | None = None, ffn: str | None = None, patch_size: int = 14, img_size: int = 518,
                 mlp_ratio: float = 4.0, pos_interp: str = "dinov2", layer_scale: float | None = 1.0) -> None:
        super().__init__()
        if size is not None:
            if size not in VIT_SIZES:
                raise ValueError(f"ViT: unknown size {size!r}; choose one of {sorted(VIT_SIZES)} or give "
                                 "embed_dim/depth/num_heads")
            d0, n0, h0, f0 = VIT_SIZES[size]
            embed_dim, depth, num_heads, ffn = embed_dim or d0, depth or n0, num_heads or h0, ffn or f0
        if not (embed_dim and depth and num_heads):
            raise ValueError("ViT: give size= or all of embed_dim=, depth=, num_heads=")
        if pos_interp not in POS_INTERP:
            raise ValueError(f"ViT: pos_interp must be one of {POS_INTERP}, got {pos_interp!r}")
        if img_size % patch_size:
            raise ValueError(f"ViT: img_size {img_size} is not a multiple of patch_size {patch_size}")
        self.embed_dim, self.depth, self.num_heads = int(embed_dim), int(depth), int(num_heads)
        self.patch_size, self.pos_interp = int(patch_size), pos_interp
        grid = img_size // patch_size
        self.patch_embed = PatchEmbed(patch_size, self.embed_dim)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, self.embed_dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, 1 + grid * grid, self.embed_dim))
        self.blocks = nn.ModuleList(Block(self.embed_dim, self.num_heads, mlp_ratio, ffn or "mlp", layer_scale)
                                    for _ in range(self.depth))
        self.norm = nn.LayerNorm(self.embed_dim, eps=1e-6)
        nn.init.trunc_normal_(self.pos_embed, std=0.02)
        nn.init.normal_(self.cls_token, std=1e-6)

    def tokens(self, x: Tensor) -> Tensor:
        """``(B, 3, H, W) -> (B, 1 + h*w, D)``: class token + patch tokens with position embedding."""
        h, w = x.shape[-2], x.shape[-1]
        t = self.patch_embed(x)
        t = torch.cat([self.cls_token.expand(t.shape[0], -1, -1), t], dim=1)
        return t + resample_pos_embed(self.pos_embed, h, w, self.patch_size, self.pos_interp)

    def intermediate(self, x: Tensor, indices: Sequence[int]) -> list[tuple[Tensor, Tensor]]:
        """``[(patch tokens (B, h*w, D), class token (B, D)), ...]`` after block ``i`` for ``i`` in ``indices``,
        each through the final ``norm`` (DINOv2's ``get_intermediate_layers(..., norm=True)``). Blocks after the
        last index are not run."""
        wanted = sorted({int(i) for i in indices})
        if not wanted or wanted[0] < 0 or wanted[-1] >= self.depth:
            raise ValueError(f"ViT: block indices must lie in 0..{self.depth - 1}, got {list(indices)}")
        t = self.tokens(x)
        found = {}
        for i, block in enumerate(self.blocks):
            if i > wanted[-1]:
                break
            t = block(t)
            if i in wanted:
                found[i] = t
        out = []
        for i in indices:
            n = self.norm(found[int(i)])
            out.append((n[:, 1:], n[:, 0]))
        return out

    def forward(self, x: Tensor) -> Tensor:
        """All tokens after the last block and the final norm: ``(B, 1 + h*w, D)`` (timm's ``forward_features``)."""
        t = self.tokens(x)
        for block in self.blocks:
            t = block(t)
        return self.norm(t)
