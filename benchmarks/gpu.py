"""GPU speed: FreDSNet inference eager and compiled, ProjectedConv2d against cuDNN, a FreDSNet training step.

    python benchmarks/gpu.py [--device cuda] [--reps 20] [--amp bf16|fp16|none] [--only fps,conv,train]
                             [--compile-modes default,reduce-overhead] [--no-compile-train] [--budget-s 200]
                             [--profile FILE]

CUDA only: without a CUDA device it prints ``no CUDA device: nothing measured`` and exits 0 (the CPU figures come
from benchmarks/projected_conv.py and benchmarks/fredsnet.py). Each part times omnidl against a baseline in the
same run:

* ``fps``: FreDSNet (ResNet-50, width 1) forward at 512x256, batch 1, eval + ``no_grad``, against torchvision's
  ``resnet50`` run the same way: eager in float32 and under autocast float16 and bfloat16, each in NCHW and in
  channels-last (input and weights; ``channels_last=True``); then compiled with ``torch.compile`` (Inductor) under
  autocast ``--amp`` (float32 with ``--amp none``): mode ``default`` through
  :func:`omnidl.engine.compile.compile_for_inference` (freezing, as ``omnidl predict --compile``) and mode
  ``reduce-overhead`` (the same with CUDA graphs: batch-1 inference is launch-bound), resnet50 compiled alike.
  Target: >= 100 frames per second.
* ``conv``: ``ProjectedConv2d`` (equirectangular camera, 3x3, padding 1, float32, batch 1: one call of
  ``torch.ops.omnidl.fixed_offset_conv2d``) at 64 ch 128x256 and 256 ch 64x128, forward (``no_grad``) and
  forward + backward, against ``nn.Conv2d`` with the same weights (cuDNN, PyTorch's default TF32 policy).
  Target: <= 1.5x ``nn.Conv2d``.
* ``train``: a FreDSNet (ResNet-50, width 1) training step at 256x128, batch 4 (zero_grad, forward, cross-entropy
  + L1 loss, backward, SGD step), eager and compiled (:func:`omnidl.engine.compile.compile_for_training`), in
  float32 and under autocast ``--amp`` (float16 with a ``GradScaler``); ratios to the eager float32 step.

Times are medians of CUDA-event times over ``--reps`` repetitions after warm-up, the jobs of a part interleaved
(one call of each per repetition, order alternated); a ratio is the median of the per-repetition ratios. A
compiled job is called once before the warm-up and that call's wall time (tracing and compiling included) is
printed as its compile time. No new compilation starts once the script has run ``--budget-s`` seconds (the
skipped jobs are named), so that the run fits one device call. A part that fails prints its traceback and the
others still run (the exit status is 1 then). ``--profile FILE`` writes the CUDA-time tables of one FreDSNet
forward and one ProjectedConv2d forward + backward (torch.profiler).
"""
from __future__ import annotations

import argparse
import contextlib
import copy
import statistics
import sys
import time
import traceback
from collections.abc import Callable
from pathlib import Path

import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._timing import ratio, target_line  # noqa: E402

#: autocast dtype of each precision's name (``None``: float32, no autocast)
PRECISIONS = {"fp32": None, "fp16": torch.float16, "bf16": torch.bfloat16}
FPS_TARGET = 100.0
CONV_TARGET = 1.5
CONV_CONFIGS = ((64, 128, 256), (256, 64, 128))


class Budget:
    """Seconds since the start; :meth:`allows` says whether a new compilation may start."""

    def __init__(self, seconds: float):
        self.seconds = seconds
        self.t0 = time.perf_counter()

    def spent(self) -> float:
        return time.perf_counter() - self.t0

    def allows(self, what: str) -> bool:
        if self.spent() < self.seconds:
            return True
        print(f"# skipped {what}: the time budget of {self.seconds:.0f} s (--budget-s) is spent "
              f"({self.spent():.0f} s so far)")
        return False


