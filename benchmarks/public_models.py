"""omnidl vs the public models, side by side in one process (issue 47).

    python benchmarks/public_models.py horizonnet --ref-dir DIR_WITH_model.py [--sizes 512x1024 256x512]
    python benchmarks/public_models.py fredsnet --ref-dir DIR_WITH_FreDSNet_model.py [--sizes 128x256]
        [--forward-sizes 256x512] [--compile] [--threads 2] [--reps 5] [--warmup 2] [--json out.json]

The public code is never part of this repository: bring it yourself (e.g. ``git show HEAD:model.py`` of
sunset1995/HorizonNet, ``git show HEAD:FreDSNet_model.py`` of Sbrunoberenguel/FreDSNet) into a folder and
pass it with ``--ref-dir`` (or the environment variables ``HORIZONNET_REF_DIR`` / ``FREDSNET_REF_DIR``).
Without a folder the line says so and nothing is measured for it.

Protocol: ``torch.set_num_threads(threads)``, random weights on both sides (the public constructors ask
torchvision for ImageNet weights; while they are built, the torchvision constructor is wrapped to build
without weights: no download), batch 1, ``warmup`` untimed calls per job, then ``reps`` repetitions that
time the public model and omnidl once each, order alternated every repetition (a load change hits both).
Ratio = median of the per-repetition omnidl / public ratios (< 1: omnidl faster); CPU seconds are printed
too (steadier than wall time on a shared machine). The 1-minute load average is printed and flagged.

* ``horizonnet``: forward (``eval()`` + ``no_grad``) of ``create_model("horizonnet", backbone="resnet50",
  rnn=True)`` vs ``HorizonNet("resnet50", True)``. The public forward only accepts 512x1024; at other sizes
  its LSTM is rebuilt for the feature width its towers give there and the public sub-modules are run in the
  public order without the size check. Reported, no target.
* ``fredsnet``: training step (``train()``, ``zero_grad`` + forward + ``CE(semantic) + L1(depth)`` +
  backward) of ``create_model("fredsnet", backbone="resnet50", width=1)`` vs ``FDS(14, "resnet50")`` at
  ``--sizes`` (target: omnidl <= 1.0x the public model in eager mode at 256x128), and the forward (``eval()`` +
  ``no_grad``) at ``--forward-sizes``. Also printed: each step's FLOP (PyTorch's counter: convolutions and matrix
  products) against the rate a 2048^3 float32 product reaches in the same run.
* ``--compile``: omnidl's model also compiled (``torch.compile``, Inductor; the forward with freezing, as
  ``omnidl predict --compile``), timed beside the two eager models; its compile time is printed.
"""
from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import statistics
import sys
import time
import warnings
from pathlib import Path
from typing import Callable, Iterator

import torch
import torch.nn as nn
import torch.nn.functional as F
import torchvision

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._timing import allocator_tag, host_line, is_loaded, load1, load_line  # noqa: E402

TARGETS = {"horizonnet": None, "fredsnet": 1.0}
FILES = {"horizonnet": "model.py", "fredsnet": "FreDSNet_model.py"}
ENV = {"horizonnet": "HORIZONNET_REF_DIR", "fredsnet": "FREDSNET_REF_DIR"}


@contextlib.contextmanager
def _no_pretrained(name: str) -> Iterator[None]:
    """While active, ``torchvision.models.<name>(...)`` builds without weights (no download)."""
    orig = getattr(torchvision.models, name)

    def build(*args, **kw):
        kw.pop("weights", None)
        kw.pop("pretrained", None)
        return orig(*args, weights=None, **kw)
    setattr(torchvision.models, name, build)
    try:
        yield
    finally:
        setattr(torchvision.models, name, orig)


def import_public(which: str, ref_dir: str):
    """Import the public model file of ``which`` from ``ref_dir`` (a clear error if it is not there)."""
    path = Path(ref_dir) / FILES[which]
    if not path.is_file():
        raise SystemExit(f"public_models.py: --ref-dir {ref_dir!r} has no {FILES[which]} (the public {which} "
                         f"model file is expected there)")
    sys.path.insert(0, str(path.parent))
    try:
        return importlib.import_module(path.stem)
    finally:
        sys.path.pop(0)


