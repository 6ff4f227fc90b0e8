"""Accuracy of the weight-free upright alignment on synthetic rooms (issue 15's acceptance)::

    python -m omnidl.apps.predict.upright_eval --rooms 50 --max-tilt 30 --width 512 [--out upright_eval.json]

Each room is rendered by :mod:`omnidl.synth` with a random tilt up to ``--max-tilt`` degrees (uniform over the
cap); :func:`omnidl.geometry.upright.estimate_upright` estimates its up vector. Reported: the angle between the
estimated and true up vectors (median, 95th percentile, max), and the corner error that the tilt error alone
causes in ``omnidl predict layout``'s input-frame corners: the room's true corners against the same corners
taken through the estimated levelling and back (a perfect layout network), as HorizonNet's corner error (mean
L2 pixel distance over the image diagonal, %).
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Sequence

import numpy as np
import torch


def evaluate(rooms: int = 50, max_tilt: float = 30.0, width: int = 512, seed: int = 7, split: str = "test",
             progress: bool = False) -> dict:
    """Run the evaluation; returns the summary dict (per-room rows under ``"rooms"``)."""
    from omnidl.cameras import Equirectangular
    from omnidl.geometry.rotations import tilt_rotation, up_from_rotation
    from omnidl.geometry.upright import estimate_upright, up_error_deg
    from omnidl.synth import render_sample
    cam = Equirectangular(width=width, height=width // 2)
    diag = math.hypot(width, width // 2)
    rows = []
    for i in range(rooms):
        s = render_sample(cam, seed, split, i, rotation="random", max_tilt_deg=max_tilt, furniture=True)
        up_true = up_from_rotation(s["rotation"].double())
        t0 = time.perf_counter()
        est = estimate_upright(s["image"])
        dt = time.perf_counter() - t0
        err = up_error_deg(est.up, up_true) if est.ok else float("nan")
        # corners (tilted camera frame) vs the same corners levelled with the truth and un-levelled with the estimate
        X = s["corners_cam"].double()[s["corners_valid"]]                       # (K, 3)
        M = est.R_up_cam.T @ tilt_rotation(up_true)
        uv_t, ok_t = cam.project(X)
        uv_p, ok_p = cam.project(X @ M.T)
        d = uv_t - uv_p
        d[:, 0] = (d[:, 0] + width / 2) % width - width / 2                   # wrap across the seam
        ok = ok_t & ok_p
        ce = float(d[ok].norm(dim=-1).mean() / diag) if ok.any() else float("nan")   # fraction of the diagonal
        tilt = up_error_deg(up_true, torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64))
        rows.append({"room": i, "tilt_deg": tilt, "error_deg": err, "corner_error": ce, "ok": est.ok,
                     "segments": est.n_segments, "vertical_segments": est.n_vertical, "seconds": dt})
        if progress:
            print(f"room {i:3d}: tilt {tilt:5.1f} deg, error {err:.3f} deg, CE {100 * ce:.4f} %, {dt:.2f} s", flush=True)
    e = np.array([r["error_deg"] for r in rows], float)
    ce = np.array([r["corner_error"] for r in rows], float)
    ok = np.isfinite(e)
    return {"rooms": rows, "n": rooms, "n_ok": int(ok.sum()), "width": width, "max_tilt_deg": max_tilt,
            "median_deg": float(np.median(e[ok])) if ok.any() else float("nan"),
            "p95_deg": float(np.percentile(e[ok], 95)) if ok.any() else float("nan"),
            "max_deg": float(e[ok].max()) if ok.any() else float("nan"),
            "corner_error_mean": float(np.nanmean(ce)), "corner_error_median": float(np.nanmedian(ce)),
            "seconds_per_room": float(np.mean([r["seconds"] for r in rows]))}


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m omnidl.apps.predict.upright_eval", description=__doc__.split("\n\n")[0])
    ap.add_argument("--rooms", type=int, default=50)
    ap.add_argument("--max-tilt", type=float, default=30.0, help="degrees")
    ap.add_argument("--width", type=int, default=512, help="panorama width (height = width / 2)")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--out", default=None, help="write the JSON summary here")
    a = ap.parse_args(argv)
    res = evaluate(a.rooms, a.max_tilt, a.width, a.seed, progress=True)
    print(f"{res['n_ok']}/{res['n']} rooms at {a.width}x{a.width // 2}, tilts up to {a.max_tilt} deg: up-vector error "
          f"median {res['median_deg']:.3f} deg, p95 {res['p95_deg']:.3f} deg, max {res['max_deg']:.3f} deg; corner error "
          f"from the levelling {100 * res['corner_error_mean']:.4f} % of the diagonal (mean); {res['seconds_per_room']:.2f} s per room")
    if a.out:
        from omnidl.utils.io import atomic_write_json
        atomic_write_json(a.out, res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