def autocast(prec: str):
    """``torch.autocast`` on CUDA for ``prec`` (``fp16``/``bf16``), or no context for ``fp32``."""
    dt = PRECISIONS[prec]
    return contextlib.nullcontext() if dt is None else torch.autocast("cuda", dtype=dt)


def cuda_times(jobs: dict[str, Callable[[], object]], reps: int, warmup: int = 3) -> dict[str, list[float]]:
    """CUDA-event milliseconds of every job per repetition (one call of each, order alternated every repetition)
    after ``warmup`` untimed rounds. A job whose wall time is well above its event time (its work ran outside
    the current stream, or the host stalled it) is named in a note."""
    for _ in range(warmup):
        for fn in jobs.values():
            fn()
    torch.cuda.synchronize()
    names = list(jobs)
    out: dict[str, list[float]] = {k: [] for k in names}
    wall: dict[str, list[float]] = {k: [] for k in names}
    for r in range(reps):
        for k in (names if r % 2 == 0 else names[::-1]):
            s, e = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            t0 = time.perf_counter()
            s.record()
            jobs[k]()
            e.record()
            torch.cuda.synchronize()
            wall[k].append((time.perf_counter() - t0) * 1e3)
            out[k].append(s.elapsed_time(e))
    odd = [f"{k} ({statistics.median(wall[k]):.2f} ms wall, {statistics.median(out[k]):.2f} ms events)"
           for k in names if statistics.median(wall[k]) > 1.25 * statistics.median(out[k]) + 0.1]
    if odd:
        print("# wall time well above the CUDA-event time: " + "; ".join(odd))
    return out


def med(times: dict[str, list[float]], k: str) -> float:
    return statistics.median(times[k])


def first_call_s(fn: Callable[[], object]) -> float:
    """Wall seconds of one call of ``fn`` (a compiled job's first: tracing and compiling included)."""
    torch.cuda.synchronize()
    t0 = time.perf_counter()
    fn()
    torch.cuda.synchronize()
    return time.perf_counter() - t0


def graph_breaks(reset: bool = False) -> str:
    """TorchDynamo's graph breaks since the last ``reset`` (count and the first reasons), for the compile lines."""
    try:
        from torch._dynamo.utils import counters
    except ImportError:  # pragma: no cover
        return "graph breaks: unknown"
    if reset:
        counters["graph_break"].clear()
        return ""
    breaks = counters["graph_break"]
    n = sum(breaks.values())
    return f"{n} graph breaks" + (f" ({'; '.join(str(k)[:80] for k in list(breaks)[:3])})" if n else "")


def compiled_once(label: str, job: Callable[[], object]) -> Callable[[], object]:
    """Call a compiled ``job`` once (compiling it) and print its compile time and graph breaks."""
    graph_breaks(reset=True)
    s = first_call_s(job)
    print(f"# {label}: compiled in {s:.1f} s (wall time of the first call), {graph_breaks()}", flush=True)
    return job


def _allow_recompiles() -> None:
    """Each compiled model (and precision) is an entry of TorchDynamo's cache for the same code: raise the limit
    of entries per code object so that none falls back to eager."""
    import torch._dynamo.config as cfg
    for name in ("recompile_limit", "cache_size_limit"):
        if hasattr(cfg, name):
            setattr(cfg, name, max(getattr(cfg, name), 64))


class FrozenMode(torch.nn.Module):
    """An eval-mode model compiled by Inductor with freezing in a given ``mode`` (``reduce-overhead``: CUDA
    graphs), called under ``no_grad`` like :class:`omnidl.engine.compile.FrozenInference` (mode default)."""

    def __init__(self, model: torch.nn.Module, mode: str):
        super().__init__()
        self.compiled = torch.compile(model, mode=mode)

    def forward(self, x):
        import torch._inductor.config as inductor_config
        with torch.no_grad(), inductor_config.patch(freezing=True):
            return self.compiled(x)


