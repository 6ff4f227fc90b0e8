"""The input check every model runs first: an RGB batch whose sides the network's stride divides.

Each model module calls ``torch.fx.wrap("check_image")`` so that ``torch.fx.symbolic_trace`` records the check as
one call (it reads the input's shape, which a symbolic trace cannot branch on) instead of tracing into it.
"""
from __future__ import annotations

from torch import Tensor


def check_image(x: Tensor, model: str, multiple: int = 1) -> None:
    """Raise a ``ValueError`` unless ``x`` is a floating-point ``(B, 3, H, W)`` with ``H`` and ``W`` multiples of
    ``multiple``, naming the model, the shape and a size that would do. Integer images (``uint8`` 0..255) are
    refused: normalising them in their own dtype would wrap around (convert with
    :func:`omnidl.data.readers.image_to_float` first)."""
    if not x.is_floating_point():
        raise ValueError(f"{model} expects a floating-point image in [0, 1], got dtype {x.dtype}; convert it first "
                         "(omnidl.data.readers.image_to_float: uint8 / 255, uint16 / 65535)")
    if x.dim() != 4 or x.shape[1] != 3:
        raise ValueError(f"{model} expects RGB images of shape (B, 3, H, W), got {tuple(x.shape)}")
    h, w = int(x.shape[-2]), int(x.shape[-1])
    if h % multiple or w % multiple:
        raise ValueError(f"{model}: input size {h}x{w} (HxW) is not divisible by the network stride {multiple}; "
                         f"resize to e.g. {max(1, round(h / multiple)) * multiple}x"
                         f"{max(1, round(w / multiple)) * multiple}")
