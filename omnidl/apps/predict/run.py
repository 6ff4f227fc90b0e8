"""The four ``omnidl predict`` commands on one image each: ``depth``, ``layout``, ``upright`` (+ the upright
step the first two run first). Every function writes its files into ``out`` and returns their paths.

Frames. Maps (depth, semantics, pictures) are returned in the **input image's frame and resolution**. When
the input is not upright, ``depth``/``layout`` estimate its tilt (:mod:`omnidl.geometry.upright`), run the
network on the upright panorama and rotate the results back. 3-D outputs (PLY, OBJ) are in the
gravity-aligned y-up frame of :mod:`omnidl.viz.ply` (y up, x right, -z = the input's forward direction
levelled); the layout JSON also gives the corners in the input camera frame and the tilt ``R_up_cam``.

Cameras. Without an input camera the image must show the model's own camera: its size is the network's input
size or that image uniformly resized (:func:`check_input_size`); anything else is refused, never stretched.
With one (``--camera``, a sidecar file; :mod:`omnidl.apps.predict.camera`) the image is re-projected into the
model's camera and every output comes back to the input's pixels and rays; pixels one camera sees and the
other does not are masked and counted (``<name>_predict.json`` / the layout JSON, and the console).

Outputs. :func:`depth_outputs` / :func:`layout_outputs` / :func:`upright_outputs` list the files of one item
before anything is written; ``claims`` (:class:`omnidl.utils.outputs.OutputClaims`) refuses an input, a file
this run already wrote and (without ``--overwrite``) a previous run's file. Every file is written atomically.
"""
from __future__ import annotations

import io
import math
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from omnidl.geometry.rotations import UPRIGHT_TO_WORLD
from omnidl.geometry.upright import UprightEstimate, UprightOptions, estimate_upright, make_upright, to_input_frame
from omnidl.utils.io import atomic_imwrite, atomic_write_bytes, atomic_write_json, atomic_write_text
from omnidl.viz import (box_edges, depth_to_points, draw_segments_3d, prediction_figure, titled_row, to_uint8_bgr,
                        write_depth_png16, write_ply, write_rgb_png, write_semantic_png)

from .camera import CameraBridge, Coverage
from .loader import Predictor
from .points import CloudOptions, subsample

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


def _describe(cam) -> str:
    base = getattr(cam, "base", None) or cam
    return f"{getattr(base, 'name', '') or type(base).__name__} {base.width}x{base.height}"


def check_input_size(pred: Predictor, width: int, height: int) -> None:
    """``ValueError`` unless a ``width x height`` input shows the model's own camera: the network's input size
    or that image uniformly resized (:func:`omnidl.cameras.resolve.is_uniform_resize`). The message names both
    sizes and ``--camera``: omnidl never stretches an image to the network."""
    from omnidl.cameras.resolve import is_uniform_resize
    if is_uniform_resize(int(width), int(height), SimpleNamespace(width=pred.width, height=pred.height)):
        return
    cam = pred.camera_for(pred.width, pred.height)
    raise ValueError(f"the input is {width}x{height} (W x H, aspect {width / height:.4g}) but the model's camera "
                     f"({_describe(cam)}) takes {pred.width}x{pred.height} images (aspect {pred.width / pred.height:.4g}) "
                     "or that image uniformly resized; omnidl does not stretch images. Give the input's own camera "
                     "with --camera FILE|PRESET (a calibration file or a preset such as kb_f195): the image is then "
                     "re-projected into the model's camera and the outputs come back to its pixels")


def _full_equirect(cam) -> bool:
    from omnidl.cameras import Equirectangular
    base = getattr(cam, "base", None) or cam
    return (isinstance(base, Equirectangular) and bool(cam.wraps_horizontally)
            and abs(base.lat_max - base.lat_min - math.pi) < 1e-9 and cam.width == 2 * cam.height)


def _claim(claims: Any, paths: list[Path]) -> None:
    if claims is not None:
        for p in paths:
            claims.claim(p)


