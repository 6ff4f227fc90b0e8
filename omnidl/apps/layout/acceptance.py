"""Acceptance study of the geometric pipeline on noise-free synthetic rooms.

Rooms: floor plans of the data engine (:func:`omnidl.synth.sample_room`, Table A.2 limits, no
furniture) with the engine's camera placement (:func:`omnidl.synth.place_camera`, upright, rig
radius ``Rc``). Boundaries: computed exactly by this package's own analytic ray caster
(:mod:`.simulate`, an independent implementation of the non-central panorama), sub-pixel or rounded
to whole pixel rows; corner probabilities are HorizonNet's ``0.96^d`` targets of the visible corners.
Every room counts in the acceptance means (the thesis' Table 5.2 omits occluded rooms); the table
also splits them into occlusion-free and occluded rooms, and the occluded ones by the longest run
of walls that no column sees (two or more consecutive hidden walls: the hidden part of the room is
not observable, only the smallest consistent room can be recovered).

    python -m omnidl.apps.layout.acceptance --n 200 [--protocol both|all|thesis --width 1024 --rc 1.0 --out table.md]
        [--all] [--no-progress]

The printed tables have the thesis' columns (CE, CEN, 3D IoU, 2D IoU over every room, failures, time);
``--all`` adds the occlusion breakdown (21 columns). CE in metres; CEN and IoU printed in % (columns labelled
``(%)``). The rows of :func:`run_study` keep omnidl's units: CEN and IoU as fractions in [0, 1].
"""
from __future__ import annotations

import argparse
import math
import time

import numpy as np

from omnidl.metrics.layout import layout_scores
from omnidl.postprocess.layout.pipeline import estimate_layout
from omnidl.apps.layout.simulate import Room, render_boundaries, ring_camera, simulate_columns, visible_corners


def engine_room(seed: int, manhattan: bool, rc: float) -> Room:
    """A data-engine room seen from an engine-placed upright camera, in the layout frame."""
    from omnidl.geometry.rotations import UPRIGHT_TO_WORLD
    from omnidl.synth import place_camera, sample_room
    from omnidl.synth.room import is_manhattan
    for k in range(100):
        scene = sample_room(seed * 1000 + k, manhattan_ratio=1.0 if manhattan else 0.4, furniture=False)
        if not manhattan and is_manhattan(scene.polygon, tol_deg=1e-3):
            continue
        cam = ring_camera(rc, 64)
        try:   # the engine keeps the rig circle Rc + margin away from walls, floor and ceiling
            pose = place_camera(scene, cam, seed * 1000 + k, rotation="upright")
        except (ValueError, RuntimeError):
            continue
        R, t = pose[:3, :3], pose[:3, 3]
        P = np.c_[scene.polygon, np.zeros(len(scene.polygon))]
        cam_pts = (P - t) @ R                                   # R^T (X - t)
        lay = cam_pts @ np.asarray(UPRIGHT_TO_WORLD).T
        return Room(lay[:, :2], float(scene.height - t[2]), float(-t[2]))
    raise RuntimeError("no room")


def hidden_run(room: Room, width: int, rc: float) -> int:
    """Longest run of consecutive walls that no panorama column sees (0: every wall is seen).

    A run of one hidden wall is fixed by the visible corners in a Manhattan room (the wall through
    the occluding corner, perpendicular to its neighbours); two or more consecutive hidden walls
    leave at least one offset unobservable from this viewpoint (only the smallest consistent room
    can be given), whatever the pipeline.
    """
    _, k = render_boundaries(room, ring_camera(rc, width))
    n = len(room.polygon)
    seen = np.zeros(n, bool)
    seen[np.unique(k[np.isfinite(k)].astype(int))] = True
    if seen.all():
        return 0
    if not seen.any():
        return n
    start = int(np.flatnonzero(seen)[0])
    best = run = 0
    for t in range(1, n + 1):
        run = 0 if seen[(start + t) % n] else run + 1
        best = max(best, run)
    return best


def sample_rooms(n: int, manhattan: bool, rc: float, seed: int = 0, occlusion_free: bool = False,
                 progress: bool = True) -> list[Room]:
    """``n`` engine rooms from consecutive seeds; with ``occlusion_free`` the occluded ones are skipped
    (the protocol of the thesis' Table 5.2) until ``n`` rooms without occlusion are collected."""
    from tqdm import tqdm
    rooms: list[Room] = []
    i = 0
    with tqdm(total=n, desc=f"{'manhattan' if manhattan else 'atlanta'} rooms", disable=not progress) as bar:
        while len(rooms) < n:
            room = engine_room(seed + i, manhattan, rc)
            i += 1
            if occlusion_free and not visible_corners(room, ring_camera(rc)).all():
                continue
            rooms.append(room)
            bar.update()
    return rooms


