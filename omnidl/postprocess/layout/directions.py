"""Manhattan direction clustering: the room's orientation and a 2-class label per wall.

Unlike the reference (which hard-codes the x/y axes), the orientation is estimated: wall
directions ``theta_k`` are folded modulo 90 degrees by the 4-fold circular mean
``theta_0 = arg(sum_k w_k exp(4 i theta_k)) / 4`` (weights = number of inlier columns), and each
wall gets label 0 (parallel to ``theta_0``) or 1 (perpendicular).
"""
from __future__ import annotations

import math

import numpy as np


def manhattan_orientation(theta: np.ndarray, weight: np.ndarray | None = None) -> float:
    """Dominant Manhattan direction in ``(-pi/4, pi/4]`` from wall directions ``theta (N,)``."""
    theta = np.asarray(theta, float)
    w = np.ones_like(theta) if weight is None else np.asarray(weight, float)
    ok = np.isfinite(theta) & (w > 0)
    if not ok.any():
        return 0.0
    z = np.sum(w[ok] * np.exp(4j * theta[ok]))
    return float(np.angle(z) / 4.0)


def manhattan_labels(theta: np.ndarray, theta0: float) -> np.ndarray:
    """Label ``(N,)`` in {0, 1}: 0 when ``theta`` is within 45 degrees of ``theta0`` (mod 180)."""
    diff = np.mod(np.asarray(theta, float) - theta0 + math.pi / 2, math.pi) - math.pi / 2
    return (np.abs(diff) > math.pi / 4).astype(int)


def direction_spread(theta: np.ndarray, theta0: float) -> np.ndarray:
    """Angular deviation ``(N,)`` (radians) of each wall from its Manhattan axis."""
    diff = np.mod(np.asarray(theta, float) - theta0 + math.pi / 4, math.pi / 2) - math.pi / 4
    return np.abs(diff)
