"""DINOv2 and DINOv3 vision transformers in plain PyTorch, with the parameter names of DINOv2 / timm.

Architecture (Oquab et al., "DINOv2", TMLR 2024, and its ``*_reg`` variants of Darcet et al., "Vision Transformers
Need Registers", ICLR 2024; Siméoni et al., "DINOv3", arXiv:2508.10104; the ``dinov2`` code that Depth-Anything-V2
ships, facebookresearch/dinov3, timm's ``vit_*_patch14_dinov2`` / ``vit_*_patch14_reg4_dinov2`` /
``vit_*_patch16_dinov3``)::

    image (B, 3, H, W), ImageNet-normalised, H and W multiples of the patch size p (DINOv2 14, DINOv3 16)
    patch_embed.proj   Conv2d(3, D, p, stride p) -> (B, h*w, D) tokens, row-major (h = H/p, w = W/p)
    tokens             [cls_token, register_tokens (R), patches]  -> (B, 1 + R + h*w, D)
      learned ("DINOv2") pos_embed (1, 1 + g*g, D), resampled to h x w, is added to [cls, patches] before the
                         registers are inserted (registers get no position; g = img_size / p)
      "rope" (DINOv3)    no pos_embed: every attention rotates the patch tokens' q and k (:mod:`.rope`)
    blocks.i           x = x + ls1(attn(norm1(x)));  x = x + ls2(mlp(norm2(x)))   (LayerNorm, eps ``norm_eps``)
                       attn: qkv Linear(D, 3D), softmax(q k^T / sqrt(D/heads)) v, proj Linear(D, D);
                       DINOv3 masks the k third of the qkv bias to zero (``mask_k_bias``)
                       mlp: fc1 Linear(D, F), GELU (erf), fc2 Linear(F, D)  — or SwiGLU: fc1 (D, 2F),
                       silu(x1) * x2, fc2 (F, D)
    norm               final LayerNorm, applied to every intermediate output that is returned

Sizes. DINOv2 (:data:`VIT_SIZES`, patch 14, 0 or 4 registers, LayerNorm eps 1e-6): ``vits`` 384/12/6,
``vitb`` 768/12/12, ``vitl`` 1024/24/16, ``vitg`` 1536/40/24 (SwiGLU). DINOv3 (:data:`DINOV3_SIZES`, the names of
facebookresearch/dinov3's ``hub/backbones.py``; patch 16, RoPE base 100, 4 registers ("storage tokens"), LayerNorm
eps 1e-5, qkv bias with a masked k part): ``vits16`` 384/12/6, ``vits16plus`` 384/12/6 (SwiGLU, ratio 6),
``vitb16`` 768/12/12, ``vitl16`` 1024/24/16, ``vitl16plus`` 1024/24/16 (SwiGLU, 6), ``vith16plus`` 1280/32/20
(SwiGLU, 6). The DINOv3 7B (4096 wide, untied class-token norms) is not provided.

The learned position embedding is resampled to the token grid exactly as the implementation whose weights are loaded
does it (``pos_interp``), since the references differ in their last digits:

* ``"dinov2"`` (the DINOv2 / Depth-Anything-V2 code): bicubic with ``scale_factor = (h + 0.1) / g`` (and ``w``),
  no anti-aliasing; unchanged when ``h * w == g * g`` and ``H == W``.
* ``"dinov2_reg"`` (the DINOv2 code for its ``*_reg`` models, which set ``interpolate_offset=0`` and
  ``interpolate_antialias=True``; transformers' ``Dinov2WithRegistersModel``): bicubic to ``size = (h, w)`` with
  anti-aliasing; same early exit as ``"dinov2"``.
* ``"hf"`` (transformers' ``Dinov2Model``): bicubic to ``size = (h, w)``, no anti-aliasing; same early exit.
* ``"timm"`` (``resample_abs_pos_embed``): bicubic to ``size = (h, w)`` with ``antialias=True``; unchanged when
  ``(h, w) == (g, g)``.

A RoPE model (DINOv3) has no table to resample: ``pos_interp`` is unused; timm, transformers and the official code
compute the same RoPE (their float32 periods differ in the last bits; the official checkpoint stores its own).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .rope import RopeEmbedding, apply_rope

#: DINOv2: name -> (embed_dim, depth, num_heads, ffn)
VIT_SIZES = {"vits": (384, 12, 6, "mlp"), "vitb": (768, 12, 12, "mlp"), "vitl": (1024, 24, 16, "mlp"),
             "vitg": (1536, 40, 24, "swiglu")}
#: DINOv3 (facebookresearch/dinov3 ``hub/backbones.py``): name -> (embed_dim, depth, num_heads, ffn, mlp_ratio)
DINOV3_SIZES = {"vits16": (384, 12, 6, "mlp", 4.0), "vits16plus": (384, 12, 6, "swiglu", 6.0),
                "vitb16": (768, 12, 12, "mlp", 4.0), "vitl16": (1024, 24, 16, "mlp", 4.0),
                "vitl16plus": (1024, 24, 16, "swiglu", 6.0), "vith16plus": (1280, 32, 20, "swiglu", 6.0)}
POS_INTERP = ("dinov2", "dinov2_reg", "hf", "timm")
POS_EMBED = ("learned", "rope")
#: the architecture settings of each family (what :class:`VisionTransformer` uses for an argument left at ``None``)
FAMILY_DEFAULTS = {
    "dinov2": {"patch_size": 14, "img_size": 518, "mlp_ratio": 4.0, "pos_embed": "learned", "num_registers": 0,
               "qkv_bias": True, "mask_k_bias": False, "norm_eps": 1e-6, "layer_scale": 1.0},
    "dinov3": {"patch_size": 16, "img_size": 224, "mlp_ratio": 4.0, "pos_embed": "rope", "num_registers": 4,
               "qkv_bias": True, "mask_k_bias": True, "norm_eps": 1e-5, "layer_scale": 1e-5},
}

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
    elif mode in ("timm", "dinov2_reg"):
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
    """Multi-head self-attention with a fused ``qkv`` projection (DINOv2 / DINOv3 / timm layout).

    ``mask_k_bias``: the k third of the qkv bias is multiplied by 0 (DINOv3's ``LinearKMaskedBias``; it stays a
    parameter so that the published ``qkv.bias`` loads as it is). ``rope``: ``(sin, cos)`` of the patch tokens,
    which are the last ``sin.shape[0]`` tokens."""

    def __init__(self, dim: int, num_heads: int, qkv_bias: bool = True, mask_k_bias: bool = False) -> None:
        super().__init__()
        if dim % num_heads:
            raise ValueError(f"ViT: embed_dim {dim} is not divisible by num_heads {num_heads}")
        self.num_heads = int(num_heads)
        self.qkv = nn.Linear(dim, 3 * dim, bias=qkv_bias)
        self.proj = nn.Linear(dim, dim)
        self.mask_k_bias = bool(mask_k_bias and qkv_bias)
        if self.mask_k_bias:
            mask = torch.ones(3 * dim)
            mask[dim:2 * dim] = 0
            self.register_buffer("bias_mask", mask, persistent=False)

    def forward(self, x: Tensor, rope: tuple[Tensor, Tensor] | None = None) -> Tensor:
        b, n, c = x.shape
        if self.mask_k_bias:
            qkv = F.linear(x, self.qkv.weight, self.qkv.bias * self.bias_mask.to(self.qkv.bias.dtype))
        else:
            qkv = self.qkv(x)
        qkv = qkv.reshape(b, n, 3, self.num_heads, c // self.num_heads).permute(2, 0, 3, 1, 4)
        q, k, v = qkv[0], qkv[1], qkv[2]
        if rope is not None:
            q, k = apply_rope(q, rope[0], rope[1]), apply_rope(k, rope[0], rope[1])
        y = F.scaled_dot_product_attention(q, k, v)
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


def swiglu_hidden(hidden: int) -> int:
    """SwiGLU width of a nominal ``hidden = int(D * mlp_ratio)``: ``8 * ceil(int(2/3 * hidden) / 8)`` (DINOv2's
    ``SwiGLUFFNFused``, DINOv3's ``SwiGLUFFN(align_to=8)``)."""
    return (int(hidden * 2 / 3) + 7) // 8 * 8


class SwiGLU(nn.Module):
    """``fc2(silu(x1) * x2)`` with ``(x1, x2) = fc1(x).chunk(2)`` (DINOv2's ``SwiGLUFFNFused``, timm's
    ``SwiGLUPacked``; DINOv3's ``w1``/``w2``/``w3`` and timm's ``fc1_g``/``fc1_x``/``fc2`` are packed into
    ``fc1``/``fc2`` by the converters) with hidden width ``F``."""

    def __init__(self, dim: int, hidden: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(dim, 2 * hidden)
        self.act = nn.SiLU()
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: Tensor) -> Tensor:
        x1, x2 = self.fc1(x).chunk(2, dim=-1)
        return self.fc2(self.act(x1) * x2)


class Block(nn.Module):
    """Pre-norm transformer block with layer scale; ``hidden``: the FFN width ``F``."""

    def __init__(self, dim: int, num_heads: int, hidden: int, ffn: str = "mlp", layer_scale: float = 1.0,
                 eps: float = 1e-6, qkv_bias: bool = True, mask_k_bias: bool = False) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=eps)
        self.attn = Attention(dim, num_heads, qkv_bias=qkv_bias, mask_k_bias=mask_k_bias)
        self.ls1 = LayerScale(dim, layer_scale)
        self.norm2 = nn.LayerNorm(dim, eps=eps)
        if ffn == "mlp":
            self.mlp: nn.Module = Mlp(dim, hidden)
        elif ffn == "swiglu":
            self.mlp = SwiGLU(dim, hidden)
        else:
            raise ValueError(f"ViT: ffn must be 'mlp' or 'swiglu', got {ffn!r}")
        self.ls2 = LayerScale(dim, layer_scale)

    def forward(self, x: Tensor, rope: tuple[Tensor, Tensor] | None = None) -> Tensor:
        x = x + self.ls1(self.attn(self.norm1(x), rope))
        return x + self.ls2(self.mlp(self.norm2(x)))


