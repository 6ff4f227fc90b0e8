"""Speed of ProjectedConv2d's fast backend vs nn.Conv2d and a wrap-correct torchvision deform_conv2d (CPU).

    python benchmarks/projected_conv.py [--threads 2] [--reps 5] [--configs 64x128x256 256x64x128]
                                        [--batch 1] [--deform-reps 1] [--skip-deform] [--skip-resnet50]
                                        [--breakdown]

Per config ``CxHxW`` (equirectangular camera of the input size, 3x3, stride 1, padding 1, float32): forward
(``no_grad``) and forward+backward (input and weight require grad) of

* ``conv2d`` / ``conv2d_cl``: ``nn.Conv2d`` on NCHW / channels-last input (the baselines of the targets);
* ``fast`` / ``fast_cl``: ``ProjectedConv2d(backend="fast")`` on the same inputs (on CPU float32 the native
  kernel that fuses the gather of the taps into the product, :mod:`omnidl.nn.fused`);
* ``tiled`` / ``tiled_cl``: the same layer on its tiled oneDNN path (:mod:`omnidl.nn.tiled`, the previous fast
  backend, still the path without a C compiler), so every run shows what the fused kernel gains;
* ``deform``: ``torchvision.ops.deform_conv2d`` called directly with the layer's offsets and mask on an
  input circularly pre-padded by one kernel radius, with the column of every sample taken modulo ``W``
  (:func:`omnidl.nn.sampling.deform_conv2d_circular`): wrap-correct, the same output size as the layer (the
  old baseline tiled the input 3x and computed a 3x-wide output, inflating the ratio ~3x). Its output is
  checked against the fast backend.

All variants run interleaved (one call of each per repetition, order alternated); ratios are medians of the
per-repetition ratios. Targets (issue 17, item 2): fast fwd+bwd <= 1.5x conv2d at 64 ch 128x256 and <= 1.2x
at 256 ch 64x128; forward <= 1.3x / <= 1.1x. The load average is printed and figures are flagged when the
load exceeds the benchmark's threads.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._timing import host_line, interleaved, is_loaded, load_line, ratio, target_line  # noqa: E402
from omnidl.cameras import Equirectangular  # noqa: E402
from omnidl.nn import ProjectedConv2d, clear_plan_cache, plan_cache_info  # noqa: E402
from omnidl.nn.projected_conv import get_plan  # noqa: E402
from omnidl.nn import fused  # noqa: E402
from omnidl.nn.sampling import circular_offsets, deform_conv2d_circular  # noqa: E402

TARGETS = {64: (1.3, 1.5), 256: (1.1, 1.2)}  # channels -> (fwd, fwd+bwd) max ratio to conv2d


def _jobs(m, x, xg):
    def fwd():
        with torch.no_grad():
            m(x)

    def fwdbwd():
        xg.grad = None
        for p in m.parameters():
            p.grad = None
        y = m(xg)
        y.backward(torch.ones_like(y))
    return fwd, fwdbwd


class _Deform(torch.nn.Module):
    """deform_conv2d_circular with the layer's weights and precomputed wrapped offsets."""

    def __init__(self, layer: ProjectedConv2d, hw) -> None:
        super().__init__()
        self.layer = layer
        off, self.mask = layer.offsets(hw, dtype=torch.float32)
        self.off, self.P = circular_offsets(off, hw, layer.kernel_size, layer.stride, layer._padding_pair(),
                                            layer.dilation)

    def forward(self, x):
        L = self.layer
        return deform_conv2d_circular(x, L.weight, L.bias, self.off, self.mask, self.P, L.stride,
                                      L._padding_pair(), L.dilation)


class _Tiled(torch.nn.Module):
    """The same layer on its tiled oneDNN path (the native fused kernel turned off for its forward, which also
    picks the backward)."""

    def __init__(self, layer: ProjectedConv2d) -> None:
        super().__init__()
        self.layer = layer

    def forward(self, x):
        before, fused.ENABLED = fused.ENABLED, False
        try:
            return self.layer(x)
        finally:
            fused.ENABLED = before


