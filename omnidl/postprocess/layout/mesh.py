"""A room layout as a textured mesh: floor, ceiling and walls, textured with the panorama they were seen in.

:func:`layout_mesh` turns a :class:`~.layout.Layout` (or its ``to_dict()``, or ground-truth corners through
:func:`room_mesh`) and its panorama into a :class:`~omnidl.viz.mesh.TexturedMesh`; :func:`save_layout_mesh`
writes it as glTF binary (``.glb``) or OBJ + MTL + PNG (``.obj``) with :mod:`omnidl.viz.mesh`.

Texture coordinates come from the panorama's camera: the texture coordinate of a vertex is
``camera.project`` of that vertex (in the camera frame, tilt included) divided by the image size, so any
360° panorama camera works, the non-central panorama included (its rays do not meet at the origin; the
camera model says where each point appears). A texture coordinate is exact at the vertices and linear across a
triangle, while the panorama's mapping is not; so every face is tessellated into triangles that each subtend at
most ``step_deg`` seen from the camera:

* **walls**: a grid per wall; columns uniform in azimuth (``ceil(angle / step)`` per wall), the same rows for all
  walls, uniform in elevation, so neighbouring walls share their vertical edge's vertices;
* **floor and ceiling**: when the room is star-shaped seen from the camera (every wall faces it: the layouts
  estimated from a panorama), a polar grid about the point below/above the camera whose rim is exactly the walls'
  bottom/top row of vertices (no cracks); otherwise (occluded corners) an ear-clipping triangulation whose
  triangles are subdivided uniformly (their rim vertices may then not coincide with the walls').

Two places of an equirectangular panorama have no single texture coordinate, and the mesh is cut there:

* **the seam** (the half plane of the first/last column, behind an upright camera): every triangle that crosses it
  is split along it (the cut point of an edge is shared by both triangles of that edge), and a vertex on the seam
  gets ``u = 0`` in the triangles on one side and ``u = 1`` in those on the other (two vertices in the files);
* **the poles** (straight up and down, the camera's ``y`` axis): the triangle the axis passes through is split at
  that point, and the pole vertex takes, per triangle, the mean ``u`` of the triangle's other vertices and the
  top/bottom row (``v = 0`` or ``1``).

Frame of the files: the gravity-aligned y-up frame of omnidl's point clouds (:mod:`omnidl.viz.ply`: origin at
the camera, ``+y`` up, ``-z`` the panorama's centre column), so a mesh and the ``.ply`` of the same panorama
overlay in any viewer; that is also glTF's ``+y`` up. Faces are wound to face into the room.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ...cameras import Camera, Equirectangular
from ...geometry.rotations import UPRIGHT_TO_WORLD
from ...viz.mesh import TexturedMesh, write_glb, write_obj
from ...viz.ply import CAM_TO_Y_UP, FRAME_COMMENT
from .layout import Layout

#: largest angle (degrees) a triangle edge subtends seen from the camera; 2° keeps the linear texture
#: interpolation within a fraction of a pixel of the true panorama mapping at 1024 columns (tests measure it)
DEFAULT_STEP_DEG = 2.0
#: glTF and OBJ suffixes :func:`save_layout_mesh` writes
FORMATS = {".glb": "glTF binary", ".obj": "Wavefront OBJ + MTL + PNG"}
_U = np.asarray(UPRIGHT_TO_WORLD, float)                # upright camera -> layout frame
#: a vertex within this angle (radians) of the camera's vertical axis is a pole vertex (its longitude is moot)
POLE_TOL = 1e-7
#: a vertex within this angle of the seam half plane lies on the seam
SEAM_TOL = 1e-9


def _cross2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _angle(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Angle (radians) between ``p`` and ``q`` (``(..., 3)``) seen from the origin."""
    return np.arctan2(np.linalg.norm(np.cross(p, q), axis=-1), (p * q).sum(-1))


