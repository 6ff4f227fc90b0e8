"""Write rendered samples in the on-disk formats of the real datasets omnidl reads.

* ``noncentral`` — NonCentralIndoorDataset: ``img/NAME.png``, ``depth_coded/NAME.png`` (24-bit RGB fixed
  point, ``d = (R/255 + G/255^2 + B/255^3) * 10`` m), ``EM_gt/NAME.png`` (white structural edges),
  ``DataPython/3D_gt/NAME.npy`` (``2N x 3``: ceiling corners then floor corners), ``cam_pose/NAME.npy``
  (``1 x 3`` camera position), ``label_ang/NAME.npy`` (``3 x W``: azimuth, ceiling and floor boundary
  elevations per column, radians), ``label_cor/NAME.txt`` (``x y`` per line, ceiling then floor of each
  visible corner, sorted by x, 0-based pixel coordinates).
  Frame of the exported 3D data: right-handed, z up, x along the camera's heading, y to its left, so
  column ``x`` looks along azimuth ``theta = pi - 2 pi (x + 0.5) / W`` (the dataset's decreasing
  azimuth ``(1 - 2x/W) pi``, at pixel centres) with direction ``(cos theta, sin theta)``.
* ``stanford`` — Stanford2D3DS panoramas: ``<area>/pano/{rgb,depth,semantic}/camera_<id>_<room>_frame_
  equirectangular_domain_{rgb,depth,semantic}.png``, 16-bit depth in 1/512 m (65535 = missing), semantic
  PNG = 24-bit index into ``assets/semantic_labels.json`` (one label per omnidl class).
* ``horizonnet`` — ``img/NAME.png`` + ``label_cor/NAME.txt`` (corners in layout order, ceiling/floor pairs).
"""
from __future__ import annotations

import io
import json
from pathlib import Path

import cv2
import numpy as np
import torch

from omnidl.cameras.equirectangular import Equirectangular
from omnidl.classes import CLASS_COLORS, CLASS_NAMES
from omnidl.utils.io import atomic_imwrite, atomic_write_bytes, atomic_write_text

DEPTH_CODED_MAX = 10.0
STANFORD_DEPTH_SCALE = 512.0
FORMATS = ("noncentral", "stanford", "horizonnet")


# -- depth coding ------------------------------------------------------------------------------------
def encode_depth_24bit(depth: np.ndarray, d_max: float = DEPTH_CODED_MAX) -> np.ndarray:
    """``(H, W)`` metres -> ``(H, W, 3)`` uint8 RGB with ``d = (R/255 + G/255^2 + B/255^3) * d_max``."""
    x = np.clip(np.asarray(depth, np.float64), 0.0, d_max) / d_max * 255.0
    r = np.floor(x)
    x = (x - r) * 255.0
    g = np.floor(x)
    b = np.rint((x - g) * 255.0)
    carry = b > 255
    b = np.where(carry, 255, b)
    return np.stack([r, g, b], -1).clip(0, 255).astype(np.uint8)


def decode_depth_24bit(rgb: np.ndarray, d_max: float = DEPTH_CODED_MAX) -> np.ndarray:
    """Inverse of :func:`encode_depth_24bit` (RGB channel order)."""
    c = np.asarray(rgb, np.float64)
    return (c[..., 0] / 255.0 + c[..., 1] / 255.0 ** 2 + c[..., 2] / 255.0 ** 3) * d_max


# -- helpers -------------------------------------------------------------------------------------------
def to_uint8_rgb(image) -> np.ndarray:
    return (np.asarray(image.permute(1, 2, 0)) * 255.0 + 0.5).clip(0, 255).astype(np.uint8)


def _write_png_rgb(path: Path, rgb: np.ndarray) -> None:
    atomic_imwrite(path, np.ascontiguousarray(rgb[..., ::-1]) if rgb.ndim == 3 else rgb)


def _write_npy(path: Path, arr: np.ndarray) -> None:
    buf = io.BytesIO()
    np.save(buf, arr)
    atomic_write_bytes(path, buf.getvalue())


def _require_upright(sample: dict, fmt: str) -> None:
    rot = np.asarray(sample["rotation"])
    if np.abs(rot - np.eye(3)).max() > 1e-5:
        raise ValueError(f"format {fmt!r} needs gravity-aligned cameras (use --rotation upright)")


