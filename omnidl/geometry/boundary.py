"""HorizonNet's boundary encoding: per-column ceiling/floor boundaries as angles <-> pixel rows.

A layout network (:mod:`omnidl.models.horizonnet`) predicts, for every column, the ceiling and the floor
boundary as the angle below the horizon ``theta = (v / H - 0.5) * pi`` of the continuous pixel row
``v`` in an image of ``H`` rows (negative = ceiling side). This is only the output encoding: the ray of
a boundary pixel always comes from the camera model (``camera.unproject`` of ``(u, v)``), so the same
encoding serves an equirectangular, a non-central or any other panorama. This module is the one home
of the formula (losses, metrics, post-processing and visualisation import it).
"""
from __future__ import annotations

import math
from typing import TypeVar

T = TypeVar("T")


def rows_to_angles(rows: T, height: int) -> T:
    """Continuous pixel rows ``v`` (tensor or array, any shape) -> boundary angles ``(v / H - 0.5) * pi``."""
    return (rows / height - 0.5) * math.pi


def angles_to_rows(angles: T, height: int) -> T:
    """Boundary angles ``theta`` (radians, any shape) -> continuous pixel rows ``(theta / pi + 0.5) * H``
    (inverse of :func:`rows_to_angles`)."""
    return (angles / math.pi + 0.5) * height
