"""GPU speed (issue 17, item 8): FreDSNet fps, ProjectedConv2d vs cuDNN conv2d, a training step.

    python benchmarks/gpu.py [--device cuda] [--reps 20] [--amp bf16|fp16|none]

* FreDSNet (ResNet-50, width 1) forward at 512x256, batch 1, eval + no_grad, float32 and under autocast:
  frames per second (target >= 100 fps on an H100/H200-class GPU; the thesis reports 33 fps on an RTX 3090),
  as a ratio to torchvision's ResNet-50 forward at the same size in the same run;
* ``ProjectedConv2d`` (fast backend) forward and forward+backward vs ``nn.Conv2d`` (cuDNN) at 64 ch 128x256
  and 256 ch 64x128, batch 1 (target <= 1.5x);
* a FreDSNet training step (CE + L1, zero_grad + forward + backward + SGD step) at 256x128, batch 4.

Times are CUDA-event medians after warm-up (plans, cuDNN autotuning), interleaved per repetition. Prints a
note and exits 0 when no CUDA device is present (CPU speed: benchmarks/projected_conv.py, fredsnet.py).
"""
from __future__ import annotations

import argparse
import statistics
import sys
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


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--amp", default="bf16", choices=["bf16", "fp16", "none"])
    a = ap.parse_args(argv)
    if not torch.cuda.is_available():
        print("no CUDA device: benchmarks/gpu.py measured nothing (the GPU items are untested here)")
        return
    import torchvision

    from omnidl.cameras import Equirectangular
    from omnidl.models.fredsnet import FreDSNet
    from omnidl.nn import ProjectedConv2d

    dev = torch.device(a.device)
    torch.backends.cudnn.benchmark = True
    amp_dtype = {"bf16": torch.bfloat16, "fp16": torch.float16, "none": None}[a.amp]
    print(f"# {torch.cuda.get_device_name(dev)}, torch {torch.__version__}, median of {a.reps} interleaved reps")

    # 1. FreDSNet forward fps at 512x256
    torch.manual_seed(0)
    net = FreDSNet(backbone="resnet50", width=1.0).to(dev).eval()
    r50 = torchvision.models.resnet50().to(dev).eval().to(memory_format=torch.channels_last)
    x = torch.rand(1, 3, 256, 512, device=dev)

    def fwd(m, amp):
        def run():
            with torch.no_grad(), torch.autocast("cuda", dtype=amp or torch.float32, enabled=amp is not None):
                m(x)
        return run
    jobs = {"fredsnet fp32": fwd(net, None), "resnet50 fp32": fwd(r50, None)}
    if amp_dtype is not None:
        jobs[f"fredsnet {a.amp}"] = fwd(net, amp_dtype)
        jobs[f"resnet50 {a.amp}"] = fwd(r50, amp_dtype)
    t = _cuda_times(jobs, a.reps)
    for prec in ["fp32"] + ([a.amp] if amp_dtype is not None else []):
        ms = t[f"fredsnet {prec}"]
        print(f"TARGET FreDSNet forward 512x256 B1 {prec}: {1e3 / ms:.0f} fps ({ms:.2f} ms) = "
              f"{ms / t[f'resnet50 {prec}']:.2f}x resnet50 forward ({t[f'resnet50 {prec}']:.2f} ms) "
              f"(target >= 100 fps: {'met' if 1e3 / ms >= 100 else 'MISSED'})")

    # 2. ProjectedConv2d vs cuDNN conv2d
    for C, H, W in ((64, 128, 256), (256, 64, 128)):
        torch.manual_seed(0)
        fast = ProjectedConv2d(C, C, 3, padding=1, camera=Equirectangular(width=W, height=H)).to(dev)
        conv = torch.nn.Conv2d(C, C, 3, padding=1).to(dev)
        conv.load_state_dict(fast.state_dict())
        xi = torch.randn(1, C, H, W, device=dev)
        xg = xi.clone().requires_grad_(True)

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
        t = _cuda_times({"fast fwd": f(fast), "conv fwd": f(conv), "fast fwdbwd": fb(fast), "conv fwdbwd": fb(conv)},
                        a.reps)
        for what in ("fwd", "fwdbwd"):
            r = t[f"fast {what}"] / t[f"conv {what}"]
            print(f"TARGET ProjectedConv2d {what} {C}ch {H}x{W} B1: {t[f'fast {what}']:.3f} ms = {r:.2f}x cuDNN "
                  f"conv2d ({t[f'conv {what}']:.3f} ms) (target <= 1.5x: {'met' if r <= 1.5 else 'MISSED'})")

    # 3. training step
    torch.manual_seed(0)
    net = FreDSNet(backbone="resnet50", width=1.0).to(dev).train()
    opt = torch.optim.SGD(net.parameters(), lr=1e-4)
    xb = torch.rand(4, 3, 128, 256, device=dev)
    lab = torch.randint(0, 14, (4, 128, 256), device=dev)
    depth = torch.rand(4, 1, 128, 256, device=dev) * 5

    def step(amp):
        def run():
            opt.zero_grad(set_to_none=True)
            with torch.autocast("cuda", dtype=amp or torch.float32, enabled=amp is not None):
                out = net(xb)
                loss = F.cross_entropy(out["semantic"].float(), lab) + F.l1_loss(out["depth"].float(), depth)
            loss.backward()
            opt.step()
        return run
    jobs = {"step fp32": step(None)}
    if amp_dtype is not None and amp_dtype == torch.bfloat16:  # fp16 would need a GradScaler
        jobs[f"step {a.amp}"] = step(amp_dtype)
    t = _cuda_times(jobs, max(5, a.reps // 2))
    for k, ms in t.items():
        print(f"FreDSNet training {k} 256x128 B4: {ms:.1f} ms ({4e3 / ms:.0f} images/s)")


if __name__ == "__main__":
    main()
