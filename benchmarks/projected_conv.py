"""Speed of ProjectedConv2d's fast backend vs nn.Conv2d and torchvision's deform_conv2d (CPU).

Run: ``python -m benchmarks.projected_conv`` or ``python benchmarks/projected_conv.py``
(options: ``--threads 2 --reps 7 --channels 64 --height 128 --width 256 --batch 1 4``).

For each batch size, the variants run interleaved (one repetition of each per
round) after a warm-up; the table shows median and minimum times in milliseconds of forward and
forward+backward (input and weight require grad; offsets fixed) and the ratios of the
medians fast / conv2d and deform_conv2d / fast. The camera is an equirectangular panorama of the
input size, 3x3 kernel, stride 1, padding 1, float32. NCHW and channels-last inputs are
timed separately (each against nn.Conv2d in the same layout). Also printed: the cache
memory of one layer (sampling plan, offsets).
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch
import torch.nn.functional as F

if __package__ in (None, ""):  # run as a script
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from omnidl.cameras import Equirectangular  # noqa: E402
from omnidl.nn import ProjectedConv2d, clear_plan_cache, plan_cache_info  # noqa: E402


def _timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return (time.perf_counter() - t0) * 1e3


def run(channels: int = 64, height: int = 128, width: int = 256, batches=(1, 4), reps: int = 7, threads: int = 2,
        skip_deform: bool = False) -> list[dict]:
    torch.set_num_threads(threads)
    torch.manual_seed(0)
    cam = Equirectangular(width=width, height=height)
    clear_plan_cache()
    fast = ProjectedConv2d(channels, channels, 3, padding=1, camera=cam, backend="fast")
    tv = ProjectedConv2d(channels, channels, 3, padding=1, camera=cam, backend="torchvision")
    conv = torch.nn.Conv2d(channels, channels, 3, padding=1)
    tv.load_state_dict(fast.state_dict())
    conv.load_state_dict(fast.state_dict())
    t0 = time.perf_counter()
    fast(torch.zeros(1, channels, height, width))
    tv(torch.zeros(1, channels, height, width))
    build_ms = (time.perf_counter() - t0) * 1e3
    info = plan_cache_info()
    rows = []
    variants = {"conv2d": (conv, False), "fast": (fast, False), "conv2d_cl": (conv, True), "fast_cl": (fast, True)}
    if not skip_deform:
        variants["deform_conv2d"] = (tv, False)
    for B in batches:
        inputs = {}
        for cl in (False, True):
            x = torch.randn(B, channels, height, width)
            if cl:
                x = x.to(memory_format=torch.channels_last)
            inputs[cl] = (x, x.clone().requires_grad_(True))

        def fwd(m, cl):
            with torch.no_grad():
                m(inputs[cl][0])

        def fwdbwd(m, cl):
            xg = inputs[cl][1]
            xg.grad = None
            m.zero_grad(set_to_none=True)
            y = m(xg)
            y.backward(torch.ones_like(y))

        times = {name: {"fwd": [], "fwdbwd": []} for name in variants}
        for name, (m, cl) in variants.items():  # warm-up
            fwd(m, cl)
            fwdbwd(m, cl)
        n_deform = max(2, reps // 3) if B > 1 else reps
        for r in range(reps):
            for name, (m, cl) in variants.items():
                if name == "deform_conv2d" and r >= n_deform:
                    continue
                times[name]["fwd"].append(_timed(lambda: fwd(m, cl)))
                times[name]["fwdbwd"].append(_timed(lambda: fwdbwd(m, cl)))
        med = {n: {k: statistics.median(v) for k, v in t.items()} for n, t in times.items()}
        row = {"batch": B, **{f"{n}_{k}_ms": v for n, t in med.items() for k, v in t.items()},
               **{f"{n}_{k}_min_ms": min(v) for n, t in times.items() for k, v in t.items()}}
        for k in ("fwd", "fwdbwd"):
            row[f"fast_vs_conv2d_{k}"] = med["fast"][k] / med["conv2d"][k]
            row[f"fast_cl_vs_conv2d_cl_{k}"] = med["fast_cl"][k] / med["conv2d_cl"][k]
            if "deform_conv2d" in med:
                row[f"deform_vs_fast_{k}"] = med["deform_conv2d"][k] / med["fast"][k]
        rows.append(row)
    print(f"# ProjectedConv2d benchmark: C={channels}, {height}x{width}, 3x3, float32, CPU, "
          f"{torch.get_num_threads()} threads, median of {reps} interleaved repetitions "
          f"(deform_conv2d: {reps} at batch 1, fewer above); *_cl = channels-last tensors")
    print(f"# cache per layer: {info['plan_bytes'] / 2 ** 20:.1f} MiB sampling plan (taps + chunked CSR "
          f"transposes), {info['offset_bytes'] / 2 ** 20:.1f} MiB offsets+mask (float64 master + float32 copy, "
          f"the latter only for the torchvision backend); first call (offsets + plan) {build_ms:.0f} ms")
    print("| batch | variant | fwd ms (median / min) | fwd+bwd ms (median / min) | fwd / conv2d | "
          "fwd+bwd / conv2d |")
    print("|---|---|---|---|---|---|")
    for row in rows:
        for n in variants:
            base = "conv2d_cl" if n.endswith("_cl") else "conv2d"
            f, fb = row[f"{n}_fwd_ms"], row[f"{n}_fwdbwd_ms"]
            print(f"| {row['batch']} | {n} | {f:.1f} / {row[n + '_fwd_min_ms']:.1f} | {fb:.1f} / "
                  f"{row[n + '_fwdbwd_min_ms']:.1f} | {f / row[base + '_fwd_ms']:.2f}x "
                  f"| {fb / row[base + '_fwdbwd_ms']:.2f}x |")
    for row in rows:
        line = (f"batch {row['batch']}: fast fwd+bwd = {row['fast_vs_conv2d_fwdbwd']:.2f}x conv2d (NCHW), "
                f"{row['fast_cl_vs_conv2d_cl_fwdbwd']:.2f}x conv2d (channels-last) (target <= 3x)")
        if "deform_vs_fast_fwdbwd" in row:
            line += (f"; deform_conv2d / fast = {row['deform_vs_fast_fwd']:.1f}x fwd, "
                     f"{row['deform_vs_fast_fwdbwd']:.1f}x fwd+bwd (target >= 20x at batch 1)")
        print(line)
    return rows


def resnet50_check(height: int = 128, width: int = 256, threads: int = 2) -> None:
    """Acceptance check: ``convert_conv2d(resnet50(), equirect)`` runs forward/backward on ``height x width``."""
    import torchvision

    from omnidl.nn import convert_conv2d

    torch.set_num_threads(threads)
    torch.manual_seed(0)
    x = torch.randn(1, 3, height, width)
    plain = torchvision.models.resnet50()
    net = convert_conv2d(torchvision.models.resnet50(), Equirectangular(width=width, height=height))
    net.load_state_dict(plain.state_dict())
    n = sum(isinstance(m, ProjectedConv2d) for m in net.modules())
    t0 = time.perf_counter()
    net(x).sum().backward()  # first call builds the sampling plans
    first = (time.perf_counter() - t0) * 1e3
    times: dict[str, list[float]] = {"resnet50": [], "resnet50+ProjectedConv2d": []}
    for _ in range(3):
        for name, m in (("resnet50", plain), ("resnet50+ProjectedConv2d", net)):
            m.zero_grad(set_to_none=True)
            times[name].append(_timed(lambda: m(x).sum().backward()))
    med = {k: statistics.median(v) for k, v in times.items()}
    print(f"# convert_conv2d(resnet50, equirect {width}x{height}): {n} convolutions converted; "
          f"first forward+backward (with plan building) {first:.0f} ms")
    print(f"resnet50 fwd+bwd, batch 1, {height}x{width}: plain {med['resnet50']:.0f} ms, converted "
          f"{med['resnet50+ProjectedConv2d']:.0f} ms ({med['resnet50+ProjectedConv2d'] / med['resnet50']:.2f}x); "
          f"plan cache {plan_cache_info()['plan_bytes'] / 2 ** 20:.0f} MiB")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--channels", type=int, default=64)
    ap.add_argument("--height", type=int, default=128)
    ap.add_argument("--width", type=int, default=256)
    ap.add_argument("--batch", type=int, nargs="+", default=[1, 4])
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--skip-deform", action="store_true", help="leave out deform_conv2d (slow)")
    ap.add_argument("--skip-resnet50", action="store_true", help="leave out the converted resnet50 check")
    a = ap.parse_args(argv)
    run(a.channels, a.height, a.width, tuple(a.batch), a.reps, a.threads, a.skip_deform)
    if not a.skip_resnet50:
        resnet50_check(a.height, a.width, a.threads)


if __name__ == "__main__":
    main()
