"""FreDSNet CPU speed: forward at 512x256 and forward+backward at 256x128, batch 1, as ratios to
torchvision's ResNet-50 forward measured in the same run.

    python benchmarks/fredsnet.py [--threads 2] [--reps 5] [--equi-parts fourier wconv] [--json out.json]

Protocol (as the reference measurement in the project notes): ``torch.set_num_threads(threads)``,
random weights, 2 warm-up runs (the Equi layers build their sampling plans there), median of
``reps`` timed runs; forward = ``eval()`` + ``no_grad``; forward+backward = ``train()``,
loss ``CE(semantic, random labels) + L1(depth, random)``, ``zero_grad`` + forward + backward.
Targets (issue 5): FreDSNet-Std forward <= 0.8 s and FreDSNet-Equi <= 1.3x Std. The load average
is printed: numbers taken on a busy machine are not comparable.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import torch
import torch.nn.functional as F
import torchvision

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from omnidl.cameras import Equirectangular  # noqa: E402
from omnidl.models.fredsnet import FreDSNet, count_parameters  # noqa: E402


def _median_time(fn, reps: int, warmup: int = 2) -> tuple[float, float]:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), min(times)


def forward_time(model: torch.nn.Module, h: int, w: int, reps: int) -> tuple[float, float]:
    model.eval()
    x = torch.rand(1, 3, h, w)

    def run():
        with torch.no_grad():
            model(x)
    return _median_time(run, reps)


def train_step_time(model: torch.nn.Module, h: int, w: int, reps: int) -> tuple[float, float]:
    model.train()
    x = torch.rand(1, 3, h, w)
    labels = torch.randint(0, 14, (1, h, w))
    depth = torch.rand(1, 1, h, w) * 5

    def run():
        model.zero_grad(set_to_none=True)
        out = model(x)
        loss = F.cross_entropy(out["semantic"], labels) + F.l1_loss(out["depth"], depth)
        loss.backward()
    return _median_time(run, reps)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--backbone", default="resnet50")
    ap.add_argument("--width", type=float, default=1.0)
    ap.add_argument("--equi-parts", nargs="+", default=None,
                    help="which 3x3 convs are Equi (default: the model's default equi_parts)")
    ap.add_argument("--extra-equi", nargs="*", default=[],
                    help="more Equi variants to time, each a comma-separated equi_parts list, e.g. backbone wconv,heads")
    ap.add_argument("--skip-equi", action="store_true")
    ap.add_argument("--json", default=None, help="also write the results here")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    torch.manual_seed(0)
    print(f"torch {torch.__version__}, {a.threads} threads, load average {os.getloadavg()}", flush=True)

    res: dict = {"threads": a.threads, "reps": a.reps, "backbone": a.backbone, "width": a.width,
                 "load_before": os.getloadavg()}
    base = torchvision.models.resnet50(weights=None)
    res["resnet50_fwd_512x256"] = forward_time(base, 256, 512, a.reps)[0]
    res["resnet50_fwd_256x128"] = forward_time(base, 128, 256, a.reps)[0]
    print(f"baseline resnet50 forward: 512x256 {res['resnet50_fwd_512x256']:.3f} s, "
          f"256x128 {res['resnet50_fwd_256x128']:.3f} s", flush=True)
    del base

    cam = Equirectangular(width=512, height=256)
    variants = [("std", {})]
    if not a.skip_equi:
        equi = dict(conv="equi", camera=cam)
        if a.equi_parts:
            equi["equi_parts"] = tuple(a.equi_parts)
        variants.append(("equi", equi))
    for parts in a.extra_equi:
        variants.append((f"equi[{parts}]", dict(conv="equi", camera=cam, equi_parts=tuple(parts.split(",")))))
    for name, kw in variants:
        model = FreDSNet(backbone=a.backbone, width=a.width, **kw)
        res[f"{name}_params"] = count_parameters(model)
        fwd, fwd_min = forward_time(model, 256, 512, a.reps)
        fb, fb_min = train_step_time(model, 128, 256, a.reps)
        res[f"{name}_fwd_512x256"], res[f"{name}_fwdbwd_256x128"] = fwd, fb
        res[f"{name}_fwd_512x256_ratio_resnet50"] = fwd / res["resnet50_fwd_512x256"]
        res[f"{name}_fwdbwd_256x128_ratio_resnet50"] = fb / res["resnet50_fwd_256x128"]
        if name.startswith("equi"):
            res[f"{name}_over_std_fwd"] = fwd / res["std_fwd_512x256"]
            res[f"{name}_over_std_fwdbwd"] = fb / res["std_fwdbwd_256x128"]
        print(f"FreDSNet-{name.capitalize()} ({res[f'{name}_params']:,} params): forward 512x256 {fwd:.3f} s "
              f"(min {fwd_min:.3f}; {res[f'{name}_fwd_512x256_ratio_resnet50']:.2f}x resnet50 fwd), "
              f"fwd+bwd 256x128 {fb:.3f} s (min {fb_min:.3f}; {res[f'{name}_fwdbwd_256x128_ratio_resnet50']:.2f}x "
              f"resnet50 fwd 256x128)", flush=True)
        del model
        if name.startswith("equi"):
            print(f"  {name} / Std: forward {res[f'{name}_over_std_fwd']:.2f}x (target <= 1.3), "
                  f"fwd+bwd {res[f'{name}_over_std_fwdbwd']:.2f}x", flush=True)
    res["std_fwd_target_met"] = res["std_fwd_512x256"] <= 0.8
    res["load_after"] = os.getloadavg()
    print(f"Std forward target (<= 0.8 s): {'met' if res['std_fwd_target_met'] else 'NOT met'}; "
          f"load average {res['load_after']}")
    if a.json:
        from omnidl.utils.io import atomic_write_json
        atomic_write_json(a.json, res)
    return res


if __name__ == "__main__":
    main()