def _texture(image: Any) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB from a ``(3, H, W)`` float tensor/array in [0, 1] or an ``(H, W, 3)`` uint8 array."""
    if isinstance(image, torch.Tensor):
        image = image.detach().cpu().numpy()
    a = np.asarray(image)
    if a.ndim == 3 and a.shape[0] == 3 and a.shape[2] != 3 and a.dtype != np.uint8:
        a = a.transpose(1, 2, 0)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"layout mesh: the panorama must be a (3, H, W) RGB tensor in [0, 1] or an (H, W, 3) uint8 "
                         f"RGB array, got shape {a.shape}")
    if a.dtype == np.uint8:
        return np.ascontiguousarray(a)
    if not np.isfinite(a).all():
        raise ValueError("layout mesh: the panorama has non-finite values")
    return (np.clip(a, 0, 1) * 255).round().astype(np.uint8)


def _check_corners(floor: np.ndarray, ceiling: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    floor, ceiling = np.asarray(floor, float), np.asarray(ceiling, float)
    for name, c in (("floor_corners", floor), ("ceiling_corners", ceiling)):
        if c.ndim != 2 or c.shape[1] != 3 or len(c) < 3:
            raise ValueError(f"layout mesh: {name} must be (N, 3) with N >= 3, got {c.shape}")
        if not np.isfinite(c).all():
            raise ValueError(f"layout mesh: {name} has non-finite values")
    if floor.shape != ceiling.shape:
        raise ValueError(f"layout mesh: floor_corners {floor.shape} and ceiling_corners {ceiling.shape} differ in "
                         "shape (one floor and one ceiling corner per wall corner)")
    if not (floor[:, 2] < 0).all() or not (ceiling[:, 2] > 0).all():
        raise ValueError(f"layout mesh: the camera must be between floor and ceiling (layout frame, z up, camera at "
                         f"the origin): floor z {floor[:, 2].round(3).tolist()} must be < 0 and ceiling z "
                         f"{ceiling[:, 2].round(3).tolist()} > 0")
    area = 0.5 * _cross2(floor[:, :2], np.roll(floor[:, :2], -1, 0)).sum()
    scale = float(np.abs(floor[:, :2]).max())
    if abs(area) < 1e-9 * max(scale, 1e-12) ** 2:
        raise ValueError(f"layout mesh: the floor polygon has no area ({floor[:, :2].round(4).tolist()})")
    if area < 0:            # counter-clockwise seen from above: the room is on the left of every wall
        floor, ceiling = floor[::-1].copy(), ceiling[::-1].copy()
    return floor, ceiling


class _Builder:
    """Vertices and oriented triangles, by group."""

    def __init__(self) -> None:
        self.points: list[np.ndarray] = []
        self.n = 0
        self.tris: dict[str, list[np.ndarray]] = {"floor": [], "ceiling": [], "walls": []}

    def add(self, pts: np.ndarray) -> np.ndarray:
        pts = np.asarray(pts, float).reshape(-1, 3)
        self.points.append(pts)
        ids = np.arange(self.n, self.n + len(pts))
        self.n += len(pts)
        return ids

    def tris_(self, group: str, tris: np.ndarray, normal: np.ndarray) -> None:
        """Add triangles ``(T, 3)`` wound so that their normals point along ``normal`` (``(3,)`` or ``(T, 3)``);
        degenerate ones are dropped."""
        tris = np.asarray(tris, np.int64).reshape(-1, 3)
        P = np.concatenate(self.points)
        a, b, c = P[tris[:, 0]], P[tris[:, 1]], P[tris[:, 2]]
        nrm = np.cross(b - a, c - a)
        size = np.linalg.norm(nrm, axis=1)
        scale = np.maximum(np.abs(np.stack([a, b, c], 1)).max((1, 2)), 1e-12)
        keep = size > 1e-14 * scale ** 2
        flip = (nrm * np.broadcast_to(normal, nrm.shape)).sum(1) < 0
        tris = np.where(flip[:, None], tris[:, [0, 2, 1]], tris)
        self.tris[group].append(tris[keep])


def _quads(ids: np.ndarray, wrap: bool) -> np.ndarray:
    """Two triangles per cell of a grid of vertex ids ``(K, R)`` (columns wrap around when ``wrap``)."""
    nxt = np.roll(ids, -1, 0) if wrap else ids[1:]
    cur = ids if wrap else ids[:-1]
    t1 = np.stack([cur[:, :-1], nxt[:, :-1], nxt[:, 1:]], -1)
    t2 = np.stack([cur[:, :-1], nxt[:, 1:], cur[:, 1:]], -1)
    return np.concatenate([t1.reshape(-1, 3), t2.reshape(-1, 3)])


def _edge_params(A: np.ndarray, B: np.ndarray, m: int) -> np.ndarray:
    """``m + 1`` parameters in [0, 1] along the top-view edge A -> B, uniform in azimuth seen from the origin
    when the edge faces the origin (counter-clockwise), else uniform."""
    t = np.linspace(0.0, 1.0, m + 1)
    turn = math.atan2(float(_cross2(A, B)), float(A @ B))
    if m == 1 or turn <= 1e-9:
        return t
    phi = math.atan2(A[1], A[0]) + turn * t[1:-1]
    d = np.stack([np.cos(phi), np.sin(phi)], 1)
    den = _cross2(B - A, d)
    if np.any(np.abs(den) < 1e-12):
        return t
    t[1:-1] = np.clip(-_cross2(A[None], d) / den, 0.0, 1.0)
    return np.maximum.accumulate(t)


def _columns(floor: np.ndarray, ceiling: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Wall columns around the room: floor points ``(K, 3)``, ceiling points ``(K, 3)``, wall index ``(K,)``."""
    n = len(floor)
    F, C, wall = [], [], []
    for i in range(n):
        j = (i + 1) % n
        m = max(1, math.ceil(max(_angle(floor[i], floor[j]), _angle(ceiling[i], ceiling[j])) / step))
        t = _edge_params(floor[i, :2], floor[j, :2], m)[:-1, None]
        F.append(floor[i] + t * (floor[j] - floor[i]))
        C.append(ceiling[i] + t * (ceiling[j] - ceiling[i]))
        wall += [i] * m
    return np.concatenate(F), np.concatenate(C), np.asarray(wall)


