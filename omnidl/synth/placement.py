"""Camera poses in a scene: free random position and height, gravity-aligned or tilted.

Pose convention (``docs/design.md#conventions``): ``X_world = R X_cam + t``; an upright camera maps camera ``-y`` to
world ``+z``; at yaw 0 camera ``x`` -> world ``+x`` and camera ``z`` (forward) -> world ``+y``
(:data:`omnidl.geometry.rotations.UPRIGHT_TO_WORLD`). Rotations come from :mod:`omnidl.geometry.rotations`
(torch, float64) and are turned into numpy here, at the call site.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from omnidl.geometry.rotations import axis_angle_to_matrix, rotation_z, upright_to_world

from ..geometry.polygon import distance_to_edges, points_in_polygon
from .scene import Scene

def rig_radius(camera) -> float:
    """Largest distance of a ray origin from the camera centre (0 for central cameras).

    Evaluated on a 129 x 65 grid of pixels spanning the image (exact for the non-central panorama,
    whose origins depend on the column only through a smooth function).
    """
    if getattr(camera, "central", True):
        return 0.0
    u = torch.linspace(0.5, camera.width - 0.5, 129, dtype=torch.float64)
    v = torch.linspace(0.5, camera.height - 0.5, 65, dtype=torch.float64)
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    rays = camera.unproject(torch.stack([uu, vv], -1))
    o = rays.origin[rays.valid]
    return float(o.norm(dim=-1).max()) if o.numel() else 0.0


def place_camera(scene: Scene, camera, seed: int | np.random.Generator, rotation="upright",
                 max_tilt_deg: float = 30.0, height_range: tuple[float, float] = (1.0, 1.8),
                 margin: float = 0.3, radius: float | None = None, max_tries: int = 2000) -> np.ndarray:
    """A random free camera pose ``(4, 4)`` (camera-to-world) in ``scene``.

    The camera centre lies inside the floor polygon, at least ``max(margin, rig radius + 0.1)`` from every
    wall and outside every floor obstacle grown by the same amount (so a non-central rig's circle of radius
    ``Rc`` never passes through a wall or an object), at a height in ``height_range`` below beams.

    Args:
        rotation: ``"upright"`` (random yaw), ``"random"`` (random yaw and a tilt about a random
            horizontal axis up to ``max_tilt_deg``), or a ``(3, 3)`` ``R_up_cam`` (fixed tilt, random yaw).
    """
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    rc = rig_radius(camera) if radius is None else float(radius)
    keep = max(margin, rc + 0.1)   # the rig circle stays >= 10 cm clear of walls and objects
    top = min(height_range[1], scene.extra.get("beam_bottom", scene.height) - keep - 0.1, scene.height - keep - 0.1)
    bottom = max(height_range[0], keep + 0.1)
    if top < bottom:
        raise ValueError(f"no free camera height: room height {scene.height:.2f} m, rig radius {rc:.2f} m")
    lo, hi = scene.polygon.min(axis=0), scene.polygon.max(axis=0)
    fps = scene.footprints
    batch = 256
    for _ in range(max(1, max_tries // batch)):
        cand = rng.uniform(lo, hi, size=(batch, 2))
        ok = points_in_polygon(cand, scene.polygon) & (distance_to_edges(cand, scene.polygon) >= keep)
        for fp in fps:
            ok &= ~points_in_polygon(cand, fp) & (distance_to_edges(cand, fp) >= keep)
        if ok.any():
            p = cand[int(np.argmax(ok))]
            break
    else:
        raise RuntimeError("could not find a free camera position (room too cluttered for this rig radius)")
    z = rng.uniform(bottom, top)
    yaw = rng.uniform(-math.pi, math.pi)
    if isinstance(rotation, str):
        if rotation == "upright":
            r_up_cam = np.eye(3)
        elif rotation == "random":
            a = rng.uniform(0, 2 * math.pi)
            tilt = math.radians(max_tilt_deg) * math.sqrt(rng.uniform(0, 1))
            axis = torch.tensor((math.cos(a), 0.0, math.sin(a)), dtype=torch.float64)
            r_up_cam = axis_angle_to_matrix(axis * tilt).numpy()
        else:
            raise ValueError(f"rotation must be 'upright', 'random' or a 3x3 matrix, got {rotation!r}")
    else:
        r_up_cam = np.asarray(rotation, np.float64)
        if r_up_cam.shape != (3, 3):
            raise ValueError(f"rotation matrix must be (3, 3), got {r_up_cam.shape}")
    pose = np.eye(4)
    heading = rotation_z(torch.tensor(yaw, dtype=torch.float64)) @ upright_to_world(torch.float64)
    pose[:3, :3] = heading.numpy() @ r_up_cam
    pose[:3, 3] = (p[0], p[1], z)
    return pose
