"""Upright alignment of a panorama without weights: vanishing directions from line segments.

Man-made scenes are full of vertical edges (wall corners, door and window frames, furniture). Every
straight 3-D line ``L`` seen by a central camera lies on the plane through the optical centre whose
normal ``n`` is the cross product of the rays of two of its image points; the line's direction ``d``
(its vanishing direction) satisfies ``n . d = 0``. So the vertical ``v`` is the direction orthogonal to
the normals of as many segments as possible. The steps:

1. the panorama is cut into the six 90° cube faces (:func:`omnidl.geometry.cubemap.equirect_to_cubemap`)
   where straight lines are straight, and OpenCV's LSD finds line segments on each face;
2. each segment's end points are un-projected through the face camera and rotated into the panorama
   frame, giving the great-circle normal ``n_i`` and a weight ``w_i`` (its angular length);
3. **voting**: candidate directions on a grid over the cap of ``max_tilt`` around the camera's up
   axis are scored by ``sum_i w_i max(0, 1 - (n_i . v / sin t)^2)`` (segments within ``t`` of passing
   through ``v``), the best one is kept;
4. **refinement**: ``v`` becomes the eigenvector of the smallest eigenvalue of ``sum w_i n_i n_i^T`` over
   its inliers, with a shrinking threshold;
5. the **horizontal** vanishing directions are where the other segments cross the horizon circle
   (``normalise(n_i x v)``): a weighted histogram of their heading modulo 90° gives the dominant
   (Manhattan) horizontal direction, reported with its support (not needed for upright alignment).

Frames: the OpenCV camera frame (x right, y down, z forward) of :mod:`omnidl.geometry.rotations`; the up
direction of an upright camera is :data:`~omnidl.geometry.rotations.UP` ``= (0, -1, 0)``. The result's
``R_up_cam`` is the zero-yaw tilt that maps the estimated up vector to ``UP``
(:func:`~omnidl.geometry.rotations.tilt_rotation`); :func:`make_upright` renders the upright panorama
(``rotate_panorama(image, R_up_cam.T)``) and :func:`to_input_frame` brings a map computed on it back.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from omnidl.cameras.base import Camera

from .cubemap import cube_face_camera, cube_face_rotations, equirect_to_cubemap
from .panorama import rotate_panorama
from .rotations import UP, tilt_from_up, tilt_rotation


@dataclass(frozen=True)
class UprightOptions:
    """Options of :func:`estimate_upright`.

    Attributes:
        face_size: cube-face size in pixels (default: ``H / 2`` of the panorama, at least 128, at most 512).
        min_length: shortest segment kept, as a fraction of the face size.
        max_tilt_deg: the vertical is searched within this angle of the camera's up axis.
        vote_step_deg: grid step of the voting stage.
        inlier_deg: angular distance (deg) within which a segment counts for a vanishing direction.
        min_inliers: fewer vertical segments than this -> ``ok=False``.
    """

    face_size: int | None = None
    min_length: float = 0.04
    max_tilt_deg: float = 45.0
    vote_step_deg: float = 0.75
    inlier_deg: float = 1.5
    min_inliers: int = 4


@dataclass
class UprightEstimate:
    """Result of :func:`estimate_upright` (float64 tensors, camera frame).

    Attributes:
        ok: False when too few vertical segments were found (``R_up_cam`` is then the identity).
        up: ``(3,)`` unit up vector (against gravity) in the camera frame.
        R_up_cam: ``(3, 3)`` camera frame -> upright frame (zero yaw), ``R_up_cam @ up = UP``.
        roll_deg, pitch_deg: the tilt of ``up`` (:func:`~omnidl.geometry.rotations.tilt_from_up`).
        tilt_deg: angle between ``up`` and the camera's own up axis.
        horizontal: ``(3,)`` dominant horizontal vanishing direction (camera frame) or None.
        n_segments, n_vertical, n_horizontal: segments found / supporting ``up`` / supporting ``horizontal``.
        reason: why ``ok`` is False.
    """

    ok: bool
    up: Tensor
    R_up_cam: Tensor
    roll_deg: float = 0.0
    pitch_deg: float = 0.0
    tilt_deg: float = 0.0
    horizontal: Tensor | None = None
    n_segments: int = 0
    n_vertical: int = 0
    n_horizontal: int = 0
    reason: str = ""
    info: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """JSON-friendly summary."""
        return {"ok": self.ok, "reason": self.reason, "up_camera_frame": self.up.tolist(),
                "R_up_cam": self.R_up_cam.tolist(), "roll_deg": self.roll_deg, "pitch_deg": self.pitch_deg,
                "tilt_deg": self.tilt_deg,
                "horizontal_vp_camera_frame": None if self.horizontal is None else self.horizontal.tolist(),
                "n_segments": self.n_segments, "n_vertical": self.n_vertical, "n_horizontal": self.n_horizontal,
                "convention": "camera frame OpenCV (x right, y down, z forward); R_up_cam maps camera directions "
                              "to the upright (gravity-aligned, zero-yaw) frame; upright image = "
                              "rotate_panorama(image, R_up_cam.T)"}


def _check_pano(image: Tensor) -> Tensor:
    if image.dim() != 3 or image.shape[0] not in (1, 3):
        raise ValueError(f"estimate_upright: image must be (3, H, W) or (1, H, W), got {tuple(image.shape)}")
    H, W = image.shape[-2:]
    if W != 2 * H:
        raise ValueError(f"estimate_upright: expected a full 360x180 equirectangular panorama (W = 2H), got {W}x{H}")
    if not torch.isfinite(image).all():
        raise ValueError("estimate_upright: image has non-finite values")
    return image


def segment_normals(image: Tensor, face_size: int, min_length: float = 0.04) -> tuple[np.ndarray, np.ndarray]:
    """Line segments of a panorama as great-circle normals.

    Args:
        image: ``(3, H, W)`` or ``(1, H, W)`` equirectangular panorama in [0, 1].
        face_size: cube-face size for the LSD.
        min_length: shortest segment kept (fraction of ``face_size``).
    Returns:
        ``normals (N, 3)`` unit (camera frame) and ``weights (N,)`` angular lengths (radians), float64.
    """
    import cv2
    img = image.detach().float().cpu()
    gray = img.mean(0, keepdim=True) if img.shape[0] == 3 else img
    faces = equirect_to_cubemap(gray[None], face_size)[0, :, 0]             # (6, F, F)
    lsd = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD)
    cam = cube_face_camera(face_size)
    R = cube_face_rotations(torch.float64)
    normals, weights = [], []
    for k in range(6):
        f8 = (faces[k].clamp(0, 1).numpy() * 255).round().astype(np.uint8)
        lines = lsd.detect(f8)[0]
        if lines is None:
            continue
        seg = lines.reshape(-1, 2, 2).astype(np.float64)
        keep = np.linalg.norm(seg[:, 0] - seg[:, 1], axis=1) >= min_length * face_size
        # drop segments hugging the face border (the cube seams, not scene edges)
        m = 1.5
        inside = ((seg > m) & (seg < face_size - m)).all(axis=(1, 2))
        seg = seg[keep & inside]
        if len(seg) == 0:
            continue
        rays = cam.unproject(torch.from_numpy(seg)).direction                  # (n, 2, 3) face frame
        d = rays @ R[k].T                                                       # panorama frame
        d = d / d.norm(dim=-1, keepdim=True)
        n = torch.linalg.cross(d[:, 0], d[:, 1], dim=-1)
        s = n.norm(dim=-1)
        ok = s > 1e-9
        normals.append((n[ok] / s[ok, None]).numpy())
        weights.append(torch.atan2(s[ok], (d[ok, 0] * d[ok, 1]).sum(-1)).numpy())
    if not normals:
        return np.zeros((0, 3)), np.zeros(0)
    return np.concatenate(normals), np.concatenate(weights)


def _cap_grid(max_tilt: float, step: float) -> np.ndarray:
    """Unit directions ``(M, 3)`` on a grid over the cap of angle ``max_tilt`` around ``UP`` (radians)."""
    k = int(math.ceil(math.sin(max_tilt) / math.sin(step)))
    a = np.linspace(-math.sin(max_tilt), math.sin(max_tilt), 2 * k + 1)
    x, z = np.meshgrid(a, a, indexing="ij")
    r2 = x ** 2 + z ** 2
    keep = r2 <= math.sin(max_tilt) ** 2
    x, z = x[keep], z[keep]
    return np.stack([x, -np.sqrt(1 - x ** 2 - z ** 2), z], 1)


def _refine(v: np.ndarray, normals: np.ndarray, weights: np.ndarray, thresholds_deg=(3.0, 1.5, 1.0, 1.0)
            ) -> tuple[np.ndarray, np.ndarray]:
    inl = np.zeros(len(normals), bool)
    for t in thresholds_deg:
        inl = np.abs(normals @ v) < math.sin(math.radians(t))
        if inl.sum() < 2:
            break
        M = (normals[inl] * weights[inl, None]).T @ normals[inl]
        _, vecs = np.linalg.eigh(M)
        v_new = vecs[:, 0]
        v = v_new if v_new @ v >= 0 else -v_new
    return v / np.linalg.norm(v), inl


def estimate_upright(image: Tensor, options: UprightOptions = UprightOptions()) -> UprightEstimate:
    """The up vector of an equirectangular panorama ``(3, H, W)`` in [0, 1] (module docstring)."""
    image = _check_pano(image)
    H = int(image.shape[-2])
    F = options.face_size or int(min(512, max(128, H // 2)))
    normals, weights = segment_normals(image, F, options.min_length)
    eye = torch.eye(3, dtype=torch.float64)
    up0 = torch.tensor(UP, dtype=torch.float64)
    if len(normals) < options.min_inliers:
        return UprightEstimate(False, up0, eye, n_segments=len(normals),
                               reason=f"only {len(normals)} line segments found (need >= {options.min_inliers})")
    grid = _cap_grid(math.radians(options.max_tilt_deg), math.radians(options.vote_step_deg))
    s = math.sin(math.radians(max(options.inlier_deg, options.vote_step_deg)))
    score = np.zeros(len(grid))
    for i in range(0, len(grid), 2048):
        score[i:i + 2048] = _joint_score(grid[i:i + 2048], normals, weights, s)
    v, inl = _best_candidate(grid, score, normals, weights, options)
    if v @ np.asarray(UP) < 0:
        v = -v
    n_vert = int(inl.sum())
    if n_vert < options.min_inliers:
        return UprightEstimate(False, up0, eye, n_segments=len(normals), n_vertical=n_vert,
                               reason=f"only {n_vert} vertical line segments (need >= {options.min_inliers})")
    up = torch.from_numpy(v)
    R = tilt_rotation(up)
    roll, pitch = tilt_from_up(up)
    tilt = math.degrees(math.acos(float(np.clip(v @ np.asarray(UP), -1, 1))))
    horizontal, n_h = _dominant_horizontal(v, normals[~inl], weights[~inl])
    return UprightEstimate(True, up, R, math.degrees(float(roll)), math.degrees(float(pitch)), tilt,
                           None if horizontal is None else torch.from_numpy(horizontal), len(normals), n_vert, n_h,
                           info={"face_size": F, "vote_score": float(score.max())})


def _joint_score(cand: np.ndarray, normals: np.ndarray, weights: np.ndarray, s: float, bin_deg: float = 1.0
                 ) -> np.ndarray:
    """Score ``(M,)`` of candidate verticals ``cand (M, 3)``: the soft vertical support
    ``sum_i w_i max(0, 1 - (n_i . v / s)^2)`` plus the line length of the strongest horizontal heading
    (modulo 90°, ``bin_deg`` bins, +-1 bin) among the other segments."""
    dots = cand @ normals.T                                                   # (M, N)
    c = np.abs(dots) / s
    vert = (np.clip(1 - c ** 2, 0, None) * weights).sum(1)
    # where each segment's great circle crosses the candidate's horizon, as a heading in its levelled frame
    R = tilt_rotation(torch.from_numpy(cand)).numpy()                         # (M, 3, 3)
    h = np.cross(normals[None], cand[:, None])                               # (M, N, 3)
    hn = np.linalg.norm(h, axis=-1)
    hu = np.einsum("mij,mnj->mni", R, h)
    ang = np.degrees(np.arctan2(hu[..., 0], hu[..., 2])) % 90.0
    nb = int(round(90 / bin_deg))
    w = weights[None] * (c >= 1) * (hn > 0.2)
    idx = (ang / bin_deg).astype(int) % nb + nb * np.arange(len(cand))[:, None]
    hist = np.bincount(idx.ravel(), weights=w.ravel(), minlength=nb * len(cand)).reshape(len(cand), nb)
    smooth = hist + np.roll(hist, 1, 1) + np.roll(hist, -1, 1)
    return vert + smooth.max(1)


def _best_candidate(grid: np.ndarray, score: np.ndarray, normals: np.ndarray, weights: np.ndarray,
                    options: UprightOptions, k: int = 5, separation_deg: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    """The vertical among the ``k`` best separated vote peaks (each refined) that explains most line length:
    its vertical inliers plus the segments of its dominant horizontal (Manhattan) direction. A room seen from
    close to a wall has few vertical edges, and a peak made of horizontal lines can then out-vote the true
    vertical; the horizontal segments, which cluster into few headings only around the true vertical,
    decide."""
    order = np.argsort(-score)
    cos_sep = math.cos(math.radians(separation_deg))
    peaks: list[np.ndarray] = []
    for i in order:
        if len(peaks) == k or score[i] <= 0:
            break
        if all(abs(grid[i] @ p) < cos_sep for p in peaks):
            peaks.append(grid[i])
    best, best_val = None, -1.0
    for p in peaks or [grid[int(np.argmax(score))]]:
        v, inl = _refine(p, normals, weights, (3.0, 1.5, options.inlier_deg, options.inlier_deg))
        _, _, h_weight = _dominant_horizontal(v, normals[~inl], weights[~inl], with_weight=True)
        val = float(weights[inl].sum()) + h_weight
        if val > best_val:
            best, best_val = (v, inl), val
    return best


def _dominant_horizontal(v: np.ndarray, normals: np.ndarray, weights: np.ndarray, bin_deg: float = 1.0,
                         with_weight: bool = False):
    """Dominant horizontal vanishing direction (Manhattan: heading modulo 90°) and its support (number of
    segments; with ``with_weight`` also their summed weight)."""
    if len(normals) == 0:
        return (None, 0, 0.0) if with_weight else (None, 0)
    h = np.cross(normals, v)
    norm = np.linalg.norm(h, axis=1)
    ok = norm > 0.2                               # segments nearly parallel to the horizon circle are unusable
    if not ok.any():
        return (None, 0, 0.0) if with_weight else (None, 0)
    h, w = h[ok] / norm[ok, None], weights[ok]
    R = tilt_rotation(torch.from_numpy(v)).numpy()
    hu = h @ R.T                                  # upright frame: heading = atan2(x, z)
    ang = np.degrees(np.arctan2(hu[:, 0], hu[:, 2])) % 90.0
    nb = int(round(90 / bin_deg))
    hist = np.bincount((ang / bin_deg).astype(int) % nb, weights=w, minlength=nb)
    smooth = hist + np.roll(hist, 1) + np.roll(hist, -1)
    peak = (int(np.argmax(smooth)) + 0.5) * bin_deg
    d = (ang - peak + 45) % 90 - 45
    sel = np.abs(d) < 1.5 * bin_deg
    if not sel.any():
        return (None, 0, 0.0) if with_weight else (None, 0)
    heading = math.radians(peak + float(np.average(d[sel], weights=w[sel])))
    dir_up = np.array([math.sin(heading), 0.0, math.cos(heading)])
    if with_weight:
        return R.T @ dir_up, int(sel.sum()), float(w[sel].sum())
    return R.T @ dir_up, int(sel.sum())


def make_upright(image: Tensor, R_up_cam: Tensor, mode: str = "bilinear", camera: Camera | None = None) -> Tensor:
    """The upright panorama of ``image (C, H, W)`` (or ``(B, C, H, W)``): ``rotate_panorama(image, R_up_cam.T)``."""
    R = torch.as_tensor(R_up_cam).to(torch.float64).transpose(-1, -2)
    out, _ = rotate_panorama(image, R, mode=mode, camera=camera, cache=False)
    return out


def to_input_frame(upright_map: Tensor, R_up_cam: Tensor, mode: str = "bilinear", camera: Camera | None = None
                   ) -> Tensor:
    """A map computed on the upright panorama (depth ranges, colours, labels with ``nearest``) back in
    the input camera's frame: ``rotate_panorama(map, R_up_cam)``."""
    out, _ = rotate_panorama(upright_map, torch.as_tensor(R_up_cam).to(torch.float64), mode=mode, camera=camera,
                             cache=False)
    return out


def up_error_deg(up_est: Tensor, up_true: Tensor) -> float:
    """Angle (degrees) between two up vectors ``(3,)``."""
    a = torch.as_tensor(up_est, dtype=torch.float64)
    b = torch.as_tensor(up_true, dtype=torch.float64)
    c = (a @ b) / (a.norm() * b.norm())
    s = torch.linalg.cross(a, b, dim=-1).norm() / (a.norm() * b.norm())
    return math.degrees(math.atan2(float(s), float(c)))
