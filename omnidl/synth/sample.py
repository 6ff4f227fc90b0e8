"""One sample of the data engine from ``(seed, split, index)``: the seeds, and the rendering with retries.

Sample ``i`` of split ``s`` is drawn from ``numpy.random.SeedSequence([seed, split_id, i, attempt])``: splits
never share a room, and the same ``(seed, split, index)`` gives a bit-identical sample. Used by the torch
datasets (:mod:`omnidl.data.synthetic`) and the writer CLI (``python -m omnidl.apps.synth``).
"""
from __future__ import annotations

from typing import Any

import numpy as np
import torch

from omnidl.cameras.base import Camera

from .placement import place_camera
from .render import render
from .room import RoomLimits
from .scene import sample_room

#: split name -> split id of the seed sequence
SPLITS = {"train": 0, "val": 1, "test": 2}
#: rooms drawn for one sample before giving up (a room is redrawn when the camera rig fits nowhere)
MAX_ATTEMPTS = 20


def sample_seeds(seed: int, split: str, index: int, attempt: int = 0) -> tuple[int, int]:
    """``(room_seed, camera_seed)`` of one sample (deterministic, disjoint across splits)."""
    if split not in SPLITS:
        raise ValueError(f"split must be one of {sorted(SPLITS)}, got {split!r}")
    ss = np.random.SeedSequence([int(seed), SPLITS[split], int(index), int(attempt)])
    a, b = ss.generate_state(2)
    return int(a), int(b)


def render_sample(camera: Camera, seed: int, split: str, index: int, rotation: Any = "upright",
                  max_tilt_deg: float = 30.0, manhattan_ratio: float = 0.7, furniture: bool = True,
                  layout: bool = True, limits: RoomLimits = RoomLimits(), shadows: bool = False,
                  dtype: torch.dtype = torch.float32) -> dict:
    """Render sample ``index`` of ``split``: the dict of :func:`omnidl.synth.render`, with ``meta`` holding
    ``seed``, ``split``, ``index`` and the room ``attempt`` (a new room is drawn if the rig fits nowhere)."""
    last_error = None
    for attempt in range(MAX_ATTEMPTS):
        room_seed, cam_seed = sample_seeds(seed, split, index, attempt)
        scene = sample_room(room_seed, limits=limits, manhattan_ratio=manhattan_ratio, furniture=furniture)
        try:
            pose = place_camera(scene, camera, cam_seed, rotation=rotation, max_tilt_deg=max_tilt_deg)
        except (RuntimeError, ValueError) as exc:
            last_error = exc
            continue
        out = render(scene, camera, pose, layout=layout, dtype=dtype, shadows=shadows)
        out["meta"].update({"seed": int(seed), "split": split, "index": int(index), "attempt": attempt})
        return out
    raise RuntimeError(f"sample {split}/{index}: no room fits the camera rig ({last_error})")