def run_config(C: int, H: int, W: int, batch: int, reps: int, threads: int, deform_reps: int,
               skip_deform: bool) -> dict:
    torch.manual_seed(0)
    cam = Equirectangular(width=W, height=H)
    clear_plan_cache()
    fast = ProjectedConv2d(C, C, 3, padding=1, camera=cam, backend="fast")
    conv = torch.nn.Conv2d(C, C, 3, padding=1)
    conv.load_state_dict(fast.state_dict())
    t0 = time.perf_counter()
    fast(torch.zeros(1, C, H, W))
    build_ms = (time.perf_counter() - t0) * 1e3
    # the previous implementation: the tiled oneDNN path (the layer's path when the native kernel is off)
    tiled = _Tiled(fast)
    x = torch.randn(batch, C, H, W)
    xcl = x.contiguous(memory_format=torch.channels_last)
    jobs = {}
    for name, m, inp in (("conv2d", conv, x), ("fast", fast, x), ("conv2d_cl", conv, xcl), ("fast_cl", fast, xcl),
                         ("tiled", tiled, x), ("tiled_cl", tiled, xcl)):
        f, fb = _jobs(m, inp, inp.clone().requires_grad_(True))
        jobs[name + " fwd"], jobs[name + " fwd+bwd"] = f, fb
    check = None
    if not skip_deform:
        dm = _Deform(fast, (H, W))
        with torch.no_grad():
            check = float((dm(x) - fast(x)).abs().max())
        f, fb = _jobs(dm, x, x.clone().requires_grad_(True))
        jobs["deform fwd"], jobs["deform fwd+bwd"] = f, fb
    capped = {"deform fwd": deform_reps, "deform fwd+bwd": deform_reps}
    loaded_before = is_loaded(threads, steal=False)
    times = interleaved(jobs, reps, warmup=1, reps_of=capped)
    loaded = loaded_before or is_loaded(threads)
    med = {k: statistics.median(v) * 1e3 for k, v in times.items()}
    print(f"\n## C={C}, {H}x{W}, batch {batch}: first call (offsets + plan) {build_ms:.0f} ms, plan "
          f"{plan_cache_info()['plan_bytes'] / 2 ** 20:.1f} MiB" + (f"; deform vs fast max |diff| {check:.1e}"
                                                                     if check is not None else ""))
    print(load_line(threads))
    print("| variant | fwd ms (median / min) | fwd+bwd ms (median / min) | fwd / base | fwd+bwd / base |")
    print("|---|---|---|---|---|")
    for n in ("conv2d", "fast", "conv2d_cl", "fast_cl", "tiled", "tiled_cl", "deform"):
        if n + " fwd" not in times:
            continue
        base = "conv2d_cl" if n.endswith("_cl") else "conv2d"
        rf, rb = ratio(times, n + " fwd", base + " fwd"), ratio(times, n + " fwd+bwd", base + " fwd+bwd")
        print(f"| {n} | {med[n + ' fwd']:.1f} / {min(times[n + ' fwd']) * 1e3:.1f} | {med[n + ' fwd+bwd']:.1f} / "
              f"{min(times[n + ' fwd+bwd']) * 1e3:.1f} | {rf:.2f}x | {rb:.2f}x |")
    tf, tb = TARGETS.get(C, (None, None))
    res = {"channels": C, "hw": (H, W), "batch": batch, "median_ms": med, "loaded": loaded}
    for lay, fn, bn in (("NCHW", "fast", "conv2d"), ("channels-last", "fast_cl", "conv2d_cl")):
        for what in ("fwd", "fwd+bwd"):
            res[f"{fn}_{what}_ratio"] = ratio(times, f"{fn} {what}", f"{bn} {what}")
            print(f"{lay}: fast {what} = {res[f'{fn}_{what}_ratio']:.2f}x nn.Conv2d in the same layout")
    # the target: the faster layout of ProjectedConv2d against the faster layout of nn.Conv2d (a slow
    # channels-last conv2d backward must not make the ratio look good)
    for what, t in (("fwd", tf), ("fwd+bwd", tb)):
        fn = min(("fast", "fast_cl"), key=lambda n: med[f"{n} {what}"])
        bn = min(("conv2d", "conv2d_cl"), key=lambda n: med[f"{n} {what}"])
        r = med[f"{fn} {what}"] / med[f"{bn} {what}"]
        res[f"best_{what}_ratio"] = r
        print(target_line(f"ProjectedConv2d {what} {C}ch {H}x{W} B{batch}", f"{med[fn + ' ' + what]:.1f} ms ({fn})",
                          r, f"the faster nn.Conv2d ({bn}, {med[bn + ' ' + what]:.1f} ms)",
                          None if t is None else f"<= {t}x", None if t is None else r <= t, loaded))
    for what in ("fwd", "fwd+bwd"):
        best = {n: min(med[f"{n} {what}"], med[f"{n}_cl {what}"]) for n in ("fast", "tiled")}
        res[f"tiled_vs_fast_{what}"] = best["tiled"] / best["fast"]
        print(f"tiled oneDNN path (the previous fast backend) / fast {what}, faster layouts: "
              f"{res[f'tiled_vs_fast_{what}']:.2f}x ({best['tiled']:.1f} vs {best['fast']:.1f} ms)")
    if "deform fwd" in times:
        for what in ("fwd", "fwd+bwd"):
            r = med[f"deform {what}"] / med[f"fast {what}"]
            res[f"deform_vs_fast_{what}"] = r
            print(f"deform_conv2d (circular pre-pad, same output) / fast {what}: {r:.1f}x "
                  f"({med['deform ' + what]:.0f} vs {med['fast ' + what]:.1f} ms, {len(times['deform ' + what])} rep)")
    return res


