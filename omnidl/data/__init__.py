"""Datasets (real formats + synthetic), transforms, collation. Loaders are imported lazily by configs
(``_target_: omnidl.data.stanford2d3ds.Stanford2D3DS``)."""
from .collate import collate_samples
from .robust import CorruptSampleError, SkipCorrupt, TooManyCorruptSamples

__all__ = ["collate_samples", "CorruptSampleError", "SkipCorrupt", "TooManyCorruptSamples"]
