"""Noise sensitivity of the solvers (thesis §5.6.2, Fig. 5.7): corner, direction and depth error vs the
standard deviation of Gaussian noise added to ground-truth boundary rows.

Rooms are exact synthetic rooms without occlusion (:mod:`.simulate`, seen by its circular panorama);
noise (``sigma`` pixel rows) is added to every column's ceiling and floor boundary, the walls' columns come from the
ground truth (a margin of 2 columns at each corner), and three solvers are compared, as in the thesis:

* ``single-wall``: §5.4.1 on each wall alone (its own heights; walls seen by fewer than 12 columns
  are left out);
* ``manhattan``: the Manhattan layout solver (Eq. 5.8) with the ground-truth wall labels;
* ``atlanta``: the Atlanta layout solver (Eq. 5.9) with the ground-truth wall directions (so its
  direction error is 0, as in Fig. 5.7b).

Metrics (Bermudez-Cameo et al. 2016): direction error ``arccos(|l . l_gt|)`` (degrees), depth error
``| |m| - |m_gt| |`` of the ceiling/floor lines (metres), corner error of consecutive line
intersections (metres). Writes ``noise_study.md`` and ``noise_study.png``.

    python -m omnidl.apps.layout.noise_study [--rooms 10 --sigmas 0 0.25 0.5 1 2 --width 512 --out DIR]
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from omnidl.postprocess.layout.corners import line_intersection
from omnidl.postprocess.layout.rays import column_rays
from omnidl.apps.layout.simulate import random_atlanta_room, random_manhattan_room, render_boundaries, ring_camera
from omnidl.postprocess.layout.solvers import atlanta_rows, manhattan_rows, solve_atlanta, solve_manhattan, solve_walls

SOLVERS = ("single-wall", "manhattan", "atlanta")
#: walls seen by fewer columns are left out of the single-wall statistics (the solver needs spread rays)
MIN_SINGLE_WALL_COLUMNS = 12


def _truth(room):
    P = room.polygon
    n = len(P)
    th, d = np.empty(n), np.empty(n)
    for k in range(n):
        e = P[(k + 1) % n] - P[k]
        t = math.atan2(e[1], e[0])
        nrm = np.array([-math.sin(t), math.cos(t)])
        if nrm @ P[k] < 0:
            t += math.pi
            nrm = -nrm
        th[k], d[k] = t, float(nrm @ P[k])
    return th, d


def _errors(th, d, h_c, h_f, th_gt, d_gt, room):
    dir_err = np.degrees(np.arccos(np.clip(np.abs(np.cos(th - th_gt)), 0, 1)))
    # |moment| of a horizontal line at height h and distance d from the vertical axis: sqrt(d^2 + h^2)
    dep = np.concatenate([np.abs(np.hypot(d, h_c) - np.hypot(d_gt, room.h_ceiling)),
                          np.abs(np.hypot(d, h_f) - np.hypot(d_gt, room.h_floor))])
    h_c, h_f = np.broadcast_to(h_c, th.shape), np.broadcast_to(h_f, th.shape)
    h_c2, h_f2 = np.roll(h_c, -1), np.roll(h_f, -1)
    n = len(th)
    X = line_intersection(th, d, np.roll(th, -1), np.roll(d, -1))
    G = np.roll(room.polygon, -1, 0)
    ce = np.concatenate([np.hypot(np.linalg.norm(X - G, axis=1), 0.5 * (h_c + h_c2) - room.h_ceiling),
                         np.hypot(np.linalg.norm(X - G, axis=1), 0.5 * (h_f + h_f2) - room.h_floor)])
    return float(np.nanmean(dir_err)), float(np.nanmean(dep)), float(np.nanmean(ce)) if n else math.nan


def run(rooms: int = 10, sigmas=(0.0, 0.25, 0.5, 1.0, 2.0), width: int = 512, rc: float = 1.0, seed: int = 0,
        reps: int = 2) -> dict:
    """``{solver: {"dir": [...], "depth": [...], "ce": [...]}}`` means over rooms x reps per sigma."""
    from tqdm import tqdm
    rng = np.random.default_rng(seed)
    camera = ring_camera(rc, width)
    res = {s: {"dir": [], "depth": [], "ce": []} for s in SOLVERS}
    room_list = [(random_manhattan_room(rng, rc=rc) if i % 2 == 0 else random_atlanta_room(rng, rc=rc))
                 for i in range(rooms)]
    for sigma in tqdm(sigmas, desc="noise levels"):
        acc = {s: {"dir": [], "depth": [], "ce": []} for s in SOLVERS}
        for room in room_list:
            rows, wall = render_boundaries(room, camera)
            th_gt, d_gt = _truth(room)
            n = len(room.polygon)
            for _ in range(reps):
                nc = rows[0] - rng.normal(0, sigma, width)
                nf = rows[1] - rng.normal(0, sigma, width)
                rays = column_rays(np.stack([nc, nf]), camera)
                cols = []
                for k in range(n):
                    c = np.flatnonzero((wall == k) & rays.valid)
                    cols.append(c[2:-2] if len(c) > 8 else c)
                if min(len(c) for c in cols) < 3:
                    continue
                idx = np.concatenate(cols)
                wid = np.concatenate([np.full(len(c), k) for k, c in enumerate(cols)])
                mc, mf = rays.moments("ceiling"), rays.moments("floor")
                # single wall
                th = np.empty(n); d = np.empty(n); hc = np.empty(n); hf = np.empty(n)
                for k, c in enumerate(cols):
                    if len(c) < MIN_SINGLE_WALL_COLUMNS:       # too few rays to fix a wall alone
                        th[k] = d[k] = hc[k] = hf[k] = np.nan
                        continue
                    f = solve_walls(rays.ceiling[c][None], mc[c][None], rays.floor[c][None], mf[c][None])
                    th[k], d[k], hc[k], hf[k] = f.theta[0], f.d[0], f.h_c[0], f.h_f[0]
                e = _errors(th, d, hc, hf, th_gt, d_gt, room)
                for key, v in zip(("dir", "depth", "ce"), e):
                    acc["single-wall"][key].append(v)
                # Manhattan (rooms with only two wall directions)
                if abs(np.sin(2 * (th_gt - th_gt[0]))).max() < 1e-6:
                    label = (np.abs(np.sin(th_gt - th_gt[0])) > 0.5).astype(int)
                    A = manhattan_rows(rays.ceiling[idx], mc[idx], rays.floor[idx], mf[idx], label, wid, n)
                    t0, dm, h_c, h_f, ok = solve_manhattan(A, label)
                    if ok:
                        thm = np.where(label == 0, t0, t0 + math.pi / 2)
                        flip = np.cos(thm - th_gt) < 0          # same line, canonical (theta, d > 0) form
                        thm, dm = np.where(flip, thm + math.pi, thm), np.where(flip, -dm, dm)
                        e = _errors(thm, dm, h_c, h_f, th_gt, d_gt, room)
                        for key, v in zip(("dir", "depth", "ce"), e):
                            acc["manhattan"][key].append(v)
                A = atlanta_rows(rays.ceiling[idx], mc[idx], rays.floor[idx], mf[idx], th_gt, wid, n)
                h_c, h_f, da, ok = solve_atlanta(A)
                if ok:
                    e = _errors(th_gt, da, h_c, h_f, th_gt, d_gt, room)
                    for key, v in zip(("dir", "depth", "ce"), e):
                        acc["atlanta"][key].append(v)
        for s in SOLVERS:
            for key in ("dir", "depth", "ce"):
                res[s][key].append(float(np.median(acc[s][key])) if acc[s][key] else math.nan)
    res["sigmas"] = list(map(float, sigmas))
    return res


def to_markdown(res: dict) -> str:
    lines = ["Median errors over rooms (noise sigma in pixel rows)\n",
             "| solver | sigma (px) | direction (deg) | depth (m) | corner (m) |", "|---|---|---|---|---|"]
    for s in SOLVERS:
        for i, sg in enumerate(res["sigmas"]):
            lines.append(f"| {s} | {sg:g} | {res[s]['dir'][i]:.4f} | {res[s]['depth'][i]:.4f} | {res[s]['ce'][i]:.4f} |")
    return "\n".join(lines) + "\n"


def plot(res: dict, path: str | Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from omnidl.utils.io import atomic_write
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.6))
    colours = {"single-wall": "tab:red", "manhattan": "tab:blue", "atlanta": "tab:green"}
    for j, (key, lab) in enumerate((("ce", "corner error (m)"), ("dir", "direction error (deg)"),
                                    ("depth", "depth error (m)"))):
        for s in SOLVERS:
            ax[j].plot(res["sigmas"], res[s][key], "-o", color=colours[s], label=s)
        ax[j].set_xlabel("noise sigma (px)")
        ax[j].set_ylabel(lab)
        if key != "ce":
            ax[j].set_yscale("symlog", linthresh=1e-3)
    ax[0].legend()
    fig.tight_layout()
    atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=110))
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rooms", type=int, default=10)
    ap.add_argument("--sigmas", type=float, nargs="+", default=[0.0, 0.25, 0.5, 1.0, 2.0])
    ap.add_argument("--width", type=int, default=512)
    ap.add_argument("--rc", type=float, default=1.0)
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="noise_study")
    a = ap.parse_args(argv)
    res = run(a.rooms, a.sigmas, a.width, a.rc, a.seed, a.reps)
    md = to_markdown(res)
    print(md)
    from omnidl.utils.io import atomic_write_text
    out = Path(a.out)
    atomic_write_text(out / "noise_study.md", md)
    plot(res, out / "noise_study.png")
    print(f"wrote {out / 'noise_study.md'} and {out / 'noise_study.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