def depth_outputs(out: Path, name: str, semantic: bool = True, ply: bool = True, camera: bool = False) -> list[Path]:
    """The files :func:`predict_depth` writes for ``name`` (in that order)."""
    names = [f"{name}_depth.npy", f"{name}_depth.png", f"{name}_depth.json"]
    names += [f"{name}_semantic.png", f"{name}_semantic_color.png"] if semantic else []
    names += [f"{name}_valid.png"] if camera else []
    names += [f"{name}.ply"] if ply else []
    names += [f"{name}_figure.png", f"{name}_upright.json", f"{name}_predict.json"]
    return [out / n for n in names]


def layout_outputs(out: Path, name: str, mesh: Sequence[str] = ()) -> list[Path]:
    """The files :func:`predict_layout` writes for ``name`` (``mesh``: the textured-mesh formats asked for,
    ``glb``/``obj``)."""
    from omnidl.viz.mesh import obj_paths
    files = [out / f"{name}{s}" for s in ("_layout.json", "_layout.obj", "_wireframe.png", "_figure.png")]
    for fmt in dict.fromkeys(mesh):
        path = out / f"{name}_room.{fmt}"
        files += [path] if fmt == "glb" else list(obj_paths(path))
    return files


def upright_outputs(out: Path, name: str) -> list[Path]:
    """The files :func:`predict_upright` writes for ``name``."""
    return [out / f"{name}{s}" for s in ("_upright.png", "_upright.json", "_figure.png")]


@dataclass
class CameraRun:
    """The network's outputs for an input seen through its own camera (see :func:`run_through_camera`)."""

    bridge: CameraBridge
    outputs: dict
    seen: torch.Tensor            # (h, w) model pixels the input fills
    est: UprightEstimate | None
    R: torch.Tensor | None        # R_up_cam applied, or None


def run_through_camera(pred: Predictor, image: torch.Tensor, camera, policy: UprightPolicy) -> CameraRun:
    """Re-project ``image`` from its ``camera`` into the model's camera (levelled first when the input is a full
    equirectangular panorama and the model is panoramic), run the network; a non-central input runs twice, the
    second time through points at the first pass's ranges (:mod:`omnidl.apps.predict.camera`)."""
    cam_m = pred.camera_for(pred.width, pred.height)
    est = R = None
    if policy.mode != "off" and _full_equirect(camera) and bool(getattr(cam_m, "wraps_horizontally", False)):
        est = estimate_upright(image, policy.options)
        if est.ok and est.tilt_deg >= policy.min_tilt_deg:
            R = est.R_up_cam
    bridge = CameraBridge(camera, cam_m, R)
    work, seen = bridge.to_model(image)
    o = pred(work)
    if not camera.central and "depth" in o:
        work, seen = bridge.to_model(image, o["depth"][0, 0])
        o = pred(work)
    return CameraRun(bridge, o, seen, est, R)


