"""Foundation models in plain PyTorch: a DINOv2 ViT (:mod:`.vit`), Depth-Anything-V2 (:mod:`.dpt`, registered as
``depth_anything_v2``), the ViT as FreDSNet's / HorizonNet's encoder (:mod:`.encoder`, ``encoder="dinov2_s"``) and
the readers/converters of the published checkpoints (:mod:`.convert`). See ``docs/foundation.md``.

Nothing here imports timm or transformers: they are only the test oracles of the parity tests. Reading a
``.safetensors`` file needs the ``safetensors`` package (the ``foundation`` extra).
"""
from .dpt import DA2_CONFIGS, DepthAnythingV2, depth_anything_v2
from .encoder import ENCODERS, ViTFeatures, build_encoder
from .vit import VIT_SIZES, VisionTransformer

__all__ = ["DA2_CONFIGS", "DepthAnythingV2", "depth_anything_v2", "ENCODERS", "ViTFeatures", "build_encoder",
           "VIT_SIZES", "VisionTransformer"]
