"""The semantic classes used everywhere in omnidl: Stanford2D3DS' 13 classes plus 0 = unknown.

The order is fixed here and nowhere else (alphabetical, as the Stanford2D3DS
``semantic_labels.json`` names sort and as FreDSNet's 14-way output uses them).
It sits on the ground floor (it imports nothing of omnidl), so datasets, the renderer, the exporter and
the colour maps all read the same list.
"""
from __future__ import annotations

CLASS_NAMES: tuple[str, ...] = (
    "unknown", "beam", "board", "bookcase", "ceiling", "chair", "clutter",
    "column", "door", "floor", "sofa", "table", "wall", "window",
)
NUM_CLASSES = len(CLASS_NAMES)  # 14, including unknown
IGNORE_INDEX = 0
CLASS_ID = {name: i for i, name in enumerate(CLASS_NAMES)}

#: an RGB colour per class (uint8), used by overlays and exports
CLASS_COLORS: tuple[tuple[int, int, int], ...] = (
    (0, 0, 0), (255, 127, 14), (44, 160, 44), (148, 103, 189), (200, 200, 200), (214, 39, 40),
    (140, 86, 75), (227, 119, 194), (188, 189, 34), (100, 100, 100), (23, 190, 207), (255, 187, 120),
    (31, 119, 180), (174, 199, 232),
)
