"""The four ``omnidl predict`` commands on one image each: ``depth``, ``layout``, ``upright`` (+ the upright
step the first two run first). Every function writes its files into ``out`` and returns their paths.

Frames. Maps (depth, semantics, pictures) are returned in the **input image's frame and resolution**. When
the input is not upright, ``depth``/``layout`` estimate its tilt (:mod:`omnidl.geometry.upright`), run the
network on the upright panorama and rotate the results back. 3-D outputs (PLY, OBJ) are in the
gravity-aligned y-up frame of :mod:`omnidl.viz.ply` (y up, x right, -z = the input's forward direction
levelled); the layout JSON also gives the corners in the input camera frame and the tilt ``R_up_cam``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from omnidl.geometry.rotations import UPRIGHT_TO_WORLD
from omnidl.geometry.upright import UprightEstimate, UprightOptions, estimate_upright, make_upright, to_input_frame
from omnidl.utils.io import atomic_imwrite, atomic_write_json, atomic_write_text
from omnidl.viz import (box_edges, depth_to_points, draw_segments_3d, prediction_figure, titled_row, to_uint8_bgr,
                        write_depth_png16, write_ply, write_rgb_png, write_semantic_png)

from .loader import Predictor

#: y-up viewer frame from the upright camera frame (see omnidl.viz.ply)
_Y_UP = np.diag([1.0, -1.0, -1.0])


@dataclass
class UprightPolicy:
    """``mode``: ``auto`` (estimate; rotate when the tilt is at least ``min_tilt_deg``), ``off`` (input is
    taken as upright)."""

    mode: str = "auto"
    min_tilt_deg: float = 1.0
    options: UprightOptions = UprightOptions()


def _is_full_pano(image: torch.Tensor) -> bool:
    return int(image.shape[-1]) == 2 * int(image.shape[-2])


def upright_step(image: torch.Tensor, policy: UprightPolicy, panoramic: bool = True
                 ) -> tuple[torch.Tensor, UprightEstimate | None, torch.Tensor | None]:
    """``(image to run the network on, estimate or None, R_up_cam or None when not rotated)``."""
    if policy.mode == "off" or not panoramic or not _is_full_pano(image):
        return image, None, None
    est = estimate_upright(image, policy.options)
    if not est.ok or est.tilt_deg < policy.min_tilt_deg:
        return image, est, None
    return make_upright(image, est.R_up_cam).clamp(0, 1), est, est.R_up_cam


def _save_figure(path: Path, fig: torch.Tensor) -> Path:
    return atomic_imwrite(path, to_uint8_bgr(fig))


def _upright_json(est: UprightEstimate | None, R: torch.Tensor | None) -> dict:
    if est is None:
        return {"ran": False, "rotated": False}
    return {"ran": True, "rotated": R is not None, **est.to_dict()}


def _is_panoramic(pred: Predictor) -> bool:
    cam = pred.camera_for(pred.width, pred.height)
    return bool(getattr(cam, "wraps_horizontally", False))


def predict_depth(pred: Predictor, name: str, image: torch.Tensor, out: Path, policy: UprightPolicy,
                  ply: bool = True) -> list[Path]:
    """Depth (and semantics when the model has them) of one image: ``<name>_depth.npy`` (float32 metres,
    range along each pixel's ray), ``<name>_depth.png`` + ``<name>_depth.json`` (16-bit, scale),
    ``<name>_semantic.png`` + ``_semantic_color.png``, ``<name>.ply`` (gravity y-up), ``<name>_figure.png``,
    ``<name>_upright.json``."""
    if "depth" not in pred.outputs:
        raise ValueError(f"predict depth: the checkpoint's model {pred.name!r} has no depth output "
                         f"(outputs {sorted(pred.outputs)}); use `omnidl predict layout` for HorizonNet")
    H, W = image.shape[-2:]
    work, est, R = upright_step(image, policy, _is_panoramic(pred))
    o = pred(work)
    depth = F.interpolate(o["depth"], size=(H, W), mode="bilinear", align_corners=False)[0]      # (1, H, W)
    sem = (F.interpolate(o["semantic"], size=(H, W), mode="bilinear", align_corners=False)[0]
           if "semantic" in o else None)
    if R is not None:
        depth = to_input_frame(depth, R)
        sem = to_input_frame(sem, R) if sem is not None else None
    if not torch.isfinite(depth).all():
        bad = int((~torch.isfinite(depth)).sum())
        raise FloatingPointError(f"predict depth {name}: the model produced {bad} non-finite depth values")
    files = []
    out.mkdir(parents=True, exist_ok=True)
    npy = out / f"{name}_depth.npy"
    tmp = npy.with_name(f".{npy.name}.tmp.npy")
    np.save(tmp, depth[0].numpy().astype(np.float32))
    tmp.replace(npy)
    files.append(npy)
    files.append(write_depth_png16(out / f"{name}_depth.png", depth)[0])
    if sem is not None:
        files += write_semantic_png(out / f"{name}_semantic.png", sem)
    if ply:
        cam = pred.camera_for(W, H)
        pts, cols = depth_to_points(depth, cam, image, frame="gravity_y_up",
                                    R_up_cam=est.R_up_cam if est is not None and est.ok else None)
        files.append(write_ply(out / f"{name}.ply", pts, cols, frame="gravity_y_up"))
    files.append(_save_figure(out / f"{name}_figure.png", prediction_figure(image, depth=depth, semantic=sem)))
    files.append(atomic_write_json(out / f"{name}_upright.json", _upright_json(est, R)))
    return files


def layout_in_input_frame(layout_dict: dict, R_up_cam: torch.Tensor | None) -> tuple[np.ndarray, np.ndarray]:
    """``(floor, ceiling)`` corners ``(N, 3)`` of a layout (layout frame, z up) in the input camera frame."""
    U = np.asarray(UPRIGHT_TO_WORLD, float)          # upright camera -> layout frame
    R = np.eye(3) if R_up_cam is None else np.asarray(R_up_cam, float)
    M = R.T @ U.T                                    # layout frame -> input camera
    fl = np.asarray(layout_dict["floor_corners"], float) @ M.T
    ce = np.asarray(layout_dict["ceiling_corners"], float) @ M.T
    return fl, ce


def layout_obj_y_up(layout_dict: dict) -> str:
    """OBJ text of a layout in the gravity-aligned y-up frame (as the PLYs): ceiling then floor vertices, a
    quad per wall, ceiling and floor polygons."""
    if not layout_dict.get("ok"):
        return f"# no layout: {layout_dict.get('reason', '')}\n"
    U = np.asarray(UPRIGHT_TO_WORLD, float)
    M = _Y_UP @ U.T                                  # layout frame -> y-up
    ce = np.asarray(layout_dict["ceiling_corners"], float) @ M.T
    fl = np.asarray(layout_dict["floor_corners"], float) @ M.T
    n = len(ce)
    lines = ["# omnidl layout, metres, gravity-aligned y-up frame (y up, x right, -z forward; see omnidl.viz.ply)"]
    lines += [f"v {p[0]:.6f} {p[1]:.6f} {p[2]:.6f}" for p in np.concatenate([ce, fl])]
    for m in range(n):
        k = (m + 1) % n
        lines.append(f"f {1 + m} {1 + k} {1 + n + k} {1 + n + m}")
    lines.append("f " + " ".join(str(1 + n + i) for i in range(n)))
    lines.append("f " + " ".join(str(1 + i) for i in reversed(range(n))))
    return "\n".join(lines) + "\n"


def estimate_room_layout(pred: Predictor, work: torch.Tensor, world: str, camera_height: float) -> dict:
    """Layout dict (:meth:`omnidl.postprocess.layout.layout.Layout.to_dict`) of an upright panorama."""
    from omnidl.postprocess.layout.hooks import layouts_from_outputs
    o = pred(work)
    cam = pred.camera_for(pred.width, pred.height)
    central = bool(getattr(cam, "central", True))
    lay = layouts_from_outputs(o, {}, camera=cam, world=world, central=central,
                               camera_height=camera_height if central else None)[0]
    return lay.to_dict()


def predict_layout(pred: Predictor, name: str, image: torch.Tensor, out: Path, policy: UprightPolicy,
                   world: str = "manhattan", camera_height: float = 1.6) -> list[Path]:
    """Room layout of one panorama: ``<name>_layout.json`` (layout frame + input-frame corners + tilt),
    ``<name>_layout.obj`` (y-up), ``<name>_wireframe.png`` (over the input image), ``<name>_figure.png``."""
    if "boundary" not in pred.outputs:
        raise ValueError(f"predict layout: the checkpoint's model {pred.name!r} has no layout outputs "
                         f"(outputs {sorted(pred.outputs)}); train model=horizonnet or use a HorizonNet checkpoint")
    H, W = image.shape[-2:]
    work, est, R = upright_step(image, policy, _is_panoramic(pred))
    lay = estimate_room_layout(pred, work, world, camera_height)
    cam_in = pred.camera_for(W, H)
    doc = {"name": name, "image_size": [int(W), int(H)], "layout": lay, "upright": _upright_json(est, R)}
    wire = image
    if lay.get("ok"):
        fl, ce = layout_in_input_frame(lay, R)
        uv_f, _ = cam_in.project(torch.from_numpy(fl))
        uv_c, _ = cam_in.project(torch.from_numpy(ce))
        doc["input_frame"] = {"frame": "input camera (OpenCV: x right, y down, z forward), metres",
                              "floor_corners": fl.tolist(), "ceiling_corners": ce.tolist(),
                              "floor_corners_uv": uv_f.tolist(), "ceiling_corners_uv": uv_c.tolist()}
        wire = draw_segments_3d(image, box_edges(fl, ce), cam_in, color=(0.1, 1.0, 0.1))
    files = [atomic_write_json(out / f"{name}_layout.json", doc),
             atomic_write_text(out / f"{name}_layout.obj", layout_obj_y_up(lay)),
             write_rgb_png(out / f"{name}_wireframe.png", wire)]
    title = "layout" if lay.get("ok") else f"no layout: {lay.get('reason', '')}"
    files.append(_save_figure(out / f"{name}_figure.png", titled_row([("input", image), (title, wire)])))
    return files


def horizon_segments(up: torch.Tensor, n: int = 72) -> np.ndarray:
    """The horizon (great circle orthogonal to ``up``) as ``(n, 2, 3)`` short 3-D segments (camera frame)."""
    u = np.asarray(up, float) / np.linalg.norm(np.asarray(up, float))
    a = np.cross(u, [0.0, 0.0, 1.0] if abs(u[2]) < 0.9 else [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(u, a)
    t = np.linspace(0, 2 * math.pi, n + 1)
    pts = np.cos(t)[:, None] * a + np.sin(t)[:, None] * b
    return np.stack([pts[:-1], pts[1:]], 1)


def predict_upright(name: str, image: torch.Tensor, out: Path, options: UprightOptions = UprightOptions()
                    ) -> list[Path]:
    """Upright alignment of one panorama: ``<name>_upright.png`` (input resolution), ``<name>_upright.json``
    (up vector, roll/pitch, ``R_up_cam``, segments), ``<name>_figure.png`` (input with its estimated horizon
    | upright panorama with the true horizon)."""
    from omnidl.cameras import Equirectangular
    if not _is_full_pano(image):
        raise ValueError(f"predict upright {name}: expected a full 360x180 panorama (width = 2 x height), got "
                         f"{image.shape[-1]}x{image.shape[-2]}")
    est = estimate_upright(image, options)
    H, W = image.shape[-2:]
    cam = Equirectangular(width=W, height=H)
    up_img = make_upright(image, est.R_up_cam).clamp(0, 1) if est.ok else image
    hor_in = draw_segments_3d(image, horizon_segments(est.up), cam, color=(1.0, 0.2, 0.2))
    hor_up = draw_segments_3d(up_img, horizon_segments(torch.tensor([0.0, -1.0, 0.0])), cam, color=(1.0, 0.2, 0.2))
    t_in = f"input, horizon (tilt {est.tilt_deg:.1f} deg)" if est.ok else f"input ({est.reason})"
    files = [write_rgb_png(out / f"{name}_upright.png", up_img),
             atomic_write_json(out / f"{name}_upright.json", {"name": name, **_upright_json(est, est.R_up_cam)}),
             _save_figure(out / f"{name}_figure.png", titled_row([(t_in, hor_in), ("upright", hor_up)]))]
    return files