def breakdown(C: int, H: int, W: int, reps: int) -> dict:
    """Where the tiled path's forward time goes, one thread, per image: the gather of every tap (all tiles), the
    oneDNN convolution of the tiles, the copy into the output, against the dense ``nn.Conv2d`` (channels-last)
    with the same FLOPs, and the layer on its fused native path. ``dense conv + gather`` is the issue's limit;
    the tile convolution differs from the dense one only in reading each tap from memory instead of re-using
    input pixels from cache; the fused kernel reads each tap from a cache-resident block."""
    from omnidl.nn.sampling import _rows
    from omnidl.nn.tiled import _tile, tile_rows, tiled_plan

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        torch.manual_seed(0)
        cam = Equirectangular(width=W, height=H)
        layer = ProjectedConv2d(C, C, 3, padding=1, camera=cam)
        conv = torch.nn.Conv2d(C, C, 3, padding=1)
        x = torch.randn(1, C, H, W).contiguous(memory_format=torch.channels_last)
        plan = get_plan(layer.geometry_key((H, W)), x.device, x.dtype)
        tp = tiled_plan(plan)
        Wo = plan.out_hw[1]
        rows = tile_rows(plan, C, 4, weight_numel=C * C * 9)
        spans = [(s, e) for s, e, *_ in tp.chunks(rows * Wo)]
        xr = _rows(x)[0]
        w = layer.weight.detach()
        tiles = [_tile(tp, xr, s, e) for s, e in spans]
        outs = [torch.nn.functional.conv2d(t, w, None, stride=(3, 3)) for t in tiles]
        result = torch.empty(1, C, H, W, memory_format=torch.channels_last)

        def gather():
            for s, e in spans:
                _tile(tp, xr, s, e)

        def tconv():
            for t in tiles:
                torch.nn.functional.conv2d(t, w, None, stride=(3, 3))

        def copy():
            for (s, e), y in zip(spans, outs):
                result[0, :, s // Wo:e // Wo].copy_(y[0])
        with torch.no_grad():
            tiled = _Tiled(layer)
            jobs = {"dense conv2d": lambda: conv(x), "layer (fused)": lambda: layer(x),
                    "layer (tiled)": lambda: tiled(x), "gather": gather, "tile conv": tconv, "copy": copy}
            times = {k: [] for k in jobs}
            for fn in jobs.values():
                fn()
            for r in range(reps):
                for k, fn in (jobs.items() if r % 2 == 0 else list(jobs.items())[::-1]):
                    t0 = time.thread_time()
                    fn()
                    times[k].append(time.thread_time() - t0)
    finally:
        torch.set_num_threads(threads)
    med = {k: statistics.median(v) * 1e3 for k, v in times.items()}
    d = med["dense conv2d"]
    print(f"\n## forward breakdown, C={C} {H}x{W}, 1 thread, CPU ms per image ({rows} output rows per tile); "
          f"{load_line(1)[2:]}")
    for k, v in med.items():
        print(f"{k}: {v:.1f} ms = {v / d:.2f}x dense conv2d")
    print(f"dense conv2d + gather (the limit named by the issue) = {(d + med['gather']) / d:.2f}x; tile conv + gather "
          f"+ copy = {(med['tile conv'] + med['gather'] + med['copy']) / d:.2f}x; the tiled layer = "
          f"{med['layer (tiled)'] / d:.2f}x; the fused layer = {med['layer (fused)'] / d:.2f}x")
    return med


def resnet50_check(height: int = 128, width: int = 256, threads: int = 2, reps: int = 3) -> None:
    """``convert_conv2d(resnet50(), equirect)`` fwd+bwd vs the plain resnet50, interleaved."""
    import torchvision

    from omnidl.nn import convert_conv2d

    torch.manual_seed(0)
    x = torch.randn(1, 3, height, width)
    plain = torchvision.models.resnet50()
    net = convert_conv2d(torchvision.models.resnet50(), Equirectangular(width=width, height=height))
    net.load_state_dict(plain.state_dict())
    n = sum(isinstance(m, ProjectedConv2d) for m in net.modules())
    t0 = time.perf_counter()
    net(x).sum().backward()
    first = (time.perf_counter() - t0) * 1e3

    def step(m):
        def run():
            m.zero_grad(set_to_none=True)
            m(x).sum().backward()
        return run
    times = interleaved({"resnet50": step(plain), "converted": step(net)}, reps, warmup=0)
    r = ratio(times, "converted", "resnet50")
    print(f"\n## convert_conv2d(resnet50, equirect {width}x{height}): {n} convolutions converted; first fwd+bwd "
          f"(plans) {first:.0f} ms")
    print(load_line(threads))
    print(f"resnet50 fwd+bwd B1 {height}x{width}: converted {statistics.median(times['converted']) * 1e3:.0f} ms = "
          f"{r:.2f}x plain ({statistics.median(times['resnet50']) * 1e3:.0f} ms)")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", nargs="+", default=["64x128x256", "256x64x128"], help="CxHxW")
    ap.add_argument("--batch", type=int, default=1)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--deform-reps", type=int, default=1)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--skip-deform", action="store_true", help="leave out deform_conv2d (slow)")
    ap.add_argument("--skip-resnet50", action="store_true", help="leave out the converted resnet50 check")
    ap.add_argument("--breakdown", action="store_true", help="also print where the forward's time goes (1 thread)")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    print(f"# ProjectedConv2d benchmark, float32, CPU, {a.threads} threads, median of {a.reps} interleaved reps")
    print(load_line(a.threads, "at start"))
    print(host_line())
    for cfg in a.configs:
        C, H, W = (int(v) for v in cfg.lower().split("x"))
        run_config(C, H, W, a.batch, a.reps, a.threads, a.deform_reps, a.skip_deform)
        if a.breakdown:
            breakdown(C, H, W, max(a.reps, 5))
    if not a.skip_resnet50:
        resnet50_check(threads=a.threads)


if __name__ == "__main__":
    main()