def compiled_for_inference(model: torch.nn.Module, mode: str, dev) -> torch.nn.Module:
    from omnidl.engine.compile import check_inductor, compile_for_inference
    if mode == "default":
        return compile_for_inference(model, dev, option="benchmarks/gpu.py --compile-modes")
    check_inductor(dev, "benchmarks/gpu.py --compile-modes", "Pass --compile-modes none")
    return FrozenMode(model, mode)


def fredsnet_fps(dev, a, budget: Budget) -> None:
    """Part ``fps``: FreDSNet forward at 512x256, batch 1, eager and compiled, against torchvision's resnet50."""
    import torchvision

    from omnidl.models.fredsnet import FreDSNet
    torch.manual_seed(0)
    models = {"fredsnet": FreDSNet(backbone="resnet50", width=1.0).to(dev).eval(),
              "resnet50": torchvision.models.resnet50().to(dev).eval()}
    cl = {"fredsnet": FreDSNet(backbone="resnet50", width=1.0, channels_last=True).to(dev).eval(),
          "resnet50": copy.deepcopy(models["resnet50"]).to(memory_format=torch.channels_last)}
    cl["fredsnet"].load_state_dict(models["fredsnet"].state_dict())
    x = torch.rand(1, 3, 256, 512, device=dev)
    x_cl = x.contiguous(memory_format=torch.channels_last)

    def forward(m, prec, inp):
        def run():
            with torch.no_grad(), autocast(prec):
                m(inp)
        return run
    jobs, labels = {}, []
    for prec in PRECISIONS:
        for fmt, ms, inp in (("", models, x), (" channels-last", cl, x_cl)):
            label = f"eager {prec}{fmt}"
            labels.append(label)
            for name, m in ms.items():
                jobs[f"{name} {label}"] = forward(m, prec, inp)
    cprec = a.amp if a.amp != "none" else "fp32"
    for mode in a.compile_modes:
        label = f"compiled {mode} {cprec}"
        if not budget.allows(f"FreDSNet and resnet50 {label}"):
            continue
        try:
            for name, m in models.items():
                jobs[f"{name} {label}"] = compiled_once(
                    f"{name} {label}", forward(compiled_for_inference(copy.deepcopy(m), mode, dev), cprec, x))
            labels.append(label)
        except Exception as e:  # noqa: BLE001 -- reported; the eager figures still stand
            print(f"# {label}: not compiled ({type(e).__name__}: {str(e).splitlines()[0][:200] if str(e) else ''})")
            traceback.print_exc()
            for name in models:
                jobs.pop(f"{name} {label}", None)
    t = cuda_times(jobs, a.reps)
    for label in labels:
        ms, base = med(t, f"fredsnet {label}"), med(t, f"resnet50 {label}")
        fps = 1e3 / ms
        print(target_line(f"FreDSNet forward 512x256 B1 {label}", f"{fps:.0f} fps ({ms:.2f} ms)",
                          ratio(t, f"fredsnet {label}", f"resnet50 {label}"),
                          f"resnet50 forward {label} ({base:.2f} ms)", f">= {FPS_TARGET:.0f} fps", fps >= FPS_TARGET))


def projected_conv(dev, a, budget: Budget) -> None:
    """Part ``conv``: ProjectedConv2d against cuDNN nn.Conv2d, forward and forward + backward."""
    from omnidl.cameras import Equirectangular
    from omnidl.nn import ProjectedConv2d
    for C, H, W in CONV_CONFIGS:
        torch.manual_seed(0)
        proj = ProjectedConv2d(C, C, 3, padding=1, camera=Equirectangular(width=W, height=H)).to(dev)
        conv = torch.nn.Conv2d(C, C, 3, padding=1).to(dev)
        conv.load_state_dict(proj.state_dict())
        xi = torch.randn(1, C, H, W, device=dev)
        xg = xi.clone().requires_grad_(True)

        def fwd(m, xi=xi):
            def run():
                with torch.no_grad():
                    m(xi)
            return run

        def fwd_bwd(m, xg=xg):
            def run():
                xg.grad = None
                m.zero_grad(set_to_none=True)
                m(xg).sum().backward()
            return run
        t = cuda_times({"projected fwd": fwd(proj), "conv fwd": fwd(conv),
                        "projected fwdbwd": fwd_bwd(proj), "conv fwdbwd": fwd_bwd(conv)}, a.reps)
        for what, name in (("fwd", "forward"), ("fwdbwd", "forward+backward")):
            r = ratio(t, f"projected {what}", f"conv {what}")
            print(target_line(f"ProjectedConv2d {name} {C}ch {H}x{W} B1 fp32", f"{med(t, f'projected {what}'):.3f} ms",
                              r, f"cuDNN nn.Conv2d ({med(t, f'conv {what}'):.3f} ms)", f"<= {CONV_TARGET}x",
                              r <= CONV_TARGET))