def heading_frame(pose: np.ndarray) -> np.ndarray:
    """``(3, 3)`` rows = export axes in the world frame: camera heading, its left, up (upright cameras)."""
    R = np.asarray(pose, np.float64)[:3, :3]
    return np.stack([R[:, 2], -R[:, 0], np.cross(R[:, 2], -R[:, 0])])


def sample_name(fmt: str, index: int, rc: float) -> str:
    if fmt == "noncentral":   # scaledLayout parses Rc from '..._R<rc * 1e4 as 5 digits>'
        return f"SYN{index:05d}_R{int(round(rc * 1e4)):05d}"
    if fmt == "stanford":
        return f"camera_{index:05d}_synthroom_{index}_frame_equirectangular_domain"
    return f"synth_{index:05d}"


def expected_files(out: Path, fmt: str, name: str, area: str = "area_1") -> list[Path]:
    """Files one sample writes (the writer writes the first one last, so it marks a finished sample)."""
    if fmt == "noncentral":
        return [out / "img" / f"{name}.png", out / "depth_coded" / f"{name}.png", out / "EM_gt" / f"{name}.png",
                out / "DataPython" / "3D_gt" / f"{name}.npy", out / "DataPython" / "cam_pose" / f"{name}.npy",
                out / "DataPython" / "label_ang" / f"{name}.npy", out / "DataPython" / "label_cor" / f"{name}.txt"]
    if fmt == "stanford":
        pano = out / area / "pano"
        return [pano / "rgb" / f"{name}_rgb.png", pano / "depth" / f"{name}_depth.png",
                pano / "semantic" / f"{name}_semantic.png"]
    if fmt == "horizonnet":
        return [out / "img" / f"{name}.png", out / "label_cor" / f"{name}.txt"]
    raise ValueError(f"unknown format {fmt!r}; expected one of {FORMATS}")


def label_cor_lines(sample: dict, layout_order: bool) -> str:
    """``x y`` lines (0-based pixels) of visible corners: ceiling then floor per corner."""
    n = int(sample["num_walls"])
    uv = np.asarray(sample["corners_uv"])[:n] - 0.5
    ok = np.asarray(sample["corners_valid"])[:n].all(-1)
    idx = np.nonzero(ok)[0]
    if not layout_order:
        idx = idx[np.argsort(uv[idx, 1, 0])]
    lines = []
    for k in idx:
        for j in (0, 1):
            lines.append(f"{uv[k, j, 0]:.2f} {uv[k, j, 1]:.2f}")
    return "\n".join(lines) + "\n"


