"""Layout pictures: wireframe overlay on the panorama (through the camera model) and a top view."""
from __future__ import annotations

from typing import Any

import numpy as np

from ...cameras import Camera, resolve_camera
from ...geometry.boundary import angles_to_rows
from .layout import Layout
from .rays import camera_rays, project_layout_points


def project_points(points: np.ndarray, camera: Any) -> np.ndarray:
    """Pixels ``(..., 2)`` of layout-frame points ``(..., 3)`` through ``camera.project``
    (any :func:`~omnidl.cameras.resolve_camera` spec)."""
    uv, _ = project_layout_points(resolve_camera(camera), points)
    return uv


def wireframe_polylines(layout: Layout, camera: Camera, samples_per_metre: int = 40) -> list[np.ndarray]:
    """Pixel polylines ``(K, 2)`` of every ceiling/floor edge and vertical corner edge, split at the seam."""
    width = camera.width
    lines = []
    n = layout.n_corners
    for h in (layout.h_ceiling, layout.h_floor):
        for m in range(n):
            a, b = layout.corners[m], layout.corners[(m + 1) % n]
            k = max(2, int(np.linalg.norm(b - a) * samples_per_metre))
            t = np.linspace(0, 1, k)[:, None]
            P = np.concatenate([a + t * (b - a), np.full((k, 1), h)], 1)
            lines.append(project_points(P, camera))
    for c in layout.corners:
        z = np.linspace(layout.h_floor, layout.h_ceiling, 32)
        P = np.concatenate([np.repeat(c[None], 32, 0), z[:, None]], 1)
        lines.append(project_points(P, camera))
    out = []
    for uv in lines:
        jumps = np.flatnonzero(np.abs(np.diff(uv[:, 0])) > width / 2)
        out += [seg for seg in np.split(uv, jumps + 1) if len(seg) >= 2]
    return out


def draw_wireframe(image: np.ndarray, layout: Layout, camera: Any,
                   color: tuple[int, int, int] = (0, 255, 0), thickness: int = 2) -> np.ndarray:
    """RGB ``uint8 (H, W, 3)`` panorama with the layout wireframe drawn on it (a copy).

    ``camera``: the panorama's camera (any :func:`~omnidl.cameras.resolve_camera` spec), resized to the image.
    """
    import cv2
    img = np.ascontiguousarray(image.copy())
    H, W = img.shape[:2]
    if not layout.ok:
        return img
    for uv in wireframe_polylines(layout, resolve_camera(camera, W, H)):
        pts = np.round(uv - 0.5).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(img, [pts], False, color, thickness, lineType=cv2.LINE_AA)
    return img


def plot_top_view(layouts: list[Layout] | Layout, labels: list[str] | None = None, ax=None, camera: Any = None):
    """Matplotlib top view of one or more layouts (metres); returns the axes.

    With ``camera`` the optical centres of its columns are drawn too (the rig circle of a non-central
    panorama, a dot for a central camera).
    """
    import matplotlib
    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    if isinstance(layouts, Layout):
        layouts = [layouts]
    if ax is None:
        _, ax = plt.subplots(figsize=(5, 5))
    for i, lay in enumerate(layouts):
        if not lay.ok:
            continue
        p = np.concatenate([lay.corners, lay.corners[:1]], 0)
        ax.plot(p[:, 0], p[:, 1], "-o", ms=3, label=labels[i] if labels else None)
        occ = lay.corners[lay.occluded] if lay.occluded.any() else np.zeros((0, 2))
        if len(occ):
            ax.plot(occ[:, 0], occ[:, 1], "rx")
    if camera is not None:
        cam = resolve_camera(camera)
        u = np.linspace(0.0, cam.width, 101)
        o, _, _ = camera_rays(cam, np.stack([u, np.full_like(u, cam.height / 2.0)], -1))
        ax.plot(o[:, 0], o[:, 1], "k.-", lw=0.8, ms=2)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    if labels:
        ax.legend()
    return ax


class LayoutVisualizer:
    """Engine visualiser ``viz(outputs, batch) -> (3, h, w)`` in ``[0, 1]``: per sample the panorama with the
    predicted boundaries (green) and the ground truth (red, from ``batch["boundary"]`` pixel rows), and a
    strip of the predicted corner probability (white) over the target (red) below it."""

    def __init__(self, max_images: int = 2, depth_max: float | None = None, strip: int = 16) -> None:
        self.max_images, self.strip = max_images, strip

    def __call__(self, outputs: dict, batch: dict):
        import torch
        imgs = []
        n = min(self.max_images, batch["image"].shape[0])
        for i in range(n):
            img = batch["image"][i].detach().float().cpu().clamp(0, 1).clone()
            _, H, W = img.shape
            cols = torch.arange(W)
            pred = angles_to_rows(outputs["boundary"][i].detach().float().cpu(), H).clamp(0, H - 1).long()
            if "boundary" in batch:
                gt = batch["boundary"][i].detach().float().cpu()
                ok = batch["boundary_valid"][i].cpu().bool() if "boundary_valid" in batch else torch.ones_like(gt, dtype=torch.bool)
                for k in (0, 1):
                    c, r = cols[ok[k]], gt[k][ok[k]].clamp(0, H - 1).long()
                    img[:, r, c] = torch.tensor([1.0, 0.0, 0.0])[:, None]
            for k in (0, 1):
                img[:, pred[k], cols] = torch.tensor([0.0, 1.0, 0.0])[:, None]
            strip = torch.zeros(3, self.strip, W)
            p = torch.sigmoid(outputs["corner"][i].detach().float().cpu()).reshape(W)
            rows = torch.arange(self.strip).view(-1, 1).float() / self.strip
            strip[:] = (rows >= 1 - p.view(1, -1)).float()
            heat = batch.get("corner_heat", batch.get("corner"))
            if heat is not None:
                strip[1:] *= (1 - 0.5 * heat[i].detach().float().cpu().reshape(1, 1, W))
            imgs.append(torch.cat([img, strip], 1))
        return torch.cat(imgs, 1)
