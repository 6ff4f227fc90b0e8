"""Structured3D panoramas: RGB (full / simple / empty furnishing), depth, semantics and the room layout.

Folder (Structured3D's ``data_organization.md``)::

    <root>/scene_<5 digits>/2D_rendering/<room_id>/panorama/<full|simple|empty>/rgb_<raw|cold|warm>light.png
    .../panorama/<full|simple|empty>/depth.png       uint16 millimetres, 0 = no reading
    .../panorama/<full|simple|empty>/semantic.png    uint8 NYUv2 40-label ids (0 = unlabelled), grey or palette
    .../panorama/layout.txt                          corner pixels, HorizonNet ``label_cor`` format

Depth: a panorama has no optical axis, so the stored value is read as the distance along each pixel's ray
(omnidl's depth convention), ``value / 1000`` metres. Semantics: NYUv2-40 ids are mapped to omnidl's classes
by name (wall, floor, ceiling, chair, sofa, table/desk, door, window, bookshelf/shelves -> bookcase,
whiteboard -> board); every other labelled id is ``clutter``, 0 stays unknown. Layout (``layout=True``):
the boundary / corner targets of :class:`~omnidl.data.horizonnet_format.HorizonNetFolderDataset` from
``layout.txt`` with HorizonNet's assumed 1.6 m camera height (only the room's shape is used), checked as every
layout adapter checks it (corners in wall order, none twice, ceiling and floor of a corner in one column).

Splits: scenes 0-2999 train, 3000-3249 val, 3250-3499 test (the split of the Structured3D paper, used by
HorizonNet's and LGT-Net's preparation scripts).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from omnidl.classes import CLASS_ID
from .horizonnet_format import read_label_cor, room_from_label_cor
from .layout_sample import MAX_WALLS
from .layout_targets import boundary_targets, corner_heat
from .paired import PairedPanoramas, PanoramaFiles, to_tensor_labels
from .readers import read_depth_png, read_label_map, resize_labels
from .splits import check_split_name
from .validate import invalid

SPLIT_SCENES = {"train": (0, 3000), "val": (3000, 3250), "test": (3250, 3500)}
VARIANTS = ("full", "simple", "empty")
LIGHTS = ("raw", "cold", "warm")
DEPTH_SCALE = 1000.0
#: NYUv2-40 id -> omnidl class name (ids not listed: clutter; 0: unknown)
NYU40_TO_CLASS = {1: "wall", 2: "floor", 5: "chair", 6: "sofa", 7: "table", 8: "door", 9: "window", 10: "bookcase",
                  14: "table", 15: "bookcase", 22: "ceiling", 30: "board"}


def nyu40_lut() -> np.ndarray:
    """``(256,)`` int64: NYUv2-40 id -> omnidl class id."""
    lut = np.full(256, CLASS_ID["clutter"], dtype=np.int64)
    lut[0] = 0
    lut[41:] = 0
    for k, name in NYU40_TO_CLASS.items():
        lut[k] = CLASS_ID[name]
    return lut


def decode_semantic(path: Path, expect_wh, out_wh) -> torch.Tensor:
    """``semantic.png`` -> omnidl class ids: NYUv2-40 ids stored as 8-bit grey values or as the indices of a
    palette PNG (the palette index is the id, as ``numpy.asarray(PIL.Image.open(f))`` reads it)."""
    raw = read_label_map(path, "semantic", dtypes=(np.uint8,), size=expect_wh)
    bad = raw > 40
    if bad.any():
        raise invalid(path, "semantic", f"label id(s) {np.unique(raw[bad])[:5].tolist()}", "NYUv2-40 ids 0..40")
    return to_tensor_labels(resize_labels(nyu40_lut()[raw], out_wh))


def decode_depth(path: Path, expect_wh, out_wh) -> torch.Tensor:
    return read_depth_png(path, DEPTH_SCALE, None, size=out_wh, expect=expect_wh)


class Structured3D(PairedPanoramas):
    """Structured3D panoramas as sample dicts (``image``, ``depth``, ``semantic``, layout keys, ``meta``).

    Args:
        root: dataset root; split: ``train``/``val``/``test`` (scene ranges above); scenes: explicit scene ids
            (``"scene_00000"``), override ``split``.
        variant: ``full`` | ``simple`` | ``empty`` furnishing; light: ``raw`` | ``cold`` | ``warm``.
        depth, semantic, layout: which labels to load (a panorama missing a requested file is an error).
        height, width: output size; max_samples: keep the first N panoramas.
    """

    def __init__(self, root: str, split: str = "train", scenes: list[str] | None = None, variant: str = "full",
                 light: str = "raw", depth: bool = True, semantic: bool = True, layout: bool = False,
                 height: int | None = 256, width: int | None = 512, max_samples: int | None = None):
        if variant not in VARIANTS:
            raise ValueError(f"Structured3D: variant={variant!r}; expected one of {', '.join(VARIANTS)}")
        if light not in LIGHTS:
            raise ValueError(f"Structured3D: light={light!r}; expected one of {', '.join(LIGHTS)}")
        root_p = Path(root).expanduser()
        if not root_p.is_dir():
            raise FileNotFoundError(f"Structured3D: dataset root {root_p} does not exist (set data.root=<folder>)")
        if scenes is None:
            lo, hi = SPLIT_SCENES[check_split_name(split, "Structured3D")]
            scenes = [p.name for p in sorted(root_p.glob("scene_*"))
                      if p.name[6:].isdigit() and lo <= int(p.name[6:]) < hi]
        samples, self.layout_files = [], []
        for sc in scenes:
            rd = root_p / sc / "2D_rendering"
            if not rd.is_dir():
                raise FileNotFoundError(f"Structured3D: scene {sc!r} has no {rd}")
            for room in sorted(p for p in rd.iterdir() if p.is_dir()):
                pano = room / "panorama"
                rgb = pano / variant / f"rgb_{light}light.png"
                if not rgb.is_file():
                    continue
                files = PanoramaFiles(name=f"{sc}_{room.name}_{variant}", image=rgb,
                                      depth=pano / variant / "depth.png" if depth else None,
                                      semantic=pano / variant / "semantic.png" if semantic else None)
                for f in (files.depth, files.semantic, pano / "layout.txt" if layout else None):
                    if f is not None and not f.is_file():
                        raise FileNotFoundError(f"Structured3D: {rgb} has no {f.name} ({f})")
                samples.append(files)
                self.layout_files.append(pano / "layout.txt")
        if not samples:
            raise FileNotFoundError(f"Structured3D: no panorama/{variant}/rgb_{light}light.png in scenes "
                                    f"{list(scenes)[:5]} of {root_p}")
        if max_samples:
            samples = samples[: int(max_samples)]
        super().__init__(samples, height, width, decode_depth if depth else None,
                         decode_semantic if semantic else None, "Structured3D")
        self.layout = layout

    def __getitem__(self, index: int) -> dict[str, Any]:
        sample = super().__getitem__(index)
        if self.layout:
            w0, h0 = sample["meta"]["stored_size"]
            sample.update(self._layout(index, sample["image"].shape[-1], sample["image"].shape[-2], w0, h0))
        return sample

    def _layout(self, index: int, W: int, H: int, w0: int, h0: int) -> dict[str, Any]:
        path = self.layout_files[index]
        cor = read_label_cor(path, w0, h0) * np.array([W / w0, H / h0])
        cc = room_from_label_cor(cor, path, W, H)
        from ..cameras import Equirectangular
        rows, valid = boundary_targets(cc, Equirectangular(width=W, height=H))
        if len(cc) > MAX_WALLS:
            raise invalid(path, "layout", f"{len(cc)} corners", f"at most {MAX_WALLS}")
        padded = torch.zeros(MAX_WALLS, 2, 3)
        padded[: len(cc)] = torch.from_numpy(cc).float()
        return {"boundary": rows, "boundary_valid": valid, "corner_heat": corner_heat(cor[0::2, 0] + 0.5, W),
                "corners_cam": padded, "num_walls": torch.tensor(len(cc)), "camera_height": torch.tensor(1.6)}
