"""Tiny layout datasets written in the public formats (PanoAnnotator JSON, ZInD zind_data.json), from their specs.

Rooms are top-view polygons in omnidl's layout frame (x right, y forward, z up; camera at the origin).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np

ROOMS = {
    "box": np.array([[-1.5, -2.0], [2.0, -2.0], [2.0, 1.5], [-1.5, 1.5]]),
    "ell": np.array([[-1.0, -1.5], [3.0, -1.5], [3.0, 0.5], [1.0, 0.5], [1.0, 2.5], [-1.0, 2.5]]),
    "slant": np.array([[-1.8, -1.2], [1.6, -2.0], [2.4, 1.0], [0.2, 2.2], [-1.6, 1.4]]),
}


def paint_room(polygon: np.ndarray, camera_height: float, ceiling_height: float, w: int, h: int,
               seed: int = 0) -> np.ndarray:
    """``(h, w, 3)`` uint8 RGB: ceiling / wall / floor colours split at the room's boundary rows, plus noise."""
    from omnidl.cameras import Equirectangular
    from omnidl.data.layout_targets import room_boundary_rows
    rows, _ = room_boundary_rows(polygon, ceiling_height, -camera_height, Equirectangular(width=w, height=h))
    v = np.arange(h)[:, None] + 0.5
    img = np.empty((h, w, 3), np.float64)
    img[:] = (200, 200, 190)
    img[v < rows[0][None]] = (240, 240, 250)
    img[v > rows[1][None]] = (120, 90, 60)
    img += np.random.default_rng(seed).normal(0, 8, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def pano_annotator_label(polygon: np.ndarray, camera_height: float, ceiling_height: float) -> dict:
    """A PanoAnnotator ``saveSceneAsJson`` dict: points in its frame (x right, y up, z backward) on the floor."""
    pts, walls = [], []
    k = len(polygon)
    for i, (x, y) in enumerate(polygon):
        xyz = [float(x), -float(camera_height), -float(y)]
        lon = math.atan2(xyz[0], -xyz[2])
        lat = math.atan2(xyz[1], math.hypot(xyz[0], xyz[2]))
        pts.append({"coords": [lon / (2 * math.pi) + 0.5, 0.5 - lat / math.pi], "depth": 1.0, "xyz": xyz, "id": i})
        walls.append({"pointsIdx": [i, (i + 1) % k], "normal": [0.0, 0.0, 1.0], "planeEquation": [0, 0, 1, 0],
                      "width": 1.0, "id": i})
    return {"name": "color.png", "cameraHeight": camera_height, "layoutHeight": camera_height + ceiling_height,
            "cameraCeilingHeight": ceiling_height, "layoutPoints": {"num": k, "points": pts},
            "layoutWalls": {"num": k, "walls": walls}}


def write_pano_annotator(root: Path, w: int = 64, h: int = 32, splits: dict | None = None,
                         rooms: dict | None = None) -> dict:
    """``root/image``, ``root/label``, ``root/split``; returns ``{name: (polygon, camera_height, ceiling)}``."""
    rooms = rooms or ROOMS
    (root / "image").mkdir(parents=True, exist_ok=True)
    (root / "label").mkdir(parents=True, exist_ok=True)
    truth = {}
    for i, (room, poly) in enumerate(rooms.items()):
        name = f"scene{i}_{room}"
        ch, ceil = 1.4 + 0.1 * i, 1.2 + 0.05 * i
        cv2.imwrite(str(root / "image" / f"{name}.png"), paint_room(poly, ch, ceil, w, h, i)[..., ::-1])
        (root / "label" / f"{name}.json").write_text(json.dumps(pano_annotator_label(poly, ch, ceil), indent=1))
        truth[name] = (poly, ch, ceil)
    names = list(truth)
    splits = splits if splits is not None else {"train": names, "val": names[:2], "test": names[1:]}
    (root / "split").mkdir(exist_ok=True)
    for split, ns in splits.items():
        (root / "split" / f"{split}.txt").write_text("".join(" ".join(n.split("_", 1)) + "\n" for n in ns))
    return truth


def zind_pano(polygon: np.ndarray, units: float, ceiling_norm: float = 1.8, image_path: str = "panos/p.jpg",
              layouts=("visible", "complete", "raw"), **extra) -> dict:
    """One ZInD pano entry: vertices in its local frame (``(-x_l, y_l) / units``), camera height 1.0."""
    v = np.stack([-polygon[:, 0], polygon[:, 1]], -1) / units
    lay = {"vertices": v.tolist(), "windows": [], "doors": [], "openings": [], "internal": []}
    pano = {"label": "room", "is_primary": True, "is_inside": True, "is_ceiling_flat": True,
            "ceiling_height": ceiling_norm, "camera_height": 1.0, "floor_number": 1, "image_path": image_path,
            "floor_plan_transformation": {"translation": [0.5, -0.25], "rotation": 30.0, "scale": 2.0}}
    for name in layouts:
        pano[f"layout_{name}"] = json.loads(json.dumps(lay))
    pano.update(extra)
    return pano


def write_zind(root: Path, w: int = 64, h: int = 32, metres_per_unit: float = 1.5, houses=("0000", "0001"),
               partition: dict | None = None, rooms: dict | None = None) -> dict:
    """A ZInD tree; floor scale ``metres_per_unit / transformation scale (2.0)``. Returns ``{name: (poly, ch, ceil)}``
    with heights in metres."""
    rooms = rooms or ROOMS
    truth = {}
    for hi, house in enumerate(houses):
        hd = root / house
        (hd / "panos").mkdir(parents=True, exist_ok=True)
        merger: dict = {"floor_01": {}}
        for i, (room, poly) in enumerate(rooms.items()):
            key = f"pano_{i + 1}"
            img = f"panos/floor_01_partial_room_0{i + 1}_{key}.jpg"
            ceiling_norm = 1.8 + 0.1 * i
            merger["floor_01"][f"complete_room_0{i + 1}"] = {
                f"partial_room_0{i + 1}": {key: zind_pano(poly, metres_per_unit, ceiling_norm, img)}}
            ch, ceil = metres_per_unit, (ceiling_norm - 1.0) * metres_per_unit
            cv2.imwrite(str(hd / img), paint_room(poly, ch, ceil, w, h, 10 * hi + i)[..., ::-1])
            truth[f"{house}_floor_01_{key}"] = (poly, ch, ceil)
        data = {"scale_meters_per_coordinate": {"floor_01": metres_per_unit / 2.0}, "merger": merger,
                "redraw": {}, "floorplan_to_redraw_transformation": {}}
        (hd / "zind_data.json").write_text(json.dumps(data))
    partition = partition if partition is not None else {"train": list(houses), "val": list(houses[:1]),
                                                         "test": list(houses[1:])}
    (root / "zind_partition.json").write_text(json.dumps(partition))
    return truth


def write_structured3d(root: Path, scenes=("scene_00000", "scene_03000", "scene_03250"), w: int = 64, h: int = 32,
                       variant: str = "full") -> dict:
    """One room per scene: RGB, depth (mm), semantic (NYU40 ids) and layout.txt of a box room (label_cor)."""
    from omnidl.metrics.layout_protocol import corner_pixels
    rng = np.random.default_rng(3)
    truth = {}
    for sc in scenes:
        pano = root / sc / "2D_rendering" / "485142" / "panorama"
        (pano / variant).mkdir(parents=True, exist_ok=True)
        rgb = paint_room(ROOMS["box"], 1.6, 1.2, w, h)
        mm = rng.integers(0, 12000, (h, w)).astype(np.uint16)
        sem = rng.integers(0, 41, (h, w)).astype(np.uint8)
        cv2.imwrite(str(pano / variant / "rgb_rawlight.png"), rgb[..., ::-1])
        cv2.imwrite(str(pano / variant / "depth.png"), mm)
        cv2.imwrite(str(pano / variant / "semantic.png"), sem)
        cor = corner_pixels(ROOMS["box"], (-1.6, 1.2), w, h).reshape(-1, 2) - 0.5
        (pano / "layout.txt").write_text("".join(f"{x:.3f} {y:.3f}\n" for x, y in cor))
        (pano / "camera_xyz.txt").write_text("100 200 1600\n")
        truth[f"{sc}_485142_{variant}"] = (rgb, mm, sem)
    return truth


def instantiate_split(tmp_path: Path, data: str, root: Path, split: str = "test", overrides=()):
    """Compose ``configs/train.yaml`` with ``data=<data> data.root=<root>`` and build ``data.<split>``."""
    from hydra.utils import instantiate
    from tests.engine.engine_helpers import make_cfg
    cfg = make_cfg(tmp_path / "cfg", [f"data={data}", f"data.root={root}", *overrides], standin=False)
    return instantiate(cfg.data[split], _convert_="all")
