"""GPU speed (issue 17, item 8): FreDSNet fps, ProjectedConv2d vs cuDNN conv2d, a training step.

    python benchmarks/gpu.py [--device cuda] [--reps 20] [--amp bf16|fp16|none] [--profile FILE] [--only fps,conv,train]

* FreDSNet (ResNet-50, width 1) forward at 512x256, batch 1, eval + no_grad, float32 and under autocast:
  frames per second (target >= 100 fps on an H100/H200-class GPU; the thesis reports 33 fps on an RTX 3090),
  as a ratio to torchvision's ResNet-50 forward at the same size in the same run; also replayed from a CUDA
  graph (batch-1 inference is launch-bound: the graph removes the per-kernel launch gaps);
* ``ProjectedConv2d`` (fast backend as it runs by default on CUDA: :mod:`omnidl.nn.grid_conv`, or with
  ``OMNIDL_TRITON=1`` the fused Triton kernels of :mod:`omnidl.nn.triton_conv`) forward and forward+backward vs
  ``nn.Conv2d`` (cuDNN, TF32 as PyTorch's default, and without TF32) at 64 ch 128x256 and 256 ch 64x128, batch 1
  (target <= 1.5x), with both CUDA backends timed beside it whatever the default, and other block sizes of the
  fused kernels; the last line says whether the fused kernels beat ``grid_conv`` at both layers;
* a FreDSNet training step (CE + L1, zero_grad + forward + backward + SGD step) at 256x128, batch 4.

Times are CUDA-event medians after warm-up (plans, cuDNN autotuning), interleaved per repetition. Each part
runs on even when another failed (its traceback is printed; the exit status is 1 then). ``--profile FILE``
writes the CUDA-time tables of one FreDSNet forward and one ProjectedConv2d forward+backward (torch.profiler).
Prints a note and exits 0 when no CUDA device is present (CPU speed: benchmarks/projected_conv.py, fredsnet.py).
"""
from __future__ import annotations

import argparse
import statistics
import sys
import traceback
from pathlib import Path

import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _cuda_times(jobs: dict, reps: int, warmup: int = 3) -> dict[str, float]:
    for fn in jobs.values():
        for _ in range(warmup):
            fn()
    torch.cuda.synchronize()
    out: dict[str, list[float]] = {k: [] for k in jobs}
    for r in range(reps):
        for k in (list(jobs) if r % 2 == 0 else list(jobs)[::-1]):
            s, e = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            s.record()
            jobs[k]()
            e.record()
            torch.cuda.synchronize()
            out[k].append(s.elapsed_time(e))
    return {k: statistics.median(v) for k, v in out.items()}


def _graphed(fn, x: torch.Tensor):
    """``fn(x)`` captured in a CUDA graph: returns ``replay()`` (reads the static ``x``), or raises what the
    capture raised (a path that syncs with the host or allocates outside the graph's pool cannot be captured)."""
    stream = torch.cuda.Stream()
    stream.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(stream):
        for _ in range(3):
            fn(x)
    torch.cuda.current_stream().wait_stream(stream)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        fn(x)
    return graph.replay