def predict_depth(pred: Predictor, name: str, image: torch.Tensor, out: Path, policy: UprightPolicy,
                  ply: bool = True, camera=None, claims: Any = None, cloud: CloudOptions = CloudOptions()
                  ) -> list[Path]:
    """Depth (and semantics when the model has them) of one image: ``<name>_depth.npy`` (float32 metres,
    range along each pixel's ray; NaN where masked), ``<name>_depth.png`` + ``<name>_depth.json`` (16-bit,
    scale; 0 = masked), ``<name>_semantic.png`` + ``_semantic_color.png`` (0 where masked), with a ``camera``
    ``<name>_valid.png`` (255 where both cameras see), ``<name>.ply`` (gravity y-up; ``cloud`` subsamples it),
    ``<name>_figure.png``, ``<name>_upright.json``, ``<name>_predict.json`` (cameras, coverage, cloud).

    ``camera``: the input's camera at its size (``None``: the model's own camera; any other size is refused,
    :func:`check_input_size`). ``claims``: an :class:`omnidl.utils.outputs.OutputClaims` checked for every file
    before anything is written (``None``: no check, for library use)."""
    if "depth" not in pred.outputs:
        raise ValueError(f"predict depth: the checkpoint's model {pred.name!r} has no depth output "
                         f"(outputs {sorted(pred.outputs)}); use `omnidl predict layout` for HorizonNet")
    H, W = image.shape[-2:]
    if camera is None:
        check_input_size(pred, W, H)
    files = depth_outputs(out, name, "semantic" in pred.outputs, ply, camera is not None)
    _claim(claims, files)
    cov: Coverage | None = None
    valid = None
    if camera is None:
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
    else:
        run = run_through_camera(pred, image, camera, policy)
        est, R, b = run.est, run.R, run.bridge
        if not torch.isfinite(run.outputs["depth"]).all():
            bad = int((~torch.isfinite(run.outputs["depth"])).sum())
            raise FloatingPointError(f"predict depth {name}: the model produced {bad} non-finite depth values")
        t, valid = b.depth_to_input(run.outputs["depth"][0], run.seen)
        depth = t.float()[None]
        sem = None
        if "semantic" in run.outputs:
            logits, ok = b.map_to_input(run.outputs["semantic"][0], run.seen, t)
            lab = torch.where(ok & valid, torch.nan_to_num(logits, nan=-math.inf).argmax(0), 0)
            sem = lab
        cov = b.coverage(run.seen, valid)
    out.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    np.save(buf, depth[0].numpy().astype(np.float32))
    atomic_write_bytes(out / f"{name}_depth.npy", buf.getvalue())
    write_depth_png16(out / f"{name}_depth.png", depth)
    if sem is not None:
        write_semantic_png(out / f"{name}_semantic.png", sem)
    if valid is not None:
        atomic_imwrite(out / f"{name}_valid.png", valid.numpy().astype(np.uint8) * 255)
    n_points = n_valid = None
    if ply:
        R_up = est.R_up_cam if est is not None and est.ok else None
        if camera is None:
            pts, cols = depth_to_points(depth, pred.camera_for(W, H), image, frame="gravity_y_up", R_up_cam=R_up)
        else:
            from omnidl.viz.ply import to_gravity_y_up
            p3, ok = run.bridge.points(depth[0].double())
            pts = to_gravity_y_up(p3[ok], R_up).float()
            cols = image.permute(1, 2, 0)[ok].float()
        n_valid = len(pts)
        pts, cols = subsample(pts, cols, cloud)
        n_points = len(pts)
        write_ply(out / f"{name}.ply", pts, cols, frame="gravity_y_up")
    _save_figure(out / f"{name}_figure.png", prediction_figure(image, depth=depth, semantic=sem))
    atomic_write_json(out / f"{name}_upright.json", _upright_json(est, R))
    doc = {"name": name, "image_size": [int(W), int(H)], "model": {"name": pred.name, "input_size": [pred.width,
           pred.height], "camera": _describe(pred.camera_for(pred.width, pred.height))},
           "depth": "range along each input pixel's own ray from its origin, metres (float32 .npy; NaN = masked)",
           "camera": None if camera is None else {**run.bridge.to_dict(), "coverage": cov.to_dict()},
           "point_cloud": None if not ply else {"points": n_points, "valid_pixels": n_valid, **cloud.to_dict(),
                                                 "frame": "gravity_y_up"}}
    atomic_write_json(out / f"{name}_predict.json", doc)
    return [f for f in files if f.exists()]


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
                   world: str = "manhattan", camera_height: float = 1.6, camera=None, claims: Any = None,
                   mesh: Sequence[str] = ()) -> list[Path]:
    """Room layout of one panorama: ``<name>_layout.json`` (layout frame + input-frame corners + tilt; with a
    ``camera`` also the cameras and the coverage), ``<name>_layout.obj`` (y-up), ``<name>_wireframe.png``
    (over the input image, drawn through the input's camera), ``<name>_figure.png``; with ``mesh`` (``glb``,
    ``obj``) the room as a mesh textured with the input image, ``<name>_room.glb`` / ``.obj`` + ``.mtl`` + PNG
    (:func:`omnidl.postprocess.layout.mesh.save_layout_mesh`; y-up frame as the ``.obj`` wireframe).
    ``camera``/``claims``: as :func:`predict_depth`."""
    if "boundary" not in pred.outputs:
        raise ValueError(f"predict layout: the checkpoint's model {pred.name!r} has no layout outputs "
                         f"(outputs {sorted(pred.outputs)}); train model=horizonnet or use a HorizonNet checkpoint")
    H, W = image.shape[-2:]
    if camera is None:
        check_input_size(pred, W, H)
    files = layout_outputs(out, name, mesh)
    _claim(claims, files)
    if camera is None:
        work, est, R = upright_step(image, policy, _is_panoramic(pred))
        lay = estimate_room_layout(pred, work, world, camera_height)
        cam_in = pred.camera_for(W, H)
        cam_doc = None
    else:
        cam_m = pred.camera_for(pred.width, pred.height)
        est = R = None
        if policy.mode != "off" and _full_equirect(camera) and bool(getattr(cam_m, "wraps_horizontally", False)):
            est = estimate_upright(image, policy.options)
            R = est.R_up_cam if est.ok and est.tilt_deg >= policy.min_tilt_deg else None
        bridge = CameraBridge(camera, cam_m, R)
        work, seen = bridge.to_model(image)
        lay = estimate_room_layout(pred, work, world, camera_height)
        cam_in = camera
        in_ok = bridge.in_valid
        sees = bridge.cm.project(bridge.in_dir @ bridge.R.T)[1] & in_ok
        cov = bridge.coverage(seen, sees)
        cam_doc = {**bridge.to_dict(), "coverage": cov.to_dict()}
    doc = {"name": name, "image_size": [int(W), int(H)], "layout": lay, "upright": _upright_json(est, R),
           "camera": cam_doc}
    wire = image
    if lay.get("ok"):
        fl, ce = layout_in_input_frame(lay, R)
        uv_f, _ = cam_in.project(torch.from_numpy(fl))
        uv_c, _ = cam_in.project(torch.from_numpy(ce))
        doc["input_frame"] = {"frame": "input camera (OpenCV: x right, y down, z forward), metres",
                              "floor_corners": fl.tolist(), "ceiling_corners": ce.tolist(),
                              "floor_corners_uv": uv_f.tolist(), "ceiling_corners_uv": uv_c.tolist()}
        wire = draw_segments_3d(image, box_edges(fl, ce), cam_in, color=(0.1, 1.0, 0.1))
    atomic_write_json(out / f"{name}_layout.json", doc)
    atomic_write_text(out / f"{name}_layout.obj", layout_obj_y_up(lay))
    write_rgb_png(out / f"{name}_wireframe.png", wire)
    if lay.get("ok"):
        from omnidl.postprocess.layout.mesh import save_layout_mesh
        for fmt in dict.fromkeys(mesh):    # the files were claimed above: replacing them here is allowed
            save_layout_mesh(lay, image, out / f"{name}_room.{fmt}", camera=cam_in, R_up_cam=R, overwrite=True)
    title = "layout" if lay.get("ok") else f"no layout: {lay.get('reason', '')}"
    _save_figure(out / f"{name}_figure.png", titled_row([("input", image), (title, wire)]))
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


def predict_upright(name: str, image: torch.Tensor, out: Path, options: UprightOptions = UprightOptions(),
                    claims: Any = None) -> list[Path]:
    """Upright alignment of one panorama: ``<name>_upright.png`` (input resolution), ``<name>_upright.json``
    (up vector, roll/pitch, ``R_up_cam``, segments), ``<name>_figure.png`` (input with its estimated horizon
    | upright panorama with the true horizon)."""
    from omnidl.cameras import Equirectangular
    if not _is_full_pano(image):
        raise ValueError(f"predict upright {name}: expected a full 360x180 panorama (width = 2 x height), got "
                         f"{image.shape[-1]}x{image.shape[-2]}")
    _claim(claims, upright_outputs(out, name))
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
