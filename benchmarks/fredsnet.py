"""FreDSNet CPU speed: forward at 512x256 and forward+backward at 256x128, batch 1, as ratios to
torchvision's ResNet-50 forward measured in the same run.

    python benchmarks/fredsnet.py [--threads 2] [--reps 5] [--extra-equi backbone wconv,heads] [--json out.json]
    python benchmarks/fredsnet.py --scaling [--threads 2] [--reps 5]   # forward growth 512x256 -> 1024x512

Protocol: ``torch.set_num_threads(threads)``, random weights, batch 1, 2 warm-up runs (the Equi layers compute
their sample positions at the first);
forward = ``eval()`` + ``no_grad``; forward+backward = ``train()``, loss
``CE(semantic, random labels) + L1(depth, random)``, ``zero_grad`` + forward + backward.
The timed runs are **interleaved**: each repetition times the baseline and every variant once, so
that a change of machine load hits all of them alike; ratios are medians of the per-repetition
ratios, absolute times medians (and minima) over repetitions. The 512x256 forwards run as one phase
and the 256x128 jobs (training steps with their baseline forward) as the next: forwards back to back,
as in inference (a training step in between returns its buffers to the OS and the next forward page-faults them
in again). The load average is printed: absolute
numbers taken on a busy machine are not comparable with anything.
Targets (issue 5): FreDSNet-Std forward <= 0.8 s and FreDSNet-Equi <= 1.3x Std.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Callable

import torch
import torch.nn.functional as F
import torchvision

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._timing import allocator_tag, host_line, load_line  # noqa: E402
from omnidl.cameras import Equirectangular  # noqa: E402
from omnidl.models.fredsnet import FreDSNet, count_parameters  # noqa: E402


def forward_fn(model: torch.nn.Module, h: int, w: int) -> Callable[[], None]:
    x = torch.rand(1, 3, h, w)

    def run():
        model.eval()
        with torch.no_grad():
            model(x)
    return run


def train_step_fn(model: torch.nn.Module, h: int, w: int) -> Callable[[], None]:
    x = torch.rand(1, 3, h, w)
    labels = torch.randint(0, 14, (1, h, w))
    depth = torch.rand(1, 1, h, w) * 5

    def run():
        model.train()
        model.zero_grad(set_to_none=True)
        out = model(x)
        loss = F.cross_entropy(out["semantic"], labels) + F.l1_loss(out["depth"], depth)
        loss.backward()
    return run


def _timed(fn: Callable[[], None]) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--warmup", type=int, default=2, help="untimed runs per job first (>= 1: Equi sample positions computed)")
    ap.add_argument("--backbone", default="resnet50")
    ap.add_argument("--width", type=float, default=1.0)
    ap.add_argument("--equi-parts", nargs="+", default=None,
                    help="which 3x3 convs are Equi (default: the model's default equi_parts)")
    ap.add_argument("--extra-equi", nargs="*", default=[],
                    help="more Equi variants to time, each a comma-separated equi_parts list, e.g. backbone wconv,heads")
    ap.add_argument("--skip-equi", action="store_true")
    ap.add_argument("--json", default=None, help="also write the results here")
    ap.add_argument("--scaling", action="store_true",
                    help="only time the Std forward at 512x256 and 1024x512 (interleaved) and print the growth")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    torch.manual_seed(0)
    if a.scaling:
        return scaling(a)
    print(f"torch {torch.__version__}, {a.threads} threads, load average {os.getloadavg()}", flush=True)
    print(host_line(), flush=True)
    print(load_line(a.threads, "at start"), flush=True)

    cam = Equirectangular(width=512, height=256)
    variants: list[tuple[str, dict]] = [("std", {})]
    if not a.skip_equi:
        equi = dict(conv="projected", camera=cam)
        if a.equi_parts:
            equi["equi_parts"] = tuple(a.equi_parts)
        variants.append(("equi", equi))
    for parts in a.extra_equi:
        variants.append((f"equi[{parts}]", dict(conv="projected", camera=cam,
                                                equi_parts=tuple(parts.split(",")))))

    res: dict = {"threads": a.threads, "reps": a.reps, "backbone": a.backbone, "width": a.width,
                 "load_before": os.getloadavg()}
    base = torchvision.models.resnet50(weights=None)
    jobs: dict[str, Callable[[], None]] = {"resnet50_fwd_512x256": forward_fn(base, 256, 512),
                                           "resnet50_fwd_256x128": forward_fn(base, 128, 256)}
    for name, kw in variants:
        model = FreDSNet(backbone=a.backbone, width=a.width, **kw)
        res[f"{name}_params"] = count_parameters(model)
        if name == "equi":
            res["equi_parts"] = list(kw.get("equi_parts", ("fourier", "wconv")))      # the model's default
        jobs[f"{name}_fwd_512x256"] = forward_fn(model, 256, 512)
        jobs[f"{name}_fwdbwd_256x128"] = train_step_fn(model, 128, 256)

    times: dict[str, list[float]] = {k: [] for k in jobs}
    # two phases, the 512x256 forwards then the 256x128 jobs (training steps and their baseline forward):
    # forwards back to back; within a phase every repetition times the baseline and each variant once
    for phase in ("512x256", "256x128"):
        keys = [k for k in jobs if k.endswith(phase)]
        for key in keys:                              # warm-up (and Equi sample positions)
            for _ in range(max(1, a.warmup)):
                jobs[key]()
            print(f"warmed up {key}", flush=True)
        for r in range(a.reps):
            for key in keys:
                times[key].append(_timed(jobs[key]))
            print(f"rep {r + 1}/{a.reps}: " + ", ".join(f"{k} {times[k][-1]:.3f}" for k in keys), flush=True)

    def ratio(num: str, den: str) -> float:
        return statistics.median(n / d for n, d in zip(times[num], times[den]))

    for key, ts in times.items():
        res[key], res[key + "_min"] = statistics.median(ts), min(ts)
    print(f"baseline resnet50 forward: 512x256 {res['resnet50_fwd_512x256']:.3f} s, "
          f"256x128 {res['resnet50_fwd_256x128']:.3f} s")
    for name, _ in variants:
        res[f"{name}_fwd_512x256_ratio_resnet50"] = ratio(f"{name}_fwd_512x256", "resnet50_fwd_512x256")
        res[f"{name}_fwdbwd_256x128_ratio_resnet50"] = ratio(f"{name}_fwdbwd_256x128", "resnet50_fwd_256x128")
        line = (f"FreDSNet-{name} ({res[f'{name}_params']:,} params): forward 512x256 {res[f'{name}_fwd_512x256']:.3f} s "
                f"({res[f'{name}_fwd_512x256_ratio_resnet50']:.2f}x resnet50 fwd), fwd+bwd 256x128 "
                f"{res[f'{name}_fwdbwd_256x128']:.3f} s ({res[f'{name}_fwdbwd_256x128_ratio_resnet50']:.2f}x resnet50 "
                f"fwd 256x128)")
        if name != "std":
            res[f"{name}_over_std_fwd"] = ratio(f"{name}_fwd_512x256", "std_fwd_512x256")
            res[f"{name}_over_std_fwdbwd"] = ratio(f"{name}_fwdbwd_256x128", "std_fwdbwd_256x128")
            line += (f"; / Std: forward {res[f'{name}_over_std_fwd']:.2f}x (target <= 1.3), "
                     f"fwd+bwd {res[f'{name}_over_std_fwdbwd']:.2f}x")
        print(line)
    res["std_fwd_target_met"] = res["std_fwd_512x256"] <= 0.8
    res["load_after"] = os.getloadavg()
    print(load_line(a.threads, "at end"))
    print(f"TARGET FreDSNet-std forward 512x256: {res['std_fwd_512x256']:.3f} s = "
          f"{res['std_fwd_512x256_ratio_resnet50']:.2f}x resnet50's forward "
          f"(target <= 0.8 s: {'met' if res['std_fwd_target_met'] else 'MISSED'})" + allocator_tag())
    if "equi_over_std_fwd" in res:
        r = res["equi_over_std_fwd"]
        print(f"TARGET FreDSNet-equi forward 512x256: {res['equi_fwd_512x256']:.3f} s = {r:.2f}x FreDSNet-std's "
              f"(target <= 1.3x: {'met' if r <= 1.3 else 'MISSED'})" + allocator_tag())
    if a.json:
        from omnidl.utils.io import atomic_write_json
        atomic_write_json(a.json, res)
    return res


def scaling(a: argparse.Namespace) -> dict:
    """Issue 17 item 4: the Std forward should grow like the pixels (x4 from 512x256 to 1024x512). Both sizes
    are timed in every repetition (order alternated); growth = median of per-repetition ratios, in wall and in
    CPU time (the steadier figure on a shared machine)."""
    from benchmarks._timing import load1
    model = FreDSNet(backbone=a.backbone, width=a.width).eval()
    sizes = {"512x256": torch.rand(1, 3, 256, 512), "1024x512": torch.rand(1, 3, 512, 1024)}
    l0 = load1()
    print(load_line(a.threads, "at start"), flush=True)
    wall: dict[str, list[float]] = {k: [] for k in sizes}
    cpu: dict[str, list[float]] = {k: [] for k in sizes}
    with torch.no_grad():
        for x in sizes.values():
            for _ in range(max(1, a.warmup)):
                model(x)
        for r in range(a.reps):
            for k in (list(sizes) if r % 2 == 0 else list(sizes)[::-1]):
                t, c = time.perf_counter(), time.process_time()
                model(sizes[k])
                wall[k].append(time.perf_counter() - t)
                cpu[k].append(time.process_time() - c)
    g_wall = statistics.median(b / s for b, s in zip(wall["1024x512"], wall["512x256"]))
    g_cpu = statistics.median(b / s for b, s in zip(cpu["1024x512"], cpu["512x256"]))
    res = {"threads": a.threads, "reps": a.reps, "growth_wall": g_wall, "growth_cpu": g_cpu,
           "fwd_512x256_s": statistics.median(wall["512x256"]), "fwd_1024x512_s": statistics.median(wall["1024x512"]),
           "load1": [l0, load1()]}
    print(f"forward 512x256 {res['fwd_512x256_s']:.3f} s, 1024x512 {res['fwd_1024x512_s']:.3f} s (medians, wall)")
    print(f"TARGET FreDSNet forward growth 512x256 -> 1024x512 (x4 pixels): x{g_wall:.2f} wall, x{g_cpu:.2f} CPU "
          f"(target <= x4.2: {'met' if g_wall <= 4.2 else 'MISSED'}); load {l0:.2f}-{res['load1'][1]:.2f}"
          + (" [taken under load]" if max(res["load1"]) > a.threads else "") + allocator_tag())
    print(load_line(a.threads, "at end"))
    if a.json:
        from omnidl.utils.io import atomic_write_json
        atomic_write_json(a.json, res)
    return res


if __name__ == "__main__":
    main()
