"""Robustness under CPU contention: how much each path slows down when a competing 2-thread process runs.

    python benchmarks/contention.py [--threads 2] [--reps 5] [--competitor-threads 2] [--max-seconds 120]

Each path is timed alone, then with a competitor process started by this script (a loop of 2-thread
1024x1024 float32 matrix products, killed when the script leaves and bounded by ``--max-seconds`` in any
case), then alone again; ``slowdown = loaded median / mean of the two alone medians``. The reference is
torchvision's ResNet-50 forward (dense convolutions), measured the same way in the same run. Target
(issue 17, item 6): every op-count-bound path's slowdown within 1.5x of ResNet-50's.

Paths: ResNet-50 forward 256x128 (reference); the photometric gyroscope (MPP 4 starts + PVG n = 5) with
``threads="auto"`` (its default, as ``Gyroscope.estimate`` runs it), on one thread and on all the process's
threads; the HoLiNet-small frame; a ProjectedConv2d (equirectangular camera) forward 64 ch 128x256 in NCHW (the
models' default memory format); the synth renderer 256x128 with layout ground truth, with ``threads="auto"``
(its default) and on all threads. The all-threads rows are shown for comparison and carry no target.

Why op-count-bound code collapses: every multi-threaded op is an OpenMP fork/join; with the cores shared, each
join waits until the descheduled worker runs again (a scheduler time slice, ms), so a path made of thousands of
10-100 us ops pays that wait thousands of times while a dense convolution pays it a few dozen times. Hence
``threads="auto"`` on the small-op paths (:func:`omnidl.utils.threads.auto_threads`: all threads while every one
has a free CPU, one when the run queue is longer than the CPUs); a ProjectedConv2d call is one op
(``torch.ops.omnidl.fixed_offset_conv2d``), whose CPU kernel runs one OpenMP parallel region per call.
"""
from __future__ import annotations

import argparse
import math
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._timing import host_line, load1, load_line, target_line  # noqa: E402

_COMPETITOR = """
import sys, time, torch
torch.set_num_threads(int(sys.argv[1]))
deadline = time.time() + float(sys.argv[2])
a = torch.randn(1024, 1024)
while time.time() < deadline:
    a = torch.tanh(a @ a)
"""


#: marks the rows shown for comparison only (all of the process's threads on a small-op path): no target line
NO_TARGET = "[comparison]"


def _paths(threads: int) -> dict:
    import torchvision

    from omnidl.cameras import Equirectangular, build
    from omnidl.geometry.rotations import random_tilt_rotation
    from omnidl.models import create_model
    from omnidl.nn import ProjectedConv2d
    from omnidl.utils.threads import limit_threads
    from omnidl.postprocess.gyroscope.mpp import mpp_yaw
    from omnidl.postprocess.gyroscope.pipeline import Gyroscope, GyroscopeOptions, model_horizon_fn
    from omnidl.postprocess.gyroscope.pvg import pvg_refine
    from omnidl.postprocess.gyroscope.scene import procedural_panorama
    from omnidl.synth import place_camera, render, sample_room

    torch.manual_seed(0)
    R = random_tilt_rotation(1, math.radians(20), generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    ref = procedural_panorama(None, 128, 256, seed=1)
    cur = procedural_panorama(R, 128, 256, seed=1)
    Rf = R.float()

    def photometric(n):
        def run():
            with limit_threads(n):
                r = mpp_yaw(cur, ref, Rf, tries=4)
                pvg_refine(cur, ref, r.rotation, level=5, max_iter=20)
        return run
    resnet = torchvision.models.resnet50().eval()
    small = create_model("holinet", backbone="resnet18", width=0.25, conv="std").eval()
    g = Gyroscope(None, GyroscopeOptions())  # frames taken as upright: MPP + PVG do the work
    g.set_reference(ref[0])
    net_fn = model_horizon_fn(small, 128)
    x = torch.rand(1, 3, 128, 256)
    layer = ProjectedConv2d(64, 64, 3, padding=1, camera=Equirectangular(width=256, height=128))
    xl = torch.randn(1, 64, 128, 256)
    cam = build({"type": "equirect", "width": 256, "height": 128})
    scene = sample_room(3)
    pose = place_camera(scene, cam, 3)

    def nograd(fn):
        def run():
            with torch.no_grad():
                fn()
        return run
    return {
        "resnet50 forward 256x128 (reference)": nograd(lambda: resnet(x)),
        "gyroscope photometric (MPP+PVG), threads='auto' (default)": photometric("auto"),
        "gyroscope photometric (MPP+PVG), 1 thread": photometric(1),
        f"gyroscope photometric (MPP+PVG), {threads} threads {NO_TARGET}": photometric(None),
        "gyroscope frame, HoLiNet-small + MPP + PVG": lambda: (net_fn(cur), g.estimate(cur)),
        "ProjectedConv2d 64ch 128x256 fwd": nograd(lambda: layer(xl)),
        "renderer 256x128 + layout GT, threads='auto' (default)": lambda: render(scene, cam, pose, layout=True),
        f"renderer 256x128 + layout GT, {threads} threads {NO_TARGET}": lambda: render(scene, cam, pose, threads=None),
    }


def _median_each(paths: dict, reps: int) -> dict:
    out = {k: [] for k in paths}
    for r in range(reps):
        for k in (list(paths) if r % 2 == 0 else list(paths)[::-1]):
            t0 = time.perf_counter()
            paths[k]()
            out[k].append(time.perf_counter() - t0)
    return {k: statistics.median(v) for k, v in out.items()}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--competitor-threads", type=int, default=2)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--max-seconds", type=float, default=120.0, help="hard bound of the competitor's life")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    paths = _paths(a.threads)
    for fn in paths.values():  # warm-up (plans, caches)
        fn()
    print(host_line())
    print(f"# contention benchmark: {a.threads} threads, competitor {a.competitor_threads}-thread matmul loop, "
          f"median of {a.reps} interleaved reps per phase")
    print(load_line(a.threads, "before (alone)"))
    busy = load1() > a.threads
    alone1 = _median_each(paths, a.reps)
    comp = subprocess.Popen([sys.executable, "-c", _COMPETITOR, str(a.competitor_threads), str(a.max_seconds)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            env={**os.environ, "OMP_NUM_THREADS": str(a.competitor_threads)})
    try:
        time.sleep(1.0)
        loaded = _median_each(paths, a.reps)
        print(load_line(a.threads + a.competitor_threads, "with the competitor"))
    finally:
        comp.kill()
        comp.wait()
    alone2 = _median_each(paths, a.reps)
    print(load_line(a.threads, "after (alone)"))
    busy = busy or load1() > a.threads
    ref_key = next(iter(paths))
    slow = {k: loaded[k] / ((alone1[k] + alone2[k]) / 2) for k in paths}
    print("| path | alone ms | with competitor ms | slowdown | / resnet50 slowdown |")
    print("|---|---|---|---|---|")
    for k in paths:
        al = (alone1[k] + alone2[k]) / 2
        print(f"| {k} | {al * 1e3:.1f} | {loaded[k] * 1e3:.1f} | {slow[k]:.2f}x | {slow[k] / slow[ref_key]:.2f} |")
    for k in list(paths)[1:]:
        if NO_TARGET in k:
            continue
        r = slow[k] / slow[ref_key]
        print(target_line(f"slowdown under load, {k}", f"{slow[k]:.2f}x", r, f"resnet50's {slow[ref_key]:.2f}x",
                          "<= 1.5x", r <= 1.5, loaded=busy))


if __name__ == "__main__":
    main()
