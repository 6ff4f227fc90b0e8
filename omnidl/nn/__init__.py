"""Distortion-aware layers: ProjectedConv2d (offsets from any camera), its fast fixed-offset backend, conversion."""
from .offsets import compute_offsets, compute_sampling
from .sampling import SamplingPlan, build_plan, deform_conv2d_reference, fixed_offset_conv2d
from .projected_conv import ProjectedConv2d, clear_plan_cache, plan_cache_info
from .convert import convert_conv2d

__all__ = ["ProjectedConv2d", "compute_offsets", "compute_sampling", "SamplingPlan", "build_plan",
           "fixed_offset_conv2d", "deform_conv2d_reference", "clear_plan_cache", "plan_cache_info",
           "convert_conv2d"]

# layers of the FFC / W-conv helper (omnidl/nn/padding.py, ffc.py, wconv.py)
from .padding import CircularConv2d, PanoramaPad2d, make_conv2d, pad_panorama
from .ffc import FFC, FourierBlock, FourierUnit, SpectralTransform, split_channels
from .wconv import ConvNormAct, WConv, make_activation

__all__ += ["CircularConv2d", "PanoramaPad2d", "make_conv2d", "pad_panorama", "FFC", "FourierBlock", "FourierUnit",
            "SpectralTransform", "split_channels", "ConvNormAct", "WConv", "make_activation"]

from .fusion import UpsampleSum, blocked_conv, interpolation_matrix, upsample_sum

__all__ += ["UpsampleSum", "blocked_conv", "interpolation_matrix", "upsample_sum"]

from . import tap_projection

__all__ += ["tap_projection"]