def public_horizonnet(mod, h: int, w: int) -> Callable[[torch.Tensor], object]:
    """The public ``HorizonNet("resnet50", True)`` as a callable for ``(1, 3, h, w)`` inputs (eval mode)."""
    with _no_pretrained("resnet50"):
        net = mod.HorizonNet("resnet50", True).eval()
    if (h, w) == (512, 1024):
        return net
    with torch.no_grad():                      # the feature width the towers give at this size
        feats = net.feature_extractor(torch.zeros(1, 3, h, w))
        width = net.reduce_height_module(feats, w // net.step_cols).shape[1]
    net.bi_rnn = nn.LSTM(input_size=width, hidden_size=net.rnn_hidden_size, num_layers=2, dropout=0.5,
                         bidirectional=True).eval()

    def run(x: torch.Tensor) -> torch.Tensor:  # the public forward's steps, without its 512x1024 check
        x = net._prepare_x(x)
        seq = net.reduce_height_module(net.feature_extractor(x), x.shape[3] // net.step_cols).permute(2, 0, 1)
        out = net.linear(net.drop_out(net.bi_rnn(seq)[0]))
        out = out.view(out.shape[0], out.shape[1], 3, net.step_cols).permute(1, 2, 0, 3)
        return out.contiguous().view(out.shape[0], 3, -1)
    run.parameters = net.parameters            # type: ignore[attr-defined]
    return run


def _time_pair(jobs: dict[str, Callable[[], object]], reps: int, warmup: int) -> dict[str, list[tuple[float, float]]]:
    """``{name: [(wall s, CPU s), ...]}``, order alternated every repetition."""
    for fn in jobs.values():
        for _ in range(warmup):
            fn()
    out: dict[str, list[tuple[float, float]]] = {k: [] for k in jobs}
    names = list(jobs)
    for r in range(reps):
        for k in (names if r % 2 == 0 else names[::-1]):
            t, c = time.perf_counter(), time.process_time()
            jobs[k]()
            out[k].append((time.perf_counter() - t, time.process_time() - c))
    return out


def _report(which: str, what: str, times: dict[str, list[tuple[float, float]]], threads: int,
            loads: tuple[float, float], target: float | None, key: str = "omnidl") -> dict:
    """One line per omnidl variant ``key`` against ``times["public"]``."""
    pub, om = times["public"], times[key]
    ratios = [o[0] / p[0] for o, p in zip(om, pub)]
    cpu_ratio = statistics.median(o[1] for o in om) / statistics.median(p[1] for p in pub)
    r = statistics.median(ratios)
    loaded = max(loads) > threads
    res = {"what": f"{what} ({key})", "public_s": statistics.median(p[0] for p in pub),
           "omnidl_s": statistics.median(o[0] for o in om), "ratio": r, "ratio_min": min(ratios),
           "ratio_max": max(ratios), "cpu_ratio": cpu_ratio, "target": target,
           "met": None if target is None else r <= target, "load1": list(loads), "loaded": loaded}
    verdict = "" if target is None else f" (target <= {target}x: {'met' if res['met'] else 'MISSED'})"
    print(f"TARGET {which} {what}, {key}: {res['omnidl_s']:.3f} s vs public {res['public_s']:.3f} s = {r:.2f}x "
          f"public [{min(ratios):.2f}-{max(ratios):.2f}], CPU-time ratio {cpu_ratio:.2f}x{verdict}; "
          f"load {loads[0]:.2f}-{loads[1]:.2f}" + (" [taken under load]" if loaded else "") + allocator_tag(),
          flush=True)
    return res


def _compiled(model: nn.Module, train: bool) -> tuple[nn.Module, float]:
    """``model`` compiled as omnidl compiles it (training: ``compile_for_training``; inference: with freezing),
    and the compile time measured on its first call by the caller (returned 0 here)."""
    from omnidl.engine.compile import compile_for_inference, compile_for_training
    if train:
        return compile_for_training(model, torch.device("cpu")), 0.0
    return compile_for_inference(model.eval(), "cpu"), 0.0


def _first_call_s(fn: Callable[[], object]) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def bench_horizonnet(mod, sizes: list[tuple[int, int]], reps: int, warmup: int, threads: int) -> list[dict]:
    from omnidl.models import create_model
    om = create_model("horizonnet", backbone="resnet50", rnn=True).eval()
    out = []
    for h, w in sizes:
        pub = public_horizonnet(mod, h, w)
        x = torch.rand(1, 3, h, w)
        l0 = load1()
        with torch.no_grad():
            times = _time_pair({"public": lambda: pub(x), "omnidl": lambda: om(x)}, reps, warmup)
        out.append(_report("horizonnet", f"forward {w}x{h}", times, threads, (l0, load1()), TARGETS["horizonnet"]))
    return out


def _train_step(model: nn.Module, x: torch.Tensor, keys: tuple[str, str]) -> Callable[[], None]:
    model.eval()
    with torch.no_grad():
        o = model(x)
    sem, dep = o[keys[0]], o[keys[1]]
    g = torch.Generator().manual_seed(0)
    labels = torch.randint(0, sem.shape[1], (x.shape[0],) + tuple(sem.shape[-2:]), generator=g)
    target = torch.rand(dep.shape, generator=g) * 5

    def run() -> None:
        model.train()
        model.zero_grad(set_to_none=True)
        o = model(x)
        (F.cross_entropy(o[keys[0]], labels) + F.l1_loss(o[keys[1]], target)).backward()
    return run


def _step_flop(step: Callable[[], None]) -> float:
    """Multiply-adds x 2 of the convolutions and matrix products in one call of ``step`` (PyTorch's counter)."""
    from torch.utils.flop_counter import FlopCounterMode
    counter = FlopCounterMode(display=False)
    with warnings.catch_warnings():      # the counter's module hooks warn that they are not serialisable
        warnings.simplefilter("ignore")
        with counter:
            step()
    return float(counter.get_total_flops())


def _gemm_rate(n: int = 2048, reps: int = 5) -> float:
    """FLOP/s of the fastest of ``reps`` float32 ``n x n`` matrix products: what the host's BLAS reaches now."""
    a, b, c = torch.randn(n, n), torch.randn(n, n), torch.empty(n, n)
    best = float("inf")
    for _ in range(reps + 1):
        t = time.perf_counter()
        torch.mm(a, b, out=c)
        best = min(best, time.perf_counter() - t)
    return 2 * n ** 3 / best


def bench_fredsnet(mod, sizes: list[tuple[int, int]], reps: int, warmup: int, threads: int,
                   forward_sizes: list[tuple[int, int]] = (), compile: bool = False) -> list[dict]:
    from omnidl.models import create_model
    with _no_pretrained("resnet50"):
        pub = mod.FDS(14, "resnet50")
    om = create_model("fredsnet", backbone="resnet50", width=1.0)
    out = []
    for h, w in sizes:
        x = torch.rand(1, 3, h, w)
        jobs = {"public": _train_step(pub, x, ("Semantic", "Depth")),
                "omnidl": _train_step(om, x, ("semantic", "depth"))}
        if compile:
            compiled, _ = _compiled(om, train=True)
            jobs["omnidl compiled"] = _train_step(compiled, x, ("semantic", "depth"))
            print(f"  compiled omnidl's training step in {_first_call_s(jobs['omnidl compiled']):.1f} s (its first "
                  "call, compile included)", flush=True)
        l0 = load1()
        times = _time_pair(jobs, reps, warmup)
        for key in [k for k in jobs if k != "public"]:
            res = _report("fredsnet", f"training step {w}x{h}", times, threads, (l0, load1()),
                          TARGETS["fredsnet"] if key == "omnidl" else None, key)
            out.append(res)
        # where the step stands against the arithmetic: its FLOP at the rate the BLAS reaches now
        flop = {k: _step_flop(jobs[k]) for k in ("public", "omnidl")}
        rate = _gemm_rate()
        step_s = statistics.median(t[0] for t in times["omnidl"])
        print(f"  FLOP per step: omnidl {flop['omnidl'] / 1e9:.1f} G, public {flop['public'] / 1e9:.1f} G; "
              f"float32 2048^3 product now {rate / 1e9:.0f} GFLOP/s; omnidl's eager step runs at "
              f"{flop['omnidl'] / step_s / 1e9:.0f} GFLOP/s ({flop['omnidl'] / step_s / rate:.0%})", flush=True)
    for h, w in forward_sizes:
        x = torch.rand(1, 3, h, w)
        pub.eval()
        om.eval()
        jobs = {"public": lambda: pub(x), "omnidl": lambda: om(x)}
        if compile:
            frozen, _ = _compiled(om, train=False)
            jobs["omnidl compiled"] = lambda: frozen(x)
            print(f"  compiled omnidl's forward in {_first_call_s(jobs['omnidl compiled']):.1f} s (its first call, "
                  "compile included)", flush=True)
        l0 = load1()
        with torch.no_grad():
            times = _time_pair(jobs, reps, warmup)
        for key in [k for k in jobs if k != "public"]:
            out.append(_report("fredsnet", f"forward {w}x{h}", times, threads, (l0, load1()), None, key))
    return out


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("which", choices=sorted(FILES))
    ap.add_argument("--ref-dir", default=None, help="folder with the public model file (never committed)")
    ap.add_argument("--sizes", nargs="*", default=None, help="HxW (default: the target sizes; none: skip)")
    ap.add_argument("--forward-sizes", nargs="*", default=["256x512"], help="fredsnet: HxW of the forward")
    ap.add_argument("--compile", action="store_true", help="also omnidl compiled (torch.compile, Inductor)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    ref_dir = a.ref_dir or os.environ.get(ENV[a.which])
    if not ref_dir:
        print(f"{a.which}: no public model given (--ref-dir or {ENV[a.which]}): nothing measured for this line")
        return []
    torch.set_num_threads(a.threads)
    torch.manual_seed(0)
    sizes = a.sizes if a.sizes is not None else (["512x1024", "256x512"] if a.which == "horizonnet" else ["128x256"])
    hw = [tuple(int(v) for v in s.lower().split("x")) for s in sizes]
    print(f"torch {torch.__version__}, {a.threads} threads, {a.reps} reps", flush=True)
    print(host_line(), flush=True)
    print(load_line(a.threads, "at start"), flush=True)
    mod = import_public(a.which, ref_dir)
    if a.which == "horizonnet":
        res = bench_horizonnet(mod, hw, a.reps, a.warmup, a.threads)     # type: ignore[arg-type]
    else:
        fwd = [tuple(int(v) for v in s.lower().split("x")) for s in a.forward_sizes]
        res = bench_fredsnet(mod, hw, a.reps, a.warmup, a.threads, fwd, a.compile)     # type: ignore[arg-type]
    print(load_line(a.threads, "at end"), flush=True)
    if a.json:
        from omnidl.utils.io import atomic_write_json
        atomic_write_json(a.json, {"which": a.which, "threads": a.threads, "reps": a.reps, "results": res,
                                   "loaded": is_loaded(a.threads)})
    return res


if __name__ == "__main__":
    main()