def _star_shaped(poly: np.ndarray) -> bool:
    """True when every edge of the counter-clockwise top-view polygon faces the origin and it winds once."""
    nxt = np.roll(poly, -1, 0)
    cr = _cross2(poly, nxt)
    if not (cr > 1e-12 * (np.linalg.norm(poly, axis=1) * np.linalg.norm(nxt, axis=1))).all():
        return False
    return abs(np.arctan2(cr, (poly * nxt).sum(1)).sum() - 2 * math.pi) < 1e-6


def _walls(b: _Builder, F: np.ndarray, C: np.ndarray, wall: np.ndarray, floor: np.ndarray, step: float
           ) -> tuple[np.ndarray, np.ndarray]:
    """Wall grids; returns the vertex ids of the bottom and top rows (``(K,)`` each)."""
    K = len(F)
    rho = np.linalg.norm(F[:, :2], axis=1)
    a_f, a_c = np.arctan2(F[:, 2], rho), np.arctan2(C[:, 2], np.linalg.norm(C[:, :2], axis=1))
    Q = max(1, math.ceil(float((a_c - a_f).max()) / step))
    q = np.arange(Q + 1) / Q
    vertical = np.linalg.norm(F[:, :2] - C[:, :2], axis=1) <= 1e-9 * np.maximum(rho, 1e-12)
    z = rho[:, None] * np.tan(a_f[:, None] + q[None] * (a_c - a_f)[:, None])       # uniform elevation
    w = np.where(vertical[:, None], (z - F[:, 2:3]) / (C[:, 2:3] - F[:, 2:3]), q[None])
    w[:, 0], w[:, -1] = 0.0, 1.0
    grid = F[:, None] + w[..., None] * (C - F)[:, None]                              # (K, Q+1, 3)
    ids = b.add(grid.reshape(-1, 3)).reshape(K, Q + 1)
    nf = len(floor)
    e = floor[(wall + 1) % nf, :2] - floor[wall, :2]
    inward = np.stack([-e[:, 1], e[:, 0], np.zeros(K)], 1)                       # left of a counter-clockwise wall
    tris = _quads(ids, wrap=True)
    b.tris_("walls", tris, np.concatenate([inward, inward]).repeat(Q, 0))
    return ids[:, 0], ids[:, -1]


