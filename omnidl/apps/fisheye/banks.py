"""Panoramas held in memory for one protocol run, reachable from Hydra configs by name.

The protocol renders (or loads) each split's panoramas once and every stage — the engine's training
runs and the evaluations — views the same in-memory copy. A data config names a bank with the node
``{_target_: omnidl.apps.fisheye.banks.panorama_bank, split: train}`` (the ``panoramas=`` source of
:class:`omnidl.data.fisheye.ViewsFromPanoramas`); :func:`holding` makes the banks of a run reachable
for its duration.
"""
from __future__ import annotations

from collections.abc import Iterator, Mapping
from contextlib import contextmanager

import torch
from tqdm import tqdm

_HELD: dict[str, "PanoramaBank"] = {}


class PanoramaBank:
    """Equirectangular samples of ``source`` kept in memory: ``image (3,H,W)`` float32, ``depth (1,H,W)``
    float32 (0 = invalid), ``semantic (H,W)`` int16. A map-style dataset."""

    def __init__(self, source, desc: str = "panoramas") -> None:
        self.items = []
        for i in tqdm(range(len(source)), desc=desc, leave=False):
            s = source[i]
            self.items.append({"image": s["image"].float(), "depth": s["depth"].float(),
                               "semantic": s["semantic"].to(torch.int16)})

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> dict:
        return self.items[i]


def bank_node(split: str) -> dict:
    """The config node that resolves to the held bank of ``split``."""
    return {"_target_": f"{__name__}.panorama_bank", "split": split}


def panorama_bank(split: str) -> PanoramaBank:
    """The bank of ``split`` held by the running protocol (see :func:`holding`)."""
    if split not in _HELD:
        raise KeyError(f"no panorama bank {split!r} is held (held: {sorted(_HELD)}); the node "
                       f"{bank_node(split)} only resolves inside omnidl.apps.fisheye.protocol.run")
    return _HELD[split]


@contextmanager
def holding(banks: Mapping[str, PanoramaBank]) -> Iterator[None]:
    """Make ``banks`` (split -> bank) reachable through :func:`panorama_bank` inside the ``with`` block."""
    before = dict(_HELD)
    _HELD.update(banks)
    try:
        yield
    finally:
        _HELD.clear()
        _HELD.update(before)
