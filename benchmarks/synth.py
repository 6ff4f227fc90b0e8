"""Speed of the built-in data engine (omnidl.synth): one panorama with RGB, depth, semantics, normals and layout.

    python benchmarks/synth.py [--threads 2] [--reps 7] [--profile]

Targets (issue 17, item 5; issue 4 had 0.5 s / 50 ms): 1024x512 <= 150 ms and 256x128 <= 25 ms on 2 CPU cores. The named baseline measured in
the same run is ``brute force``: the same render with object culling disabled (every box slab-tested
against every pixel); the ratio baseline / engine is printed next to the absolute medians. ``previous``
is the renderer before the issue-17 speed work (``tests/reference/synth_renderer.py``, same outputs to float32
rounding),
timed interleaved with the engine (``--no-previous`` skips it). Process CPU
time is printed too: on a shared machine it is the steadier figure (wall time includes waiting for cores).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._timing import (host_line, interleaved, is_loaded, load_line, median_times, ratio,  # noqa: E402
                               target_line)
from omnidl.cameras import build  # noqa: E402
from omnidl.synth import place_camera, render, sample_room  # noqa: E402
from omnidl.synth import raycast  # noqa: E402
from tests.reference.synth_renderer import render_reference  # noqa: E402


class _BruteForce:
    """Context manager: cast_boxes without culling (one group per box, every pixel a candidate)."""

    def __enter__(self):
        self.orig = raycast.cast_boxes

        def brute(origin, direction, boxes, groups, t_best, centre, rig_radius, **_culling):
            # the engine's culling inputs (tile candidates, group spheres) are dropped: every ray, every box
            single = [torch.tensor([i]) for g in groups for i in g.tolist()]
            return self.orig(origin, direction, boxes, single, t_best, centre, rig_radius, cull=False)

        import sys
        r = sys.modules["omnidl.synth.render"]   # the module (omnidl.synth.render is the function)
        self.r = r
        r.cast_boxes = brute
        return self

    def __exit__(self, *exc):
        self.r.cast_boxes = self.orig


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--reps", type=int, default=7)
    p.add_argument("--seeds", type=int, nargs="+", default=[3, 11, 42])
    p.add_argument("--cameras", nargs="+", default=["equirect", "noncentral_pano"])
    p.add_argument("--profile", action="store_true")
    p.add_argument("--no-previous", dest="previous", action="store_false",
                   help="skip the interleaved timing of the previous renderer (tests/reference/synth_renderer.py)")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {args.threads} threads, median of {args.reps}")
    print(host_line(), flush=True)
    print(load_line(args.threads, "at start"), flush=True)
    targets = {(1024, 512): 0.15, (256, 128): 0.025}  # issue 17, item 5 (issue 4: 0.5 s / 50 ms)
    for cam_type in args.cameras:
        for (w, h), target in targets.items():
            cfg = {"type": cam_type, "width": w, "height": h}
            if cam_type == "noncentral_pano":
                cfg["rc"] = 1.0
            cam = build(cfg)
            for seed in args.seeds:
                sc = sample_room(seed)
                try:
                    pose = place_camera(sc, cam, seed)
                except RuntimeError:
                    continue
                t_engine, c_engine = median_times(lambda: render(sc, cam, pose, layout=True), args.reps)
                with _BruteForce():
                    t_brute, _ = median_times(lambda: render(sc, cam, pose, layout=True), max(3, args.reps // 2))
                print(f"{cam_type:16s} {w:4d}x{h:<4d} seed {seed:3d}: {sc.num_primitives:3d} primitives "
                      f"({sc.num_walls} walls, {len(sc.boxes)} boxes, {len(sc.decals)} openings) | engine "
                      f"{t_engine * 1e3:7.1f} ms wall, {c_engine * 1e3:7.1f} ms CPU (target {target * 1e3:.0f} ms: wall "
                      f"{t_engine / target:.2f}x, CPU/threads {c_engine / args.threads / target:.2f}x) | brute force {t_brute * 1e3:7.1f} ms | speed-up "
                      f"x{t_brute / t_engine:.2f}", flush=True)
                print(target_line(f"render {cam_type} {w}x{h} seed {seed} (layout GT)", f"{t_engine * 1e3:.1f} ms",
                                  t_engine / t_brute, "brute force", f"<= {target * 1e3:.0f} ms", t_engine <= target,
                                  is_loaded(args.threads)), flush=True)
                if args.previous:
                    times = interleaved({"engine": lambda: render(sc, cam, pose, layout=True),
                                         "previous": lambda: render_reference(sc, cam, pose, layout=True)}, args.reps)
                    med = {k: sorted(v)[len(v) // 2] for k, v in times.items()}
                    print(f"{'':16s} {w:4d}x{h:<4d} seed {seed:3d}: interleaved engine {med['engine'] * 1e3:7.1f} ms, "
                          f"previous renderer {med['previous'] * 1e3:7.1f} ms: engine/previous "
                          f"{ratio(times, 'engine', 'previous'):.2f}x", flush=True)
    print(load_line(args.threads, "at end"), flush=True)
    t_room = median_times(lambda: [sample_room(s) for s in range(20)], 3)[0] / 20
    print(f"room sampling (floor plan + furniture): {t_room * 1e3:.1f} ms per room")
    if args.profile:
        import cProfile
        import pstats
        cam = build({"type": "equirect", "width": 1024, "height": 512})
        sc = sample_room(args.seeds[0])
        pose = place_camera(sc, cam, args.seeds[0])
        render(sc, cam, pose)
        prof = cProfile.Profile()
        prof.enable()
        render(sc, cam, pose)
        prof.disable()
        pstats.Stats(prof).sort_stats("tottime").print_stats(20)


if __name__ == "__main__":
    main()