def _fan(b: _Builder, group: str, rim: np.ndarray, step: float) -> None:
    """Polar grid of the floor/ceiling about the point below/above the camera, rim = the walls' row ``rim``."""
    P = np.concatenate(b.points)
    B = P[rim]
    h = float(B[:, 2].mean())
    O = np.array([0.0, 0.0, h])
    theta = np.arctan2(np.linalg.norm(B[:, :2], axis=1), abs(h))                    # angle from the vertical
    R = max(1, math.ceil(float(theta.max()) / step))
    r = np.arange(1, R) / R
    s = np.tan(theta[:, None] * r[None]) / np.tan(theta)[:, None]                    # uniform in angle
    rings = O + s[..., None] * (B - O)[:, None]                                      # (K, R-1, 3)
    K = len(B)
    ring_ids = b.add(rings.reshape(-1, 3)).reshape(K, R - 1)
    cols = np.concatenate([ring_ids, rim[:, None]], 1)                               # (K, R) from centre out
    centre = b.add(O[None])[0]
    normal = np.array([0.0, 0.0, 1.0 if group == "floor" else -1.0])
    inner = np.stack([np.full(K, centre), cols[:, 0], np.roll(cols[:, 0], -1)], 1)
    b.tris_(group, np.concatenate([inner, _quads(cols, wrap=True)]), normal)


def _ear_clip(poly: np.ndarray) -> list[tuple[int, int, int]]:
    """Triangles of a simple counter-clockwise polygon ``(N, 2)`` by ear clipping (collinear corners allowed)."""
    idx = list(range(len(poly)))
    out = []
    guard = 0
    while len(idx) > 3 and guard < 10 * len(poly) ** 2:
        guard += 1
        for k in range(len(idx)):
            i, j, l = idx[k - 1], idx[k], idx[(k + 1) % len(idx)]
            a, bb, c = poly[i], poly[j], poly[l]
            if _cross2(bb - a, c - bb) <= 1e-12:
                continue                                                             # reflex or flat: not an ear
            others = [poly[m] for m in idx if m not in (i, j, l)]
            if any(_cross2(bb - a, p - a) >= 0 and _cross2(c - bb, p - bb) >= 0 and _cross2(a - c, p - c) >= 0
                   for p in others):
                continue
            out.append((i, j, l))
            idx.pop(k)
            break
        else:
            raise ValueError(f"layout mesh: the floor polygon {poly.round(4).tolist()} is not simple "
                             "(its walls cross), so it has no floor/ceiling triangulation")
    out.append(tuple(idx))
    return out


def _subdivided(b: _Builder, group: str, corners: np.ndarray, step: float) -> None:
    """Ear-clipped floor/ceiling with every triangle split into a uniform grid of ``n^2`` triangles."""
    normal = np.array([0.0, 0.0, 1.0 if group == "floor" else -1.0])
    for tri in _ear_clip(corners[:, :2]):
        A, B, C = corners[list(tri)]
        n = max(1, math.ceil(max(_angle(A, B), _angle(B, C), _angle(C, A)) / step))
        ij = [(i, j) for i in range(n + 1) for j in range(n + 1 - i)]
        pts = np.array([A + (B - A) * i / n + (C - A) * j / n for i, j in ij])
        ids = dict(zip(ij, b.add(pts)))
        tris = [(ids[i, j], ids[i + 1, j], ids[i, j + 1]) for i in range(n) for j in range(n - i)]
        tris += [(ids[i + 1, j], ids[i + 1, j + 1], ids[i, j + 1]) for i in range(n) for j in range(n - i - 1)]
        b.tris_(group, np.asarray(tris), normal)