def fredsnet_fps(dev, reps: int, amp: str, amp_dtype) -> None:
    """Part 1: FreDSNet forward fps at 512x256 (eager, autocast, CUDA graph) against torchvision's ResNet-50."""
    import torchvision

    from omnidl.models.fredsnet import FreDSNet
    torch.manual_seed(0)
    net = FreDSNet(backbone="resnet50", width=1.0).to(dev).eval()
    r50 = torchvision.models.resnet50().to(dev).eval()
    x = torch.rand(1, 3, 256, 512, device=dev)

    def call(m, amp_dt):
        def run(inp=x):
            with torch.no_grad(), torch.autocast("cuda", dtype=amp_dt or torch.float32, enabled=amp_dt is not None):
                return m(inp)
        return run
    nchw = FreDSNet(backbone="resnet50", width=1.0, channels_last=False).to(dev).eval()
    nchw.load_state_dict(net.state_dict())
    jobs = {"fredsnet fp32": call(net, None), "resnet50 fp32": call(r50, None), "fredsnet-nchw fp32": call(nchw, None)}
    if amp_dtype is not None:
        jobs[f"fredsnet {amp}"] = call(net, amp_dtype)
        jobs[f"resnet50 {amp}"] = call(r50, amp_dtype)
    precs = ["fp32"] + ([amp] if amp_dtype is not None else [])
    graphs = {}
    for prec in precs:
        for name, m in (("fredsnet", net), ("resnet50", r50)):
            try:
                graphs[f"{name} {prec} graph"] = _graphed(call(m, None if prec == "fp32" else amp_dtype), x)
            except Exception as e:  # noqa: BLE001 -- reported, the eager figures still stand
                where = [f"{f.filename.rsplit('omnidl/', 1)[-1]}:{f.lineno}"
                         for f in traceback.extract_tb(e.__traceback__) if "/omnidl/" in f.filename][-3:]
                print(f"# {name} {prec}: no CUDA graph ({type(e).__name__}: "
                      f"{str(e).splitlines()[0][:160]}; at {where})")
                torch.cuda.synchronize()
    t = _cuda_times({**jobs, **graphs}, reps)
    print(f"# FreDSNet eager fp32 in NCHW memory (channels_last=False): {t['fredsnet-nchw fp32']:.2f} ms "
          f"against {t['fredsnet fp32']:.2f} ms channels-last (the eval default)")
    for prec in precs:
        for mode in ("", " graph"):
            key = f"fredsnet {prec}{mode}"
            if key not in t:
                continue
            ms, base = t[key], t.get(f"resnet50 {prec}{mode}", float("nan"))
            print(f"TARGET FreDSNet forward 512x256 B1 {prec}{mode or ' eager'}: {1e3 / ms:.0f} fps ({ms:.2f} ms) = "
                  f"{ms / base:.2f}x resnet50 forward ({base:.2f} ms) "
                  f"(target >= 100 fps: {'met' if 1e3 / ms >= 100 else 'MISSED'})")


# block-size candidates of the fused kernels (omnidl.nn.triton_conv.TUNE) timed beside its own choice
FWD_CONFIGS = {"p64 n64 c16 w4": dict(BLOCK_P=64, BLOCK_N=64, BLOCK_C=16, num_warps=4, num_stages=1),
               "p64 n128 c16 w4": dict(BLOCK_P=64, BLOCK_N=128, BLOCK_C=16, num_warps=4, num_stages=1),
               "p128 n128 c16 w8": dict(BLOCK_P=128, BLOCK_N=128, BLOCK_C=16, num_warps=8, num_stages=1),
               "p64 n64 c32 w8": dict(BLOCK_P=64, BLOCK_N=64, BLOCK_C=32, num_warps=8, num_stages=1),
               "p128 n64 c32 w8": dict(BLOCK_P=128, BLOCK_N=64, BLOCK_C=32, num_warps=8, num_stages=1)}
BWD_CONFIGS = {"gcols p128 c64 n32 s2": {"gcols": dict(BLOCK_P=128, BLOCK_C=64, BLOCK_N=32, num_warps=4, num_stages=2)},
               "gcols p64 c64 n32 s3": {"gcols": dict(BLOCK_P=64, BLOCK_C=64, BLOCK_N=32, num_warps=4, num_stages=3)},
               "sell c32": {"sell": dict(BLOCK_C=32, num_warps=4)},
               "wgrad r32 c32 n64": {"wgrad": dict(BLOCK_R=32, BLOCK_C=32, BLOCK_N=64, num_warps=4, num_stages=1)},
               "wgrad r32 c64 n64 w8": {"wgrad": dict(BLOCK_R=32, BLOCK_C=64, BLOCK_N=64, num_warps=8, num_stages=1)}}


