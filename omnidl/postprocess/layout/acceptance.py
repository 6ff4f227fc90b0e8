"""Acceptance study of the geometric pipeline on noise-free synthetic rooms (issue 6).

Rooms: floor plans of the data engine (:func:`omnidl.synth.sample_room`, Table A.2 limits, no
furniture) with the engine's camera placement (:func:`omnidl.synth.place_camera`, upright, rig
radius ``Rc``). Boundaries: computed exactly by this package's own analytic ray caster
(:mod:`.simulate`, an independent implementation of the non-central panorama), sub-pixel or rounded
to whole pixel rows; corner probabilities are HorizonNet's ``0.96^d`` targets of the visible corners.
Rooms whose camera sees an occlusion are reported separately (the thesis' Table 5.2 omits them).

    python -m omnidl.postprocess.layout.acceptance --n 200 [--width 1024 --rc 1.0 --out table.md]
"""
from __future__ import annotations

import argparse
import math
import time

import numpy as np

from ...metrics.layout import layout_scores
from .pipeline import estimate_layout
from .simulate import Room, simulate_columns, visible_corners


def engine_room(seed: int, manhattan: bool, rc: float) -> Room:
    """A data-engine room seen from an engine-placed upright camera, in the layout frame."""
    from ...cameras import build
    from ...synth import place_camera, sample_room
    from ...synth.room import is_manhattan
    from .rays import R_WORLD_FROM_CAM
    for k in range(100):
        scene = sample_room(seed * 1000 + k, manhattan_ratio=1.0 if manhattan else 0.4, furniture=False)
        if not manhattan and is_manhattan(scene.polygon, tol_deg=1e-3):
            continue
        cam = build({"type": "noncentral_pano", "width": 64, "height": 32, "rc": rc})
        try:   # the engine keeps the rig circle Rc + margin away from walls, floor and ceiling
            pose = place_camera(scene, cam, seed * 1000 + k, rotation="upright")
        except (ValueError, RuntimeError):
            continue
        R, t = pose[:3, :3], pose[:3, 3]
        P = np.c_[scene.polygon, np.zeros(len(scene.polygon))]
        cam_pts = (P - t) @ R                                   # R^T (X - t)
        lay = cam_pts @ R_WORLD_FROM_CAM.T
        return Room(lay[:, :2], float(scene.height - t[2]), float(-t[2]))
    raise RuntimeError("no room")


def run_study(n: int = 200, width: int = 1024, rc: float = 1.0, seed: int = 0, progress: bool = True) -> list[dict]:
    """Rows of the acceptance table (one per world x boundary kind)."""
    from tqdm import tqdm
    rows = []
    for world in ("manhattan", "atlanta"):
        rooms = [engine_room(seed + i, world == "manhattan", rc) for i in
                 tqdm(range(n), desc=f"{world} rooms", disable=not progress)]
        for quant in (False, True):
            res = {"ce": [], "iou_3d": [], "iou_3d_u2s": [], "cen": [], "iou_2d": [], "h_err": [], "occ": [],
                   "t": []}
            fails = 0
            for room in tqdm(rooms, desc=f"{world} {'rounded' if quant else 'sub-pixel'}", disable=not progress):
                rays, prob = simulate_columns(room, width, width // 2, rc, quantise=quant)
                t0 = time.perf_counter()
                lay = estimate_layout(rays, prob, world=world)
                res["t"].append(time.perf_counter() - t0)
                occluded = not visible_corners(room, rc).all()
                if not lay.ok:
                    fails += 1
                    continue
                s = layout_scores(lay.corners, (lay.h_floor, lay.h_ceiling), room.polygon,
                                  (room.h_floor, room.h_ceiling))
                for k in ("ce", "iou_3d", "iou_3d_u2s", "cen", "iou_2d"):
                    res[k].append(s[k])
                res["h_err"].append(max(abs(lay.h_ceiling - room.h_ceiling), abs(lay.h_floor - room.h_floor)))
                res["occ"].append(occluded)
            occ = np.array(res["occ"], bool)
            free = ~occ

            def m(key, mask=free):
                v = np.asarray(res[key])[mask]
                return float(np.mean(v)) if len(v) else math.nan
            rows.append({"world": world, "boundaries": "rounded" if quant else "sub-pixel", "rooms": n,
                         "occlusion_free": int(free.sum()), "failed": fails,
                         "ce_m": m("ce"), "iou_3d": m("iou_3d"), "iou_3d_u2s": m("iou_3d_u2s"), "cen": m("cen"),
                         "iou_2d": m("iou_2d"), "height_err_max_m": float(np.max(np.asarray(res["h_err"])[free]))
                         if free.any() else math.nan,
                         "height_err_mean_m": m("h_err"),
                         "ce_all_m": m("ce", np.ones_like(occ)), "iou_3d_all": m("iou_3d", np.ones_like(occ)),
                         "ms_per_layout": 1000 * float(np.mean(res["t"]))})
    return rows


def to_markdown(rows: list[dict], width: int, rc: float) -> str:
    head = (f"Noise-free synthetic rooms, {width}x{width // 2}, Rc = {rc} m (occlusion-free rooms; *_all: every room)\n\n"
            "| world | boundaries | rooms | occl.-free | failed | CE (m) | 3D IoU % | u2s IoU % | CEN % | 2D IoU % "
            "| max h err (m) | CE all (m) | 3D IoU all % | ms/layout |\n|" + "---|" * 14)
    lines = [head]
    for r in rows:
        lines.append(f"| {r['world']} | {r['boundaries']} | {r['rooms']} | {r['occlusion_free']} | {r['failed']} | "
                     f"{r['ce_m']:.4f} | {r['iou_3d']:.2f} | {r['iou_3d_u2s']:.2f} | {r['cen']:.3f} | {r['iou_2d']:.2f} | "
                     f"{r['height_err_max_m']:.4f} | {r['ce_all_m']:.4f} | {r['iou_3d_all']:.2f} | "
                     f"{r['ms_per_layout']:.1f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=200)
    ap.add_argument("--width", type=int, default=1024)
    ap.add_argument("--rc", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None, help="write the markdown table here (atomically)")
    a = ap.parse_args(argv)
    rows = run_study(a.n, a.width, a.rc, a.seed)
    md = to_markdown(rows, a.width, a.rc)
    print(md)
    if a.out:
        from ...utils.io import atomic_write_text
        atomic_write_text(a.out, md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