def tessellate_room(floor_corners: np.ndarray, ceiling_corners: np.ndarray, step_deg: float = DEFAULT_STEP_DEG
                    ) -> tuple[np.ndarray, dict[str, np.ndarray], dict]:
    """Triangles of a room, each subtending at most ``step_deg`` seen from the camera (module docstring).

    Args:
        floor_corners, ceiling_corners: ``(N, 3)`` layout frame (z up, metres, camera at the origin), in the
            order of the walls (wall ``i`` joins corner ``i`` and ``i + 1``), either orientation.
    Returns:
        ``points (V, 3)`` layout frame, ``{"floor", "ceiling", "walls"} -> (F, 3)`` vertex ids wound to face
        into the room, and ``info`` (``star_shaped``, ``columns``, ``step_deg``).
    """
    if not (math.isfinite(step_deg) and 0.05 <= step_deg <= 45):
        raise ValueError(f"layout mesh: step_deg must be in [0.05, 45] degrees, got {step_deg}")
    floor, ceiling = _check_corners(floor_corners, ceiling_corners)
    step = math.radians(step_deg)
    b = _Builder()
    F, C, wall = _columns(floor, ceiling, step)
    bottom, top = _walls(b, F, C, wall, floor, step)
    star = _star_shaped(floor[:, :2]) and _star_shaped(ceiling[:, :2])
    if star:
        _fan(b, "floor", bottom, step)
        _fan(b, "ceiling", top, step)
    else:
        _subdivided(b, "floor", floor, step)
        _subdivided(b, "ceiling", ceiling, step)
    faces = {g: np.concatenate(t).reshape(-1, 3) if t else np.zeros((0, 3), np.int64) for g, t in b.tris.items()}
    return np.concatenate(b.points), faces, {"star_shaped": bool(star), "columns": int(len(F)), "step_deg": step_deg}


# --- cutting at the seam and the poles, texture coordinates --------------------------------------------------------