def projected_conv(dev, reps: int) -> None:
    """Part 2: ProjectedConv2d (fast backend) vs cuDNN conv2d, forward and forward+backward."""
    from omnidl.cameras import Equirectangular
    from omnidl.nn import ProjectedConv2d, triton_conv
    fused_vs_grid = {}
    for C, H, W in ((64, 128, 256), (256, 64, 128)):
        torch.manual_seed(0)
        fast = ProjectedConv2d(C, C, 3, padding=1, camera=Equirectangular(width=W, height=H)).to(dev)
        conv = torch.nn.Conv2d(C, C, 3, padding=1).to(dev)
        conv.load_state_dict(fast.state_dict())
        xi = torch.randn(1, C, H, W, device=dev)
        xg = xi.clone().requires_grad_(True)
        backend = "triton_conv" if triton_conv.applies(xi, fast.weight) else "grid_conv"
        keep_enabled, triton_conv.ENABLED = triton_conv.ENABLED, True
        fused = triton_conv.applies(xi, fast.weight)      # the fused kernels compile and pass their self-check here
        triton_conv.ENABLED = keep_enabled

        def f(m):
            def run():
                with torch.no_grad():
                    m(xi)
            return run

        def fb(m):
            def run():
                xg.grad = None
                m.zero_grad(set_to_none=True)
                m(xg).sum().backward()
            return run

        def exact(fn):                  # cuDNN without TF32
            def run():
                with torch.backends.cudnn.flags(enabled=True, benchmark=True, deterministic=False, allow_tf32=False):
                    fn()
            return run

        def backend_set(fn, enabled, tune=None):   # the fused Triton kernels on/off, with block sizes ``tune``
            def run():
                keep = triton_conv.ENABLED, triton_conv.TUNE
                triton_conv.ENABLED, triton_conv.TUNE = enabled, tune or {}
                try:
                    fn()
                finally:
                    triton_conv.ENABLED, triton_conv.TUNE = keep
            return run
        jobs = {"fast fwd": f(fast), "conv fwd": f(conv), "fast fwdbwd": fb(fast), "conv fwdbwd": fb(conv),
                "conv32 fwd": exact(f(conv)), "conv32 fwdbwd": exact(fb(conv)),
                "grid fwd": backend_set(f(fast), False), "grid fwdbwd": backend_set(fb(fast), False)}
        if fused:
            jobs.update({"triton fwd": backend_set(f(fast), True), "triton fwdbwd": backend_set(fb(fast), True)})
            jobs.update({f"tune fwd {k}": backend_set(f(fast), True, {"fwd": v}) for k, v in FWD_CONFIGS.items()})
            jobs.update({f"tune fwdbwd {k}": backend_set(fb(fast), True, v) for k, v in BWD_CONFIGS.items()})
        t = _cuda_times(jobs, reps)
        for what in ("fwd", "fwdbwd"):
            r = t[f"fast {what}"] / t[f"conv {what}"]
            print(f"TARGET ProjectedConv2d {what} {C}ch {H}x{W} B1 ({backend}): {t[f'fast {what}']:.3f} ms = {r:.2f}x "
                  f"cuDNN conv2d ({t[f'conv {what}']:.3f} ms, TF32) "
                  f"(target <= 1.5x: {'met' if r <= 1.5 else 'MISSED'}); "
                  f"{t[f'fast {what}'] / t[f'conv32 {what}']:.2f}x cuDNN without TF32 ({t[f'conv32 {what}']:.3f} ms); "
                  f"grid_conv backend {t[f'grid {what}']:.3f} ms ({t[f'grid {what}'] / t[f'conv {what}']:.2f}x); "
                  + (f"fused Triton backend {t[f'triton {what}']:.3f} ms "
                     f"({t[f'triton {what}'] / t[f'conv {what}']:.2f}x)"
                     if fused else "fused Triton backend: not usable here (see the warning above)"))
            if fused:
                fused_vs_grid[f"{what} {C}ch"] = t[f"triton {what}"] / t[f"grid {what}"]
            tunes = {k.split(" ", 2)[2]: v for k, v in t.items() if k.startswith(f"tune {what} ")}
            if tunes:
                print(f"#   block sizes, {what} {C}ch: " + ", ".join(f"{k}: {v:.3f} ms" for k, v in tunes.items()))
    if fused_vs_grid:
        faster = all(r < 1 for r in fused_vs_grid.values())
        print("# fused Triton kernels / grid_conv: " + ", ".join(f"{k} {r:.2f}x" for k, r in fused_vs_grid.items())
              + (": faster everywhere, triton_conv.ENABLED can default to on" if faster
                 else ": not faster everywhere, keep triton_conv.ENABLED off by default"))