def run_study(n: int = 200, width: int = 1024, rc: float = 1.0, seed: int = 0, progress: bool = True,
              occlusion_free: bool = False) -> list[dict]:
    """Rows of the acceptance table (one per world x boundary kind); CE in metres, CEN and IoUs as fractions.

    Every room counts in the ``*_all`` means; the same means are also given on the occlusion-free
    rooms, on the occluded ones, and on the rooms with two or more consecutive hidden walls
    (``hidden2``, whose hidden part is not determined by the image). ``occlusion_free``: the ``n``
    rooms are the first ``n`` occlusion-free ones (the thesis' Table 5.2 protocol).
    """
    from tqdm import tqdm
    rows = []
    for world in ("manhattan", "atlanta"):
        rooms = sample_rooms(n, world == "manhattan", rc, seed, occlusion_free, progress)
        runs = np.array([hidden_run(r, width, rc) for r in rooms])
        camera = ring_camera(rc, width)
        occluded = np.array([not visible_corners(r, camera).all() for r in rooms])
        for quant in (False, True):
            keys = ("ce", "iou_3d", "iou_3d_u2s", "cen", "iou_2d", "h_err")
            res = {k: np.full(n, np.nan) for k in keys}
            ok = np.zeros(n, bool)
            times = []
            for i, room in enumerate(tqdm(rooms, desc=f"{world} {'rounded' if quant else 'sub-pixel'}",
                                          disable=not progress)):
                rays, prob = simulate_columns(room, camera, quantise=quant)
                t0 = time.perf_counter()
                lay = estimate_layout(rays, prob, world=world)
                times.append(time.perf_counter() - t0)
                if not lay.ok:
                    continue
                ok[i] = True
                sc = layout_scores(lay.corners, (lay.h_floor, lay.h_ceiling), room.polygon,
                                   (room.h_floor, room.h_ceiling))
                for k in keys[:-1]:
                    res[k][i] = sc[k]
                res["h_err"][i] = max(abs(lay.h_ceiling - room.h_ceiling), abs(lay.h_floor - room.h_floor))

            def m(key, mask=None):
                v = res[key][ok if mask is None else (ok & mask)]
                return float(np.mean(v)) if len(v) else math.nan
            row = {"world": world, "boundaries": "rounded" if quant else "sub-pixel", "rooms": n,
                   "occluded": int(occluded.sum()), "hidden2": int((runs >= 2).sum()), "failed": int((~ok).sum()),
                   "height_err_max_m": float(np.nanmax(res["h_err"])) if ok.any() else math.nan,
                   "ms_per_layout": 1000 * float(np.mean(times))}
            for key in keys[:-1]:
                row[f"{key}_all"] = m(key)
            for tag, mask in (("free", ~occluded), ("occ", occluded), ("hidden2", runs >= 2),
                              ("hidden1", occluded & (runs <= 1))):
                row[f"ce_{tag}"], row[f"iou_3d_{tag}"] = m("ce", mask), m("iou_3d", mask)
            rows.append(row)
    return rows


#: the compact table: (header, row key, digits) — the thesis' Table 5.2 columns over every room
COMPACT = (("rooms", "rooms", None), ("failed", "failed", None), ("CE (m) ↓", "ce_all", 4), ("CEN (%) ↓", "cen_all", 3),
           ("3D IoU (%) ↑", "iou_3d_all", 2), ("2D IoU (%) ↑", "iou_2d_all", 2), ("ms/layout", "ms_per_layout", 1))
#: row-key prefixes of fraction metrics, printed in percent in the "(%)" columns
PERCENT_KEYS = ("cen_", "iou_")


def _shown(key: str, v):
    """The printed value of row ``key``: fractions (CEN, IoU) in percent, anything else as is."""
    return 100.0 * v if key.startswith(PERCENT_KEYS) else v


def _cell(v, digits: int | None) -> str:
    if digits is None:
        return str(v)
    return "–" if not math.isfinite(v) else f"{v:.{digits}f}"