class _Cutter:
    """Splits camera-frame triangles at the camera's vertical axis (poles) and along its seam half plane."""

    def __init__(self, points: np.ndarray, seam_dir: np.ndarray, axis: np.ndarray) -> None:
        self.P = [p for p in points]
        self.axis = axis / np.linalg.norm(axis)
        self.seam_dir = seam_dir - (seam_dir @ self.axis) * self.axis
        self.seam_dir /= np.linalg.norm(self.seam_dir)
        self.normal = np.cross(self.seam_dir, self.axis)     # the seam half plane: normal . p = 0, seam_dir . p > 0
        self.cache: dict[tuple, int] = {}

    def _new(self, key: tuple | None, p: np.ndarray) -> int:
        if key is not None and key in self.cache:
            return self.cache[key]
        self.P.append(p)
        if key is not None:
            self.cache[key] = len(self.P) - 1
        return len(self.P) - 1

    def pole_split(self, tri: tuple[int, int, int]) -> list[tuple[int, int, int]]:
        """Split ``tri`` at the point where the camera's vertical axis passes through it."""
        a, b, c = (self.P[i] for i in tri)
        if any(self.is_pole(p) for p in (a, b, c)):
            return [tri]
        nrm = np.cross(b - a, c - a)
        den = nrm @ self.axis
        if abs(den) <= 1e-12 * np.linalg.norm(nrm):
            return [tri]
        X = (nrm @ a) / den * self.axis
        # barycentric coordinates of X
        T = np.stack([a - c, b - c], 1)
        l12, *_ = np.linalg.lstsq(T, X - c, rcond=None)
        lam = np.array([l12[0], l12[1], 1 - l12.sum()])
        eps = 1e-9
        if (lam < -eps).any() or (lam > 1 - eps).any():
            return [tri]                                   # outside, or at a vertex (a pole vertex already)
        zero = np.flatnonzero(np.abs(lam) <= eps)
        if len(zero) == 0:
            x = self._new(None, X)
            return [(tri[0], tri[1], x), (tri[1], tri[2], x), (tri[2], tri[0], x)]
        k = int(zero[0])                                   # on the edge opposite corner k
        i, j = tri[(k + 1) % 3], tri[(k + 2) % 3]
        x = self._new(("pole", min(i, j), max(i, j)), X)
        return [(tri[k], i, x), (tri[k], x, j)]

    def is_pole(self, p: np.ndarray) -> bool:
        n = float(np.linalg.norm(p))
        return float(np.linalg.norm(p - (p @ self.axis) * self.axis)) <= POLE_TOL * n

    def side(self, p: np.ndarray) -> float:
        return float(self.normal @ p)

    def sign(self, p: np.ndarray) -> int:
        """-1, 0 or 1: the side of the seam plane ``p`` is on (0 within ``1e-9 |p|``)."""
        s = self.side(p)
        if self.is_pole(p) or abs(s) <= SEAM_TOL * float(np.linalg.norm(p)):
            return 0
        return 1 if s > 0 else -1

    def candidates(self, tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Masks ``(T,)`` of the triangles :meth:`pole_split` and :meth:`seam_split` may split (a cheap superset)."""
        P = np.asarray(self.P)
        a, b, c = P[tris[:, 0]], P[tris[:, 1]], P[tris[:, 2]]
        nrm = np.cross(b - a, c - a)
        den = nrm @ self.axis
        X = ((nrm * a).sum(1) / np.where(den == 0, 1.0, den))[:, None] * self.axis
        tol = -1e-6 * np.linalg.norm(nrm, axis=1)
        inside = np.ones(len(tris), bool)
        for p, q in ((a, b), (b, c), (c, a)):
            inside &= (np.cross(q - p, X - p) * nrm).sum(1) >= tol * np.linalg.norm(q - p, axis=1) * 10
        V = np.stack([a, b, c], 1)
        at_pole = (np.linalg.norm(V - (V @ self.axis)[..., None] * self.axis, axis=2)
                   <= POLE_TOL * np.linalg.norm(V, axis=2))
        pole = inside & (np.abs(den) > 1e-12 * np.linalg.norm(nrm, axis=1)) & ~at_pole.any(1)
        s = V @ self.normal
        near = (np.abs(s) <= SEAM_TOL * np.linalg.norm(V, axis=2)) | at_pole
        seam = ((s > 0) & ~near).any(1) & ((s < 0) & ~near).any(1)
        return pole, seam

    def seam_split(self, tri: tuple[int, int, int]) -> list[tuple[int, int, int]]:
        """Cut ``tri`` along the seam half plane (only where the cut lies behind, on the seam)."""
        sg = [self.sign(self.P[i]) for i in tri]
        if not (1 in sg and -1 in sg):
            return [tri]
        cuts = {}
        for e in range(3):
            i, j = tri[e], tri[(e + 1) % 3]
            if sg[e] * sg[(e + 1) % 3] < 0:
                lo, hi = (i, j) if i < j else (j, i)       # the same point from both triangles of the edge
                slo, shi = self.side(self.P[lo]), self.side(self.P[hi])
                X = self.P[lo] + slo / (slo - shi) * (self.P[hi] - self.P[lo])
                cuts[e] = (X, ("seam", lo, hi))
        if not any(self.seam_dir @ X > 0 for X, _ in cuts.values()):
            return [tri]                                   # crosses the front meridian only
        ring: list[int] = []
        for e in range(3):
            ring.append(tri[e])
            if e in cuts:
                X, key = cuts[e]
                ring.append(self._new(key, X))
        out = []
        for want in (1, -1):                               # Sutherland-Hodgman: one convex piece per side
            piece = [v for v in ring if v not in tri or sg[tri.index(v)] in (0, want)]
            out += [(piece[0], piece[m], piece[m + 1]) for m in range(1, len(piece) - 1)]
        return out


def _project(camera: Camera, P: np.ndarray) -> np.ndarray:
    """Pixels ``(V, 2)`` of camera-frame points; points the camera cannot see from their own position (inside a
    non-central rig's circle) are projected from far along their direction from the origin."""
    uv, valid = camera.project(torch.from_numpy(P))
    uv, valid = uv.double().numpy(), valid.numpy()
    if not valid.all():
        far = P[~valid] / np.maximum(np.linalg.norm(P[~valid], axis=1, keepdims=True), 1e-300) * 1e6
        uv2, valid2 = camera.project(torch.from_numpy(far))
        uv[~valid] = uv2.double().numpy()
        valid[~valid] = valid2.numpy()
    return uv, valid


def _texture_coords(camera: Camera, P: np.ndarray, tris: np.ndarray, cut: _Cutter) -> tuple[np.ndarray, np.ndarray]:
    """Per-corner pixels ``(T, 3, 2)`` of the triangles and the vertex id of each corner ``(T, 3)``."""
    W, H = camera.width, camera.height
    uv, valid = _project(camera, P)
    norm = np.linalg.norm(P, axis=1)
    along = P @ cut.axis
    pole = np.linalg.norm(P - along[:, None] * cut.axis, axis=1) <= POLE_TOL * norm       # as _Cutter.is_pole
    seam = (np.abs(P @ cut.normal) <= SEAM_TOL * norm) & (P @ cut.seam_dir > 0) & ~pole   # as _Cutter.sign
    bad = ~valid & ~pole
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"layout mesh: the camera {type(camera).__name__} does not see the room point "
                         f"{P[i].round(4).tolist()} (camera frame); a textured mesh needs a full 360° panorama")
    c = uv[tris]                                                     # (T, 3, 2)
    cs, cp = seam[tris], pole[tris]
    plain = ~cs & ~cp
    cnt = plain.sum(1)
    keep = cnt > 0
    ref = np.where(cnt > 0, (c[..., 0] * plain).sum(1) / np.maximum(cnt, 1), W / 2)
    c[..., 0] = np.where(cs, np.where(ref < W / 2, 0.0, float(W))[:, None], c[..., 0])
    other = ~cp
    mean_u = (c[..., 0] * other).sum(1) / np.maximum(other.sum(1), 1)
    c[..., 0] = np.where(cp, mean_u[:, None], c[..., 0])
    c[..., 1] = np.where(cp, np.where(along[tris] < 0, 0.0, float(H)), c[..., 1])   # -y is up: the top row
    spread = c[..., 0].max(1) - c[..., 0].min(1)
    if (spread[keep] > W / 2).any():
        raise RuntimeError("layout mesh: a triangle still spans the panorama's seam after cutting (a bug: please "
                           "report it with the layout)")
    return c[keep], tris[keep]


def room_mesh(floor_corners: np.ndarray, ceiling_corners: np.ndarray, image: Any, camera: Camera | None = None,
              R_up_cam: Any = None, step_deg: float = DEFAULT_STEP_DEG) -> TexturedMesh:
    """A room's floor, ceiling and walls textured with the panorama it was seen in.

    Args:
        floor_corners, ceiling_corners: ``(N, 3)`` corners in the layout frame (z up, metres, camera at the origin;
            :class:`~.layout.Layout`), one per wall corner, in wall order.
        image: the panorama, ``(3, H, W)`` RGB in [0, 1] (tensor or array) or ``(H, W, 3)`` uint8 RGB.
        camera: its camera (a full 360° panorama model of size ``W x H``; default ``Equirectangular(W, H)``).
        R_up_cam: ``(3, 3)`` tilt of the camera (camera frame -> upright camera frame,
            :mod:`omnidl.geometry.rotations`), as ``omnidl predict`` reports it; None: the panorama is upright.
        step_deg: largest angle a triangle edge subtends seen from the camera.
    Returns:
        a :class:`~omnidl.viz.mesh.TexturedMesh` in the gravity-aligned y-up frame with groups ``floor``,
        ``ceiling``, ``walls`` (module docstring).
    """
    tex = _texture(image)
    H, W = tex.shape[:2]
    camera = Equirectangular(W, H) if camera is None else camera
    if (camera.width, camera.height) != (W, H):
        raise ValueError(f"layout mesh: the camera is {camera.width}x{camera.height} but the panorama is {W}x{H}")
    if not camera.wraps_horizontally:
        raise ValueError(f"layout mesh: the camera {type(camera).__name__} is not a full 360° panorama (columns "
                         "wrapping around); a room's walls all around need one as texture")
    R = np.eye(3) if R_up_cam is None else np.asarray(R_up_cam, float)
    if R.shape != (3, 3) or not np.isfinite(R).all() or not np.allclose(R @ R.T, np.eye(3), atol=1e-6):
        raise ValueError(f"layout mesh: R_up_cam must be a (3, 3) rotation, got {np.asarray(R_up_cam).tolist()}")
    pts, faces, info = tessellate_room(floor_corners, ceiling_corners, step_deg)
    M = R.T @ _U.T                                                   # layout frame -> camera frame
    seam = camera.unproject(torch.tensor([[0.0, H / 2]], dtype=torch.float64)).direction[0].numpy()
    cut = _Cutter(pts @ M.T, seam, np.array([0.0, 1.0, 0.0]))
    groups, all_c, all_t = [], [], []
    for g in ("floor", "ceiling", "walls"):
        tris = faces[g]
        for split, which in ((cut.pole_split, 0), (cut.seam_split, 1)):
            mask = cut.candidates(tris)[which]
            parts = [tris[~mask]] + [np.asarray(split(tuple(int(i) for i in t)), np.int64).reshape(-1, 3)
                                     for t in tris[mask]]
            tris = np.concatenate(parts)
        groups.append((g, len(tris)))
        all_t.append(tris)
    P = np.asarray(cut.P)
    first = 0
    out_groups, corner_px, corner_id = [], [], []
    for (g, _), tris in zip(groups, all_t):
        c, t = _texture_coords(camera, P, tris, cut)
        corner_px.append(c)
        corner_id.append(t)
        out_groups.append((g, first, first + len(t)))
        first += len(t)
    c = np.concatenate(corner_px).reshape(-1, 2)
    ids = np.concatenate(corner_id).reshape(-1)
    key = np.stack([ids, np.round(c[:, 0] * 1e6), np.round(c[:, 1] * 1e6)], 1).astype(np.int64)
    uniq, first_of, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    Y = np.asarray(CAM_TO_Y_UP, float) @ R                           # camera frame -> gravity-aligned y-up
    positions = P[ids[first_of]] @ Y.T
    uv = c[first_of] / np.array([W, H], float)
    info.update({"vertices": int(len(uniq)), "triangles": int(first), "seam_vertices": int(
        (np.abs(uv[:, 0]) < 1e-12).sum() + (np.abs(uv[:, 0] - 1) < 1e-12).sum())})
    return TexturedMesh(positions, uv, inverse.reshape(-1, 3), tex, out_groups,
                        frame=FRAME_COMMENT["gravity_y_up"].removeprefix("frame "), info=info)


def layout_corners(layout: Layout | dict) -> tuple[np.ndarray, np.ndarray]:
    """``(floor (N, 3), ceiling (N, 3))`` layout-frame corners of a :class:`~.layout.Layout` or its ``to_dict()``
    (also ``omnidl predict layout``'s ``<name>_layout.json``, whose ``"layout"`` holds it)."""
    if isinstance(layout, dict) and "layout" in layout and isinstance(layout["layout"], dict):
        layout = layout["layout"]
    if isinstance(layout, dict):
        if not layout.get("ok", False):
            raise ValueError(f"layout mesh: no layout to mesh ({layout.get('reason', 'ok is false')})")
        return np.asarray(layout["floor_corners"], float), np.asarray(layout["ceiling_corners"], float)
    if not layout.ok:
        raise ValueError(f"layout mesh: no layout to mesh ({layout.reason})")
    return layout.floor_corners, layout.ceiling_corners


def layout_mesh(layout: Layout | dict, image: Any, camera: Camera | None = None, R_up_cam: Any = None,
                step_deg: float = DEFAULT_STEP_DEG) -> TexturedMesh:
    """:func:`room_mesh` of a :class:`~.layout.Layout` (or its ``to_dict()``) and the panorama it came from."""
    floor, ceiling = layout_corners(layout)
    return room_mesh(floor, ceiling, image, camera=camera, R_up_cam=R_up_cam, step_deg=step_deg)


def save_layout_mesh(layout: Layout | dict, image: Any, path: str | Path, camera: Camera | None = None,
                     R_up_cam: Any = None, step_deg: float = DEFAULT_STEP_DEG, overwrite: bool = False
                     ) -> list[Path]:
    """Write :func:`layout_mesh` to ``path``: ``.glb`` (glTF binary, texture inside) or ``.obj`` (with ``.mtl`` and
    the texture ``.png`` beside it). Never replaces an existing file unless ``overwrite``. Returns the paths."""
    path = Path(path)
    kind = path.suffix.lower()
    if kind not in FORMATS:
        raise ValueError(f"layout mesh: {path} should end in one of {sorted(FORMATS)} ({', '.join(FORMATS.values())})")
    mesh = layout_mesh(layout, image, camera=camera, R_up_cam=R_up_cam, step_deg=step_deg)
    if kind == ".glb":
        return [write_glb(path, mesh, overwrite=overwrite)]
    return write_obj(path, mesh, overwrite=overwrite)