def training_step(dev, reps: int, amp: str, amp_dtype) -> None:
    """Part 3: a FreDSNet training step (CE + L1, SGD) at 256x128, batch 4."""
    from omnidl.models.fredsnet import FreDSNet
    torch.manual_seed(0)
    net = FreDSNet(backbone="resnet50", width=1.0).to(dev).train()
    opt = torch.optim.SGD(net.parameters(), lr=1e-4)
    xb = torch.rand(4, 3, 128, 256, device=dev)
    lab = torch.randint(0, 14, (4, 128, 256), device=dev)
    depth = torch.rand(4, 1, 128, 256, device=dev) * 5

    def step(amp_dt):
        def run():
            opt.zero_grad(set_to_none=True)
            with torch.autocast("cuda", dtype=amp_dt or torch.float32, enabled=amp_dt is not None):
                out = net(xb)
                loss = F.cross_entropy(out["semantic"].float(), lab) + F.l1_loss(out["depth"].float(), depth)
            loss.backward()
            opt.step()
        return run
    jobs = {"step fp32": step(None)}
    if amp_dtype is not None and amp_dtype == torch.bfloat16:  # fp16 would need a GradScaler
        jobs[f"step {amp}"] = step(amp_dtype)
    t = _cuda_times(jobs, max(5, reps // 2))
    for k, ms in t.items():
        print(f"FreDSNet training {k} 256x128 B4: {ms:.1f} ms ({4e3 / ms:.0f} images/s)")


def profile(dev, path: str, fredsnet: bool = True) -> None:
    """The CUDA-time tables of one FreDSNet forward at 512x256 (``fredsnet``) and one ProjectedConv2d forward+backward
    at 256 ch 64x128 (after warm-up), written to ``path``."""
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as prof

    text = ""
    if fredsnet:
        from omnidl.models.fredsnet import FreDSNet
        net = FreDSNet(backbone="resnet50", width=1.0).to(dev).eval()
        x = torch.rand(1, 3, 256, 512, device=dev)
        with torch.no_grad():
            for _ in range(3):
                net(x)
            torch.cuda.synchronize()
            with prof(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as p:
                net(x)
                torch.cuda.synchronize()
        text = "FreDSNet forward 512x256 B1 fp32\n" + p.key_averages().table(sort_by="cuda_time_total", row_limit=40)
    from omnidl.cameras import Equirectangular
    from omnidl.nn import ProjectedConv2d
    conv = ProjectedConv2d(256, 256, 3, padding=1, camera=Equirectangular(width=128, height=64)).to(dev)
    xg = torch.randn(1, 256, 64, 128, device=dev, requires_grad=True)

    def table(title: str) -> str:       # one forward+backward after 3 warm-ups
        for _ in range(3):
            conv(xg).sum().backward()
        torch.cuda.synchronize()
        with prof(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as p:
            conv(xg).sum().backward()
            torch.cuda.synchronize()
        return f"\n\n{title}\n" + p.key_averages().table(sort_by="cuda_time_total", row_limit=25)
    text += table("ProjectedConv2d 256ch 64x128 forward+backward")
    from omnidl.nn import triton_conv
    keep, triton_conv.ENABLED = triton_conv.ENABLED, True
    try:
        if triton_conv.applies(xg, conv.weight):
            text += table("the same, fused Triton kernels")
    finally:
        triton_conv.ENABLED = keep
    Path(path).write_text(text)
    print(f"# profile written: {path}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--amp", default="bf16", choices=["bf16", "fp16", "none"])
    ap.add_argument("--profile", default=None, help="write one FreDSNet forward's CUDA-time table here")
    ap.add_argument("--only", default="fps,conv,train", help="parts to run: fps, conv, train (comma-separated)")
    a = ap.parse_args(argv)
    if not torch.cuda.is_available():
        print("no CUDA device: benchmarks/gpu.py measured nothing (the GPU items are untested here)")
        return 0
    dev = torch.device(a.device)
    torch.backends.cudnn.benchmark = True
    amp_dtype = {"bf16": torch.bfloat16, "fp16": torch.float16, "none": None}[a.amp]
    print(f"# {torch.cuda.get_device_name(dev)}, torch {torch.__version__}, median of {a.reps} interleaved reps")
    chosen = set(a.only.split(","))
    parts = [part for name, part in (("fps", lambda: fredsnet_fps(dev, a.reps, a.amp, amp_dtype)),
                                     ("conv", lambda: projected_conv(dev, a.reps)),
                                     ("train", lambda: training_step(dev, a.reps, a.amp, amp_dtype)))
             if name in chosen]
    if a.profile:
        parts.append(lambda: profile(dev, a.profile, fredsnet="fps" in chosen))
    failed = 0
    for part in parts:
        try:
            part()
        except Exception:  # noqa: BLE001 -- one part's failure must not hide the others' figures
            failed += 1
            traceback.print_exc()
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
