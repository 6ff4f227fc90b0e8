"""Speed of ProjectedConv2d (the op torch.ops.omnidl.fixed_offset_conv2d) against nn.Conv2d and torchvision's
deform_conv2d on the CPU.

    python benchmarks/projected_conv.py [--threads 2] [--reps 7] [--configs 64x128x256 256x64x128]
                                        [--deform-reps 2] [--skip-deform]

Per config ``CxHxW`` (an equirectangular camera of the input size, 3x3, stride 1, padding 1, float32, batch 1),
forward (``no_grad``) and forward + backward (input and weight require grad) of

* ``conv2d`` / ``conv2d_cl``: ``nn.Conv2d`` on NCHW / channels-last input and weight (the baselines);
* ``projected`` / ``projected_cl``: ``ProjectedConv2d`` on the same;
* ``deform``: ``ProjectedConv2d(backend="torchvision")``: ``deform_conv2d`` with the same offsets (the reference;
  a 360° wrap tiles the input three times), checked against the op.

All variants run interleaved (one call of each per repetition, order alternated); a ratio is the median of the
per-repetition ratios against ``conv2d`` in the same memory format. Target (issue 47): forward + backward
<= 1.5x ``nn.Conv2d``. The load average is printed, and figures are flagged when it exceeds the threads.
"""
from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._timing import host_line, interleaved, is_loaded, load_line, ratio, target_line  # noqa: E402
from omnidl.cameras import Equirectangular  # noqa: E402
from omnidl.nn import ProjectedConv2d  # noqa: E402

TARGET_FWD_BWD = 1.5


def _layers(C: int, H: int, W: int):
    torch.manual_seed(0)
    cam = Equirectangular(width=W, height=H)
    conv = torch.nn.Conv2d(C, C, 3, padding=1)
    proj = ProjectedConv2d(C, C, 3, padding=1, camera=cam)
    deform = ProjectedConv2d(C, C, 3, padding=1, camera=cam, backend="torchvision")
    proj.load_state_dict(conv.state_dict())
    deform.load_state_dict(conv.state_dict())
    return conv, proj, deform


def _channels_last(m: torch.nn.Module) -> torch.nn.Module:
    import copy
    return copy.deepcopy(m).to(memory_format=torch.channels_last)


def _fwd(m, x):
    def run():
        with torch.no_grad():
            m(x)
    return run


def _fwd_bwd(m, x):
    xg = x.clone().requires_grad_(True)

    def run():
        m.zero_grad(set_to_none=True)
        xg.grad = None
        m(xg).sum().backward()
    return run


def run_config(C: int, H: int, W: int, reps: int, threads: int, deform_reps: int, skip_deform: bool) -> None:
    conv, proj, deform = _layers(C, H, W)
    x = torch.randn(1, C, H, W)
    xcl = x.contiguous(memory_format=torch.channels_last)
    conv_cl, proj_cl = _channels_last(conv), _channels_last(proj)
    with torch.no_grad():
        y = proj(x)
        if not skip_deform:
            err = float((deform(x) - y).abs().max() / y.abs().max())
            print(f"# {C}x{H}x{W}: op vs deform_conv2d, max relative difference {err:.1e}")
    loaded = is_loaded(threads, steal=False)
    for mode, make in (("forward", _fwd), ("fwd+bwd", _fwd_bwd)):
        jobs = {"conv2d": make(conv, x), "projected": make(proj, x), "conv2d_cl": make(conv_cl, xcl),
                "projected_cl": make(proj_cl, xcl)}
        caps = {}
        if not skip_deform:
            jobs["deform"] = make(deform, x)
            caps["deform"] = deform_reps
        t = interleaved(jobs, reps, reps_of=caps)
        loaded = loaded or is_loaded(threads)
        med = {k: 1e3 * statistics.median(v) for k, v in t.items()}
        print(f"{C}x{H}x{W} {mode}: " + ", ".join(f"{k} {v:.2f} ms" for k, v in med.items()))
        for fmt, base in (("projected", "conv2d"), ("projected_cl", "conv2d_cl")):
            r = ratio(t, fmt, base)
            figure = f"ProjectedConv2d {mode} {C} ch {H}x{W} ({'channels-last' if fmt.endswith('cl') else 'NCHW'})"
            target = f"<= {TARGET_FWD_BWD}x" if mode == "fwd+bwd" else None
            print(target_line(figure, f"{med[fmt]:.2f} ms", r, f"nn.Conv2d ({med[base]:.2f} ms)", target,
                              r <= TARGET_FWD_BWD if target else None, loaded))
        if "deform" in med:
            print(f"#   deform_conv2d: {med['deform'] / med['projected']:.1f}x the op ({med['deform']:.1f} ms)")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", nargs="+", default=["64x128x256", "256x64x128"], help="CxHxW")
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--deform-reps", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--skip-deform", action="store_true", help="leave out deform_conv2d (slow)")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    print(f"# ProjectedConv2d benchmark, float32, CPU, {a.threads} threads, median of {a.reps} interleaved reps")
    print(load_line(a.threads, "at start"))
    print(host_line())
    for cfg in a.configs:
        C, H, W = (int(v) for v in cfg.lower().split("x"))
        run_config(C, H, W, a.reps, a.threads, a.deform_reps, a.skip_deform)
    print(load_line(a.threads, "at end"))


if __name__ == "__main__":
    main()
