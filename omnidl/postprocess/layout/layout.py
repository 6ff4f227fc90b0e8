"""The :class:`Layout` result of the geometric pipeline and its exports (JSON, OBJ)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ...utils.io import atomic_write_json, atomic_write_text


@dataclass
class Layout:
    """A room layout in the gravity-aligned layout frame (z up, metres, rig centre at the origin).

    Attributes:
        ok: False when no layout could be recovered; ``reason`` then says why.
        reason: ``""`` or a human-readable explanation (degenerate input, no scale, ...).
        corners: ``(N, 2)`` top-view corners in the order of increasing panorama column.
        h_ceiling: ceiling height above the camera circle (> 0).
        h_floor: floor height relative to the camera circle (< 0).
        occluded: ``(N,)`` bool, corners created by occlusion handling (not seen directly).
        world: ``"manhattan"`` or ``"atlanta"``.
        scale: ``"metric"`` (from the rig radius), ``"camera_height"`` (central, given height) or
            ``"none"``.
        info: extra diagnostics (number of walls, RANSAC inliers, adjustment cost, timings ...).
    """

    ok: bool
    reason: str = ""
    corners: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    h_ceiling: float = math.nan
    h_floor: float = math.nan
    occluded: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    world: str = "atlanta"
    scale: str = "metric"
    info: dict = field(default_factory=dict)

    @classmethod
    def failed(cls, reason: str, world: str = "atlanta", **info: Any) -> "Layout":
        """A "no layout" result with its reason."""
        return cls(ok=False, reason=reason, world=world, scale="none", info=dict(info))

    @property
    def n_corners(self) -> int:
        return int(len(self.corners))

    @property
    def ceiling_corners(self) -> np.ndarray:
        """``(N, 3)`` ceiling corners (metres)."""
        return np.concatenate([self.corners, np.full((self.n_corners, 1), self.h_ceiling)], 1)

    @property
    def floor_corners(self) -> np.ndarray:
        """``(N, 3)`` floor corners (metres)."""
        return np.concatenate([self.corners, np.full((self.n_corners, 1), self.h_floor)], 1)

    @property
    def corners_3d(self) -> np.ndarray:
        """``(2N, 3)``: ceiling corners then floor corners."""
        return np.concatenate([self.ceiling_corners, self.floor_corners], 0)

    @property
    def height(self) -> float:
        """Room height ``h_c - h_f`` (metres)."""
        return float(self.h_ceiling - self.h_floor)

    def wall_lines(self) -> tuple[np.ndarray, np.ndarray]:
        """Plücker lines ``(N, 6)`` = (unit direction, moment) of the ceiling and floor edges of each wall.

        Wall ``m`` joins corner ``m`` and corner ``m+1``.
        """
        def lines(P):
            Q = np.roll(P, -1, 0)
            d = Q - P
            d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
            return np.concatenate([d, np.cross(P, d)], 1)
        return lines(self.ceiling_corners), lines(self.floor_corners)

    def to_dict(self) -> dict:
        """JSON-friendly dict (lists of floats)."""
        out = {"ok": bool(self.ok), "reason": self.reason, "world": self.world, "scale": self.scale,
               "frame": "layout frame: z up, metres, rig centre at origin (x_w, y_w, z_w) = (x_c, z_c, -y_c)"}
        if self.ok:
            lc, lf = self.wall_lines()
            out.update({"h_ceiling": float(self.h_ceiling), "h_floor": float(self.h_floor),
                        "corners_2d": self.corners.tolist(), "ceiling_corners": self.ceiling_corners.tolist(),
                        "floor_corners": self.floor_corners.tolist(), "occluded": self.occluded.tolist(),
                        "ceiling_lines": lc.tolist(), "floor_lines": lf.tolist()})
        out["info"] = {k: v for k, v in self.info.items() if isinstance(v, (int, float, str, bool, list))}
        return out

    @classmethod
    def from_dict(cls, d: dict) -> "Layout":
        if not d.get("ok", False):
            return cls.failed(d.get("reason", "unknown"), world=d.get("world", "atlanta"))
        return cls(ok=True, corners=np.asarray(d["corners_2d"], float), h_ceiling=float(d["h_ceiling"]),
                   h_floor=float(d["h_floor"]), occluded=np.asarray(d.get("occluded", []), bool),
                   world=d.get("world", "atlanta"), scale=d.get("scale", "metric"), info=d.get("info", {}))

    def save_json(self, path: str | Path) -> Path:
        """Write :meth:`to_dict` atomically."""
        return atomic_write_json(path, self.to_dict())

    def to_obj(self) -> str:
        """Wavefront OBJ text: 2N vertices (ceiling, floor), one quad per wall, ceiling and floor polygons."""
        if not self.ok:
            return f"# no layout: {self.reason}\n"
        n = self.n_corners
        lines = [f"# omnidl layout ({self.world}, scale={self.scale}), metres, z up"]
        for p in self.corners_3d:
            lines.append(f"v {p[0]:.6f} {p[1]:.6f} {p[2]:.6f}")
        for m in range(n):
            k = (m + 1) % n
            # ceiling i -> 1 + i, floor i -> 1 + n + i
            lines.append(f"f {1 + m} {1 + k} {1 + n + k} {1 + n + m}")
        lines.append("f " + " ".join(str(1 + i) for i in range(n)))
        lines.append("f " + " ".join(str(1 + n + i) for i in reversed(range(n))))
        return "\n".join(lines) + "\n"

    def save_obj(self, path: str | Path) -> Path:
        """Write :meth:`to_obj` atomically."""
        return atomic_write_text(path, self.to_obj())
