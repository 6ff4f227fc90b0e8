"""Distortion-aware layers: ProjectedConv2d (offsets from any camera), panorama padding, FFC and W-conv blocks."""
from omnidl.ops import fixed_offset_conv2d

from .offsets import compute_offsets, compute_sampling
from .sampling import deform_conv2d_reference, sample_positions
from .projected_conv import ProjectedConv2d, clear_sampling_cache, sampling_cache_info
from .convert import convert_conv2d
from .padding import CircularConv2d, PanoramaPad2d, make_conv2d, pad_panorama
from .ffc import FFC, FourierBlock, FourierUnit, SpectralTransform, split_channels
from .wconv import ConvNormAct, WConv, make_activation

__all__ = ["ProjectedConv2d", "compute_offsets", "compute_sampling", "sample_positions", "fixed_offset_conv2d",
           "deform_conv2d_reference", "clear_sampling_cache", "sampling_cache_info", "convert_conv2d",
           "CircularConv2d", "PanoramaPad2d", "make_conv2d", "pad_panorama", "FFC", "FourierBlock", "FourierUnit",
           "SpectralTransform", "split_channels", "ConvNormAct", "WConv", "make_activation"]
