"""Layout pipeline CPU speed: mean time per layout for 6-wall Manhattan and Atlanta rooms (1024x512,
Rc = 1 m, boundaries rounded to whole rows as a network would give them), as ratios to

* ``loop-RANSAC``: the same pipeline with the RANSAC hypotheses solved one at a time in a Python loop
  (one SVD per hypothesis, 129 hypotheses per wall as in scaledLayout), measured in the same run;
* the reference pipeline's published CPU times (scaledLayout on the same kind of 2-core machine;
  ``docs/design.md#reference-layout-pipeline-scaledlayout``, figures in ``benchmarks/RESULTS.md``),
  printed for context only (not measured here).

    python benchmarks/layout.py [--threads 2] [--reps 20] [--json out.json]

Targets (issue 6): <= 20 ms Manhattan, <= 50 ms Atlanta per layout. The pipeline runs with
single-threaded BLAS (tiny matrices), so the CPU time of this process is reported as the main
figure (it is what an idle core gives); the wall clock and the load average are printed too.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._timing import load_line  # noqa: E402
from omnidl.postprocess.layout import estimate_layout  # noqa: E402
from omnidl.postprocess.layout import ransac as ransac_mod  # noqa: E402
from omnidl.apps.layout.simulate import Room, ring_camera, simulate_columns  # noqa: E402
from omnidl.postprocess.layout.solvers import WallFit, solve_walls  # noqa: E402

ROOMS = {
    # L-shaped Manhattan room, 6 walls, rotated 20 degrees
    "manhattan": Room(np.array([[-2.5, -2.0], [4.0, -2.0], [4.0, 1.5], [1.5, 1.5], [1.5, 4.0], [-2.5, 4.0]])
                      @ np.array([[np.cos(0.35), np.sin(0.35)], [-np.sin(0.35), np.cos(0.35)]]), 1.2, -1.4),
    # Atlanta room, 6 walls (two oblique)
    "atlanta": Room(np.array([[-2.5, -2.0], [3.0, -2.5], [4.0, 0.5], [2.0, 3.5], [-1.5, 4.0], [-3.0, 1.0]]), 1.2, -1.4),
}


def _looped_solve_walls(dir_c, mom_c, dir_f, mom_f, w_c=None, w_f=None):
    """Baseline: one hypothesis at a time (what a per-iteration Python RANSAC does)."""
    fits = [solve_walls(dir_c[i:i + 1], mom_c[i:i + 1], dir_f[i:i + 1], mom_f[i:i + 1],
                        None if w_c is None else w_c[i:i + 1], None if w_f is None else w_f[i:i + 1])
            for i in range(dir_c.shape[0])]
    cat = lambda k: np.concatenate([getattr(f, k) for f in fits])  # noqa: E731
    return WallFit(cat("theta"), cat("d"), cat("h_c"), cat("h_f"), cat("ok"), cat("cost"))


def time_layout(world: str, reps: int, looped: bool) -> tuple[float, bool]:
    rays, prob = simulate_columns(ROOMS[world], ring_camera(1.0, 1024), quantise=True)
    kw = {"ransac_outliers": 0.5} if looped else {}      # 0.5 -> 129 hypotheses per wall (scaledLayout)
    orig = ransac_mod.solve_walls
    if looped:
        ransac_mod.solve_walls = _looped_solve_walls
    try:
        lay = estimate_layout(rays, prob, world=world, **kw)
        t0, c0 = time.perf_counter(), time.process_time()
        for _ in range(reps):
            estimate_layout(rays, prob, world=world, **kw)
        dt = (time.perf_counter() - t0) / reps
        dc = (time.process_time() - c0) / reps
    finally:
        ransac_mod.solve_walls = orig
    return dt, dc, lay.ok


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    import torch
    torch.set_num_threads(a.threads)
    os.environ.setdefault("OMP_NUM_THREADS", str(a.threads))
    print(f"load average before: {os.getloadavg()}")
    print(load_line(1, "before (the pipeline runs single-threaded)"))
    ref = {"manhattan": (0.59, 1.29), "atlanta": (0.80, 3.17)}
    target = {"manhattan": 0.020, "atlanta": 0.050}
    out = {}
    for world in ("manhattan", "atlanta"):
        tw, t, ok = time_layout(world, a.reps, looped=False)
        tbw, tb, okb = time_layout(world, max(3, a.reps // 4), looped=True)
        print(f"{world:9s}: wall clock {1000 * tw:.2f} ms/layout (loop-RANSAC {1000 * tbw:.2f} ms); "
              "CPU time of this process (robust to other load) below")
        out[world] = {"ms_per_layout": 1000 * t, "wall_ms_per_layout": 1000 * tw, "ok": ok, "loop_ransac_ms": 1000 * tb,
                      "speedup_vs_loop_ransac": tb / t, "speedup_vs_reference_published": [ref[world][0] / t,
                                                                                          ref[world][1] / t],
                      "target_ms": 1000 * target[world], "meets_target": t <= target[world]}
        print(f"{world:9s}: {1000 * t:7.2f} ms/layout (ok={ok})  loop-RANSAC baseline {1000 * tb:7.2f} ms "
              f"-> x{tb / t:.1f};  vs reference published {ref[world][0]:.2f}-{ref[world][1]:.2f} s -> "
              f"x{ref[world][0] / t:.0f}-x{ref[world][1] / t:.0f};  target <= {1000 * target[world]:.0f} ms: "
              f"{'met' if t <= target[world] else 'NOT met'}")
        print(f"TARGET layout {world} (CPU time per layout): {1000 * t:.2f} ms = {t / tb:.2f}x the loop-RANSAC "
              f"baseline ({1000 * tb:.2f} ms) (target <= {1000 * target[world]:.0f} ms: "
              f"{'met' if t <= target[world] else 'MISSED'})")
    print(f"load average after: {os.getloadavg()}")
    print(load_line(1, "after"))
    if a.json:
        from omnidl.utils.io import atomic_write_json
        atomic_write_json(a.json, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