def to_markdown(rows: list[dict], width: int, rc: float, occlusion_free: bool = False, all_columns: bool = True) -> str:
    """The acceptance table: every column with ``all_columns`` (21), else the compact :data:`COMPACT` ones."""
    which = ("the first rooms without occlusion (the thesis' Table 5.2 protocol)" if occlusion_free else
             "consecutive rooms, occluded ones included")
    if not all_columns:
        head = [f"Noise-free synthetic rooms ({which}), {width}x{width // 2}, Rc = {rc} m; means over every room "
                "(--all: the occlusion breakdown).", "",
                "| world | boundaries | " + " | ".join(h for h, _, _ in COMPACT) + " |",
                "|" + "---|" * (2 + len(COMPACT))]
        body = [f"| {r['world']} | {r['boundaries']} | " + " | ".join(_cell(_shown(k, r[k]), d) for _, k, d in COMPACT)
                + " |"
                for r in rows]
        return "\n".join(head + body) + "\n"
    head = (f"Noise-free synthetic rooms ({which}), {width}x{width // 2}, Rc = {rc} m. *all*: every room of the "
            "table; then the occlusion-free rooms, the occluded ones, and among those the rooms with at most "
            "one / two or more consecutive walls that no column sees (*hidden 1* / *hidden >= 2*). CE in metres, "
            "CEN and IoU in %.\n\n"
            "| world | boundaries | rooms | occluded | hidden >= 2 | failed | CE all | 3D IoU (%) all | "
            "u2s IoU (%) all | CEN (%) all | 2D IoU (%) all | CE occl.-free | 3D IoU (%) occl.-free | CE occluded | "
            "3D IoU (%) occluded | CE hidden 1 | 3D IoU (%) hidden 1 | CE hidden >= 2 | 3D IoU (%) hidden >= 2 | "
            "max h err (m) | ms/layout |\n|"
            + "---|" * 21)
    lines = [head]

    def f(v: float, digits: int) -> str:
        return "–" if not math.isfinite(v) else f"{v:.{digits}f}"
    for r in rows:
        lines.append(
            f"| {r['world']} | {r['boundaries']} | {r['rooms']} | {r['occluded']} | {r['hidden2']} | {r['failed']} | "
            + " | ".join(f(_shown(k, r[k]), d) for k, d in (
                ("ce_all", 4), ("iou_3d_all", 2), ("iou_3d_u2s_all", 2), ("cen_all", 3), ("iou_2d_all", 2),
                ("ce_free", 4), ("iou_3d_free", 2), ("ce_occ", 4), ("iou_3d_occ", 2), ("ce_hidden1", 4),
                ("iou_3d_hidden1", 2), ("ce_hidden2", 4), ("iou_3d_hidden2", 2), ("height_err_max_m", 4),
                ("ms_per_layout", 1)))
            + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=200)
    ap.add_argument("--width", type=int, default=1024)
    ap.add_argument("--rc", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--protocol", choices=("both", "all", "thesis"), default="both",
                    help="'all': n consecutive rooms, occlusions included; 'thesis': the first n occlusion-free "
                         "rooms (Table 5.2 leaves occluded rooms out); 'both' (default): both tables")
    ap.add_argument("--out", default=None, help="write the markdown tables here (atomically; every column)")
    ap.add_argument("--all", action="store_true", help="print every column (the occlusion breakdown: 21 columns)")
    ap.add_argument("--no-progress", action="store_true", help="no progress bars")
    a = ap.parse_args(argv)
    for flag, value, low in (("--n", a.n, 1), ("--width", a.width, 16)):
        if value < low:
            ap.error(f"{flag} must be >= {low}, got {value}")
    if not (math.isfinite(a.rc) and a.rc >= 0):
        ap.error(f"--rc is the rig radius in metres, >= 0; got {a.rc}")
    studies = []
    for occlusion_free in {"all": (False,), "thesis": (True,), "both": (True, False)}[a.protocol]:
        rows = run_study(a.n, a.width, a.rc, a.seed, occlusion_free=occlusion_free, progress=not a.no_progress)
        studies.append((rows, occlusion_free))
    print("\n".join(to_markdown(rows, a.width, a.rc, free, all_columns=a.all) for rows, free in studies))
    if a.out:
        from omnidl.utils.io import atomic_write_text
        atomic_write_text(a.out, "\n".join(to_markdown(rows, a.width, a.rc, free) for rows, free in studies))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
