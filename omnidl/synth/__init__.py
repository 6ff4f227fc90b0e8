"""The built-in data engine: procedural indoor rooms ray-cast for any camera, with exact ground truth.

See ``docs/synth.md``. Public API: :func:`sample_room`, :func:`place_camera`, :func:`render`,
:class:`RoomLimits`, :class:`Scene`,
:func:`render_sample` (one sample of a split from its seeds). Writer CLI: ``python -m omnidl.apps.synth``.
"""
from .room import RoomLimits, check_room, is_manhattan, sample_floor_plan
from .scene import Scene, sample_room
from .placement import place_camera, rig_radius
from .render import render
from .layout import N_MAX
from .sample import SPLITS, render_sample, sample_seeds

__all__ = ["RoomLimits", "check_room", "is_manhattan", "sample_floor_plan", "Scene", "sample_room",
           "place_camera", "rig_radius", "render", "N_MAX", "SPLITS", "render_sample", "sample_seeds"]