def training_step(dev, a, budget: Budget) -> None:
    """Part ``train``: a FreDSNet training step (CE + L1, SGD) at 256x128, batch 4, eager and compiled."""
    from omnidl.engine.compile import compile_for_training
    from omnidl.models.fredsnet import FreDSNet
    torch.manual_seed(0)
    net = FreDSNet(backbone="resnet50", width=1.0).to(dev).train()
    opt = torch.optim.SGD(net.parameters(), lr=1e-4, momentum=0.9)
    xb = torch.rand(4, 3, 128, 256, device=dev)
    lab = torch.randint(0, net.num_classes, (4, 128, 256), device=dev)
    depth = torch.rand(4, 1, 128, 256, device=dev) * 5
    aprec = a.amp if a.amp != "none" else None
    scaler = torch.amp.GradScaler("cuda") if aprec == "fp16" else None

    def step(model, prec):
        def run():
            opt.zero_grad(set_to_none=True)
            with autocast(prec):
                out = model(xb)
                loss = F.cross_entropy(out["semantic"].float(), lab) + F.l1_loss(out["depth"].float(), depth)
            if prec == "fp16":
                scaler.scale(loss).backward()
                scaler.step(opt)
                scaler.update()
            else:
                loss.backward()
                opt.step()
        return run
    precs = ["fp32"] + ([aprec] if aprec else [])
    jobs = {f"eager {p}": step(net, p) for p in precs}
    compiled = None
    for p in ([] if a.no_compile_train else precs):
        if not budget.allows(f"the compiled FreDSNet training step {p}"):
            continue
        try:
            if compiled is None:                # one compiled module: autocast on/off recompiles it
                compiled = compile_for_training(net, dev)
            jobs[f"compiled {p}"] = compiled_once(f"FreDSNet training step compiled {p} (forward and backward)",
                                                  step(compiled, p))
        except Exception as e:  # noqa: BLE001 -- reported; the eager figures still stand
            print(f"# compiled training step {p}: failed ({type(e).__name__}: "
                  f"{str(e).splitlines()[0][:200] if str(e) else ''})")
            traceback.print_exc()
    t = cuda_times(jobs, max(5, a.reps // 2))
    base = med(t, "eager fp32")
    for k in jobs:
        ms = med(t, k)
        print(target_line(f"FreDSNet training step 256x128 B4 {k}", f"{ms:.1f} ms ({4e3 / ms:.0f} images/s)",
                          ratio(t, k, "eager fp32"), f"eager fp32 step ({base:.1f} ms)"))


def profile(dev, path: str) -> None:
    """The CUDA-time tables of one FreDSNet forward at 512x256 (eager float32) and one ProjectedConv2d forward +
    backward at 256 ch 64x128, each after warm-up, written to ``path``."""
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as prof

    from omnidl.cameras import Equirectangular
    from omnidl.models.fredsnet import FreDSNet
    from omnidl.nn import ProjectedConv2d

    def table(title: str, fn: Callable[[], object], rows: int) -> str:
        for _ in range(3):
            fn()
        torch.cuda.synchronize()
        with prof(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as p:
            fn()
            torch.cuda.synchronize()
        return f"{title}\n" + p.key_averages().table(sort_by="cuda_time_total", row_limit=rows) + "\n\n"
    net = FreDSNet(backbone="resnet50", width=1.0).to(dev).eval()
    x = torch.rand(1, 3, 256, 512, device=dev)

    def forward():
        with torch.no_grad():
            net(x)
    text = table("FreDSNet forward 512x256 B1 fp32 (eager)", forward, 40)
    conv = ProjectedConv2d(256, 256, 3, padding=1, camera=Equirectangular(width=128, height=64)).to(dev)
    xg = torch.randn(1, 256, 64, 128, device=dev, requires_grad=True)
    text += table("ProjectedConv2d 256ch 64x128 forward+backward", lambda: conv(xg).sum().backward(), 25)
    Path(path).write_text(text)
    print(f"# profile written: {path}")


PARTS = {"fps": fredsnet_fps, "conv": projected_conv, "train": training_step}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda", help="a CUDA device (cuda, cuda:N)")
    ap.add_argument("--reps", type=int, default=20, help="timed repetitions per job (training: half, at least 5)")
    ap.add_argument("--amp", default="bf16", choices=["bf16", "fp16", "none"],
                    help="autocast dtype of the compiled forward and of the AMP training step")
    ap.add_argument("--only", default="fps,conv,train", help="parts to run: fps, conv, train (comma-separated)")
    ap.add_argument("--compile-modes", default="default,reduce-overhead",
                    help="torch.compile modes of the fps part (comma-separated; 'none': no compiled forward)")
    ap.add_argument("--no-compile-train", action="store_true", help="time the training step eager only")
    ap.add_argument("--budget-s", type=float, default=200.0,
                    help="start no new compilation after this many seconds (default 200)")
    ap.add_argument("--profile", default=None, help="write the CUDA-time tables of one FreDSNet forward and one "
                                                    "ProjectedConv2d forward+backward here")
    a = ap.parse_args(argv)
    chosen = [p.strip() for p in a.only.split(",") if p.strip()]
    unknown = [p for p in chosen if p not in PARTS]
    if unknown:
        ap.error(f"--only: unknown parts {unknown}; choose from {list(PARTS)}")
    a.compile_modes = [m.strip() for m in a.compile_modes.split(",") if m.strip() and m.strip() != "none"]
    if not torch.cuda.is_available():
        print("no CUDA device: nothing measured (benchmarks/gpu.py needs CUDA; the CPU figures come from "
              "benchmarks/projected_conv.py and benchmarks/fredsnet.py)")
        return 0
    dev = torch.device(a.device)
    if dev.type != "cuda":
        ap.error(f"--device must be a CUDA device, got {a.device!r}")
    torch.cuda.set_device(dev)
    from torch import _dynamo
    torch.backends.cudnn.benchmark = True
    _allow_recompiles()
    budget = Budget(a.budget_s)
    print(f"# {torch.cuda.get_device_name(dev)}, torch {torch.__version__}, CUDA {torch.version.cuda}, cuDNN "
          f"{torch.backends.cudnn.version()}; cudnn.benchmark on, TF32: convolutions "
          f"{torch.backends.cudnn.allow_tf32}, matmul {torch.backends.cuda.matmul.allow_tf32} (PyTorch's defaults); "
          f"median of {a.reps} interleaved reps", flush=True)
    failed = 0
    for name in chosen:
        t0 = time.perf_counter()
        try:
            PARTS[name](dev, a, budget)
        except Exception:  # noqa: BLE001 -- one part's failure must not hide the others' figures
            failed += 1
            traceback.print_exc()
        finally:
            _dynamo.reset()                # frees the compiled graphs (and CUDA-graph pools) of the part
            torch.cuda.empty_cache()
        print(f"# part {name}: {time.perf_counter() - t0:.0f} s", flush=True)
    if a.profile:
        try:
            profile(dev, a.profile)
        except Exception:  # noqa: BLE001
            failed += 1
            traceback.print_exc()
    print(f"# total {budget.spent():.0f} s")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