def _resolve(size: str | None, family: str | None, given: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    """The family and full architecture settings: explicit arguments > ``size`` > the family's defaults."""
    preset: dict[str, Any] = {}
    if size is not None:
        if size in VIT_SIZES:
            d, n, h, f = VIT_SIZES[size]
            preset, fam = {"embed_dim": d, "depth": n, "num_heads": h, "ffn": f}, "dinov2"
        elif size in DINOV3_SIZES:
            d, n, h, f, r = DINOV3_SIZES[size]
            preset, fam = {"embed_dim": d, "depth": n, "num_heads": h, "ffn": f, "mlp_ratio": r}, "dinov3"
        else:
            raise ValueError(f"ViT: unknown size {size!r}; choose one of {sorted(VIT_SIZES)} (DINOv2) or "
                             f"{sorted(DINOV3_SIZES)} (DINOv3), or give embed_dim/depth/num_heads")
        if family is not None and family != fam:
            raise ValueError(f"ViT: size {size!r} is a {fam} size, not {family}")
        family = fam
    family = family or "dinov2"
    if family not in FAMILY_DEFAULTS:
        raise ValueError(f"ViT: family must be one of {sorted(FAMILY_DEFAULTS)}, got {family!r}")
    cfg = {**FAMILY_DEFAULTS[family], "ffn": "mlp", **preset}
    cfg.update({k: v for k, v in given.items() if v is not None})
    return family, cfg


class VisionTransformer(nn.Module):
    """DINOv2 / DINOv3 ViT (see the module docstring). Input: ImageNet-normalised ``(B, 3, H, W)``, sides multiples
    of ``patch_size``; :meth:`intermediate` returns normalised token maps of chosen blocks.

    Every architecture argument left at ``None`` comes from ``size``, else from the ``family``'s defaults
    (:data:`FAMILY_DEFAULTS`).

    Args:
        size: a key of :data:`VIT_SIZES` (DINOv2) or :data:`DINOV3_SIZES` (DINOv3; sets ``family="dinov3"``), or
            ``None`` with ``embed_dim``/``depth``/``num_heads`` given (tiny test configurations).
        family: ``"dinov2"`` (default) or ``"dinov3"``.
        ffn: ``"mlp"`` or ``"swiglu"``; ``mlp_ratio``: nominal FFN width ``int(D * mlp_ratio)`` (SwiGLU: reduced by
            :func:`swiglu_hidden`); ``ffn_hidden``: the FFN width ``F`` itself (overrides ``mlp_ratio``).
        patch_size: 14 (DINOv2) or 16 (DINOv3).
        img_size: the pre-training size setting the learned position-embedding grid (518 -> 37 x 37).
        pos_embed: ``"learned"`` (DINOv2) or ``"rope"`` (DINOv3).
        num_registers: register tokens after the class token (DINOv2 ``*_reg``: 4; DINOv3: 4).
        qkv_bias, mask_k_bias: a qkv bias; its k third multiplied by 0 (DINOv3).
        norm_eps: LayerNorm epsilon (DINOv2 1e-6, DINOv3 1e-5).
        layer_scale: initial layer-scale value (DINOv2 1.0, DINOv3 1e-5; loaded weights replace it).
        pos_interp: ``"dinov2"``, ``"dinov2_reg"``, ``"hf"`` or ``"timm"`` (how a learned ``pos_embed`` is
            resampled).
        rope_base, rope_rescale: RoPE period base and training-time coordinate rescaling (:mod:`.rope`).
    """

    def __init__(self, size: str | None = "vits", *, family: str | None = None, embed_dim: int | None = None,
                 depth: int | None = None, num_heads: int | None = None, ffn: str | None = None,
                 patch_size: int | None = None, img_size: int | None = None, mlp_ratio: float | None = None,
                 ffn_hidden: int | None = None, pos_embed: str | None = None, num_registers: int | None = None,
                 qkv_bias: bool | None = None, mask_k_bias: bool | None = None, norm_eps: float | None = None,
                 layer_scale: float | None = None, pos_interp: str = "dinov2", rope_base: float = 100.0,
                 rope_rescale: float | None = None) -> None:
        super().__init__()
        family, cfg = _resolve(size, family, {
            "embed_dim": embed_dim, "depth": depth, "num_heads": num_heads, "ffn": ffn, "patch_size": patch_size,
            "img_size": img_size, "mlp_ratio": mlp_ratio, "pos_embed": pos_embed, "num_registers": num_registers,
            "qkv_bias": qkv_bias, "mask_k_bias": mask_k_bias, "norm_eps": norm_eps, "layer_scale": layer_scale})
        if not (cfg.get("embed_dim") and cfg.get("depth") and cfg.get("num_heads")):
            raise ValueError("ViT: give size= or all of embed_dim=, depth=, num_heads=")
        if pos_interp not in POS_INTERP:
            raise ValueError(f"ViT: pos_interp must be one of {POS_INTERP}, got {pos_interp!r}")
        if cfg["pos_embed"] not in POS_EMBED:
            raise ValueError(f"ViT: pos_embed must be one of {POS_EMBED}, got {cfg['pos_embed']!r}")
        self.family = family
        self.embed_dim, self.depth, self.num_heads = int(cfg["embed_dim"]), int(cfg["depth"]), int(cfg["num_heads"])
        self.patch_size, self.pos_interp = int(cfg["patch_size"]), pos_interp
        self.num_registers = int(cfg["num_registers"])
        self.num_prefix_tokens = 1 + self.num_registers
        self.use_rope = cfg["pos_embed"] == "rope"
        self.patch_embed = PatchEmbed(self.patch_size, self.embed_dim)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, self.embed_dim))
        self.register_tokens = (nn.Parameter(torch.zeros(1, self.num_registers, self.embed_dim))
                                if self.num_registers else None)
        if self.use_rope:
            if self.embed_dim % (4 * self.num_heads):
                raise ValueError(f"ViT: RoPE needs embed_dim ({self.embed_dim}) divisible by 4 * num_heads "
                                 f"({4 * self.num_heads})")
            self.pos_embed = None
            self.rope = RopeEmbedding(self.embed_dim // self.num_heads, rope_base, rope_rescale)
        else:
            img = int(cfg["img_size"])
            if img % self.patch_size:
                raise ValueError(f"ViT: img_size {img} is not a multiple of patch_size {self.patch_size}")
            grid = img // self.patch_size
            self.pos_embed = nn.Parameter(torch.zeros(1, 1 + grid * grid, self.embed_dim))
            self.rope = None
            nn.init.trunc_normal_(self.pos_embed, std=0.02)
        if ffn_hidden is not None:
            hidden = int(ffn_hidden)
        else:
            hidden = int(self.embed_dim * float(cfg["mlp_ratio"]))
            hidden = swiglu_hidden(hidden) if cfg["ffn"] == "swiglu" else hidden
        self.blocks = nn.ModuleList(
            Block(self.embed_dim, self.num_heads, hidden, cfg["ffn"], float(cfg["layer_scale"]),
                  float(cfg["norm_eps"]), bool(cfg["qkv_bias"]), bool(cfg["mask_k_bias"]))
            for _ in range(self.depth))
        self.norm = nn.LayerNorm(self.embed_dim, eps=float(cfg["norm_eps"]))
        nn.init.normal_(self.cls_token, std=1e-6 if family == "dinov2" else 0.02)
        if self.register_tokens is not None:
            nn.init.normal_(self.register_tokens, std=1e-6 if family == "dinov2" else 0.02)

    def tokens(self, x: Tensor) -> tuple[Tensor, tuple[Tensor, Tensor] | None]:
        """``(B, 3, H, W) -> (B, 1 + R + h*w, D)``: class token, register tokens and patch tokens (with the learned
        position embedding), and the RoPE ``(sin, cos)`` of the patch grid (``None`` without RoPE)."""
        h, w = x.shape[-2], x.shape[-1]
        t = self.patch_embed(x)
        cls = self.cls_token.expand(t.shape[0], -1, -1)
        rope = None
        if self.pos_embed is not None:
            t = torch.cat([cls, t], dim=1) + resample_pos_embed(self.pos_embed, h, w, self.patch_size,
                                                                self.pos_interp)
            if self.register_tokens is not None:
                t = torch.cat([t[:, :1], self.register_tokens.expand(t.shape[0], -1, -1), t[:, 1:]], dim=1)
        else:
            parts = [cls] if self.register_tokens is None else [cls, self.register_tokens.expand(t.shape[0], -1, -1)]
            t = torch.cat(parts + [t], dim=1)
        if self.rope is not None:
            rope = self.rope(h // self.patch_size, w // self.patch_size)
        return t, rope

    def intermediate(self, x: Tensor, indices: Sequence[int]) -> list[tuple[Tensor, Tensor]]:
        """``[(patch tokens (B, h*w, D), class token (B, D)), ...]`` after block ``i`` for ``i`` in ``indices``,
        each through the final ``norm`` (DINOv2's / DINOv3's ``get_intermediate_layers(..., norm=True)``; register
        tokens are dropped). Blocks after the last index are not run."""
        wanted = sorted({int(i) for i in indices})
        if not wanted or wanted[0] < 0 or wanted[-1] >= self.depth:
            raise ValueError(f"ViT: block indices must lie in 0..{self.depth - 1}, got {list(indices)}")
        t, rope = self.tokens(x)
        found = {}
        for i, block in enumerate(self.blocks):
            if i > wanted[-1]:
                break
            t = block(t, rope)
            if i in wanted:
                found[i] = t
        out = []
        p = self.num_prefix_tokens
        for i in indices:
            n = self.norm(found[int(i)])
            out.append((n[:, p:], n[:, 0]))
        return out

    def forward(self, x: Tensor) -> Tensor:
        """All tokens after the last block and the final norm: ``(B, 1 + R + h*w, D)``, class token first, then the
        registers (timm's ``forward_features``, transformers' ``last_hidden_state``)."""
        t, rope = self.tokens(x)
        for block in self.blocks:
            t = block(t, rope)
        return self.norm(t)


__all__ = ["DINOV3_SIZES", "FAMILY_DEFAULTS", "POS_EMBED", "POS_INTERP", "VIT_SIZES", "VisionTransformer",
           "resample_pos_embed", "swiglu_hidden"]