# -- writers --------------------------------------------------------------------------------------------
def _label_angles(boundary: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """The dataset's ``label_ang`` angles of boundary rows ``(2, W)``: ``theta (W,)`` (its azimuth, the negated
    omnidl longitude of each column centre) and ``elev (2, W)`` (the latitude of each boundary row), asked of
    the equirect camera of the image."""
    cam = Equirectangular(width=width, height=height)
    u = torch.arange(width, dtype=torch.float64) + 0.5
    uv = torch.stack([u.expand(2, width), torch.as_tensor(boundary, dtype=torch.float64)], -1)
    lon, lat = cam.uv_to_lonlat(uv)
    return -lon[0].numpy(), lat.numpy()


def write_sample(out: Path, fmt: str, name: str, sample: dict, area: str = "area_1") -> None:
    """Write one rendered sample (the dict of :func:`omnidl.synth.render`) in format ``fmt``."""
    files = expected_files(out, fmt, name, area)
    rgb = to_uint8_rgb(sample["image"])
    depth = np.asarray(sample["depth"][0], np.float64)
    if fmt == "noncentral":
        _require_upright(sample, fmt)
        n = int(sample["num_walls"])
        A = heading_frame(np.asarray(sample["pose"], np.float64))
        cw = np.asarray(sample["corners_world"], np.float64)[:n]
        gt = np.concatenate([cw[:, 0], cw[:, 1]]) @ A.T
        cam = (A @ np.asarray(sample["pose"], np.float64)[:3, 3])[None]
        H, W = depth.shape
        theta, elev = _label_angles(np.asarray(sample["boundary"], np.float64), W, H)
        elev = np.where(np.asarray(sample["boundary_valid"]), elev, 0.0)  # 0 = not seen
        _write_png_rgb(files[1], encode_depth_24bit(np.where(np.asarray(sample["valid"]), depth, 0.0)))
        atomic_imwrite(files[2], (np.asarray(sample["edges"][0]) * 255).astype(np.uint8))
        _write_npy(files[3], gt)
        _write_npy(files[4], cam)
        _write_npy(files[5], np.stack([theta, elev[0], elev[1]]))
        atomic_write_text(files[6], label_cor_lines(sample, layout_order=False))
        _write_png_rgb(files[0], rgb)
    elif fmt == "stanford":
        d16 = np.where(np.asarray(sample["valid"]), np.clip(np.rint(depth * STANFORD_DEPTH_SCALE), 0, 65534),
                       65535).astype(np.uint16)
        sem = np.asarray(sample["semantic"]).astype(np.int64)
        code = np.where(np.asarray(sample["valid"]), sem, 0x0D0D0D)
        sem_rgb = np.stack([(code >> 16) & 255, (code >> 8) & 255, code & 255], -1).astype(np.uint8)
        atomic_imwrite(files[1], d16)
        _write_png_rgb(files[2], sem_rgb)
        _write_png_rgb(files[0], rgb)
        labels = out / "assets" / "semantic_labels.json"
        if not labels.exists():
            names = ["<UNK>_0_<UNK>_0_0"] + [f"{c}_0_synthroom_0_synth" for c in CLASS_NAMES[1:]]
            atomic_write_text(labels, json.dumps(names) + "\n")
    elif fmt == "horizonnet":
        _require_upright(sample, fmt)
        atomic_write_text(files[1], label_cor_lines(sample, layout_order=True))
        _write_png_rgb(files[0], rgb)
    else:
        raise ValueError(f"unknown format {fmt!r}; expected one of {FORMATS}")


# -- contact sheet ----------------------------------------------------------------------------------------
def _colour_depth(depth: np.ndarray, valid: np.ndarray) -> np.ndarray:
    d = np.clip(depth / max(float(depth[valid].max()) if valid.any() else 1.0, 1e-6), 0, 1)
    bgr = cv2.applyColorMap((d * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    bgr[~valid] = 0
    return bgr[..., ::-1]


def _colour_semantic(sem: np.ndarray) -> np.ndarray:
    lut = np.array(CLASS_COLORS, np.uint8)
    return lut[np.clip(sem, 0, len(lut) - 1)]


def _wireframe(sample: dict) -> np.ndarray:
    img = (to_uint8_rgb(sample["image"]) * 0.6).astype(np.uint8)
    H, W = img.shape[:2]
    edges = np.asarray(sample["edges"][0]) > 0
    img[edges] = (255, 255, 255)
    b, ok = np.asarray(sample["boundary"]), np.asarray(sample["boundary_valid"])
    cols = np.arange(W)
    for j, colour in ((0, (80, 255, 80)), (1, (255, 80, 80))):
        r = np.clip(np.floor(b[j]).astype(int), 0, H - 1)
        img[r[ok[j]], cols[ok[j]]] = colour
    heat = np.asarray(sample["corner_heat"][0])
    img[:max(2, H // 40)] = (np.clip(heat, 0, 1)[None, :, None] * np.array([255, 255, 0])).astype(np.uint8)
    return img


def contact_sheet(samples: list[dict], tile_width: int = 512) -> np.ndarray:
    """RGB ``uint8`` grid: one row per sample, columns RGB | depth | semantics | layout wireframe."""
    rows = []
    for s in samples:
        valid = np.asarray(s["valid"])
        tiles = [to_uint8_rgb(s["image"]), _colour_depth(np.asarray(s["depth"][0]), valid),
                 _colour_semantic(np.asarray(s["semantic"])), _wireframe(s)]
        H, W = valid.shape
        th = max(1, int(round(H * tile_width / W)))
        tiles = [cv2.resize(np.ascontiguousarray(t), (tile_width, th), interpolation=cv2.INTER_AREA) for t in tiles]
        sep = np.full((th, 4, 3), 255, np.uint8)
        row = np.concatenate([x for t in tiles for x in (t, sep)][:-1], 1)
        rows.append(row)
        rows.append(np.full((4, row.shape[1], 3), 255, np.uint8))
    return np.concatenate(rows[:-1], 0) if rows else np.zeros((1, 1, 3), np.uint8)


def write_contact_sheet(path: Path, samples: list[dict], tile_width: int = 512) -> None:
    _write_png_rgb(Path(path), contact_sheet(samples, tile_width))
