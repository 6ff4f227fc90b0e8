"""Foundation models in plain PyTorch: DINOv2 (with or without registers) and DINOv3 ViTs (:mod:`.vit`, RoPE in
:mod:`.rope`), Depth-Anything-V2 (:mod:`.dpt`, registered as ``depth_anything_v2``), the ViT as FreDSNet's /
HorizonNet's encoder (:mod:`.encoder`, ``encoder="dinov2_s"``, ``"dinov2_s_reg"``, ``"dinov3_s"``, ...) and the
readers/converters of the published checkpoints (:mod:`.convert`). See ``docs/foundation.md``.

Nothing here imports timm or transformers: they are only the test oracles of the parity tests. Reading a
``.safetensors`` file needs the ``safetensors`` package (the ``foundation`` extra).
"""
from .dpt import DA2_CONFIGS, DepthAnythingV2, depth_anything_v2
from .encoder import ENCODERS, ViTFeatures, build_encoder
from .rope import RopeEmbedding
from .vit import DINOV3_SIZES, VIT_SIZES, VisionTransformer

__all__ = ["DA2_CONFIGS", "DINOV3_SIZES", "ENCODERS", "VIT_SIZES", "DepthAnythingV2", "RopeEmbedding", "ViTFeatures",
           "VisionTransformer", "build_encoder", "depth_anything_v2"]
