"""Visual gyroscope (thesis ch. 6): CPU speed of HoLiNet + MPP + PVG, and accuracy histograms.

    python benchmarks/gyroscope.py speed [--threads 2] [--reps 5] [--warmup 2] [--json out.json]
    python benchmarks/gyroscope.py accuracy [--out benchmarks/results/gyroscope] [--n 40]

``speed``: frames per second of ``Gyroscope.estimate`` end to end (one call per frame: HoLiNet forward at
256x128, horizon RANSAC, MPP yaw n = 3 with 4 starts, PVG n = 5) with the ResNet-50 + EquiConv thesis model
and the small CPU model, random weights; the network runs but the tilt comes from ground-truth heat maps (an
untrained net gives no valid horizon), so MPP/PVG start where a trained net would put them. The stages are
also timed alone (also as in a frame: with the reference's parts prepared once). ``Gyroscope.track`` (default
``pipeline="auto"``: after the first frame, the network of the next frame in a worker thread while this one's
horizon fit, MPP and PVG run, one intra-op thread each, where that pays, else ``estimate`` frame by frame) is timed
on a few frames: its fps is the throughput of a stream.
The named baseline, interleaved in the same run, is MPP evaluated as the published gyroscope evaluates it
(``tests/reference/gyroscope.py``'s ``mpp_yaw_reference`` with ``tries=1, grid_height=0``: one start, all N x N
Gaussian sums re-computed every Gauss-Newton iteration) on a pure-yaw pair, against omnidl's MPP with one start
on the same pair. Targets (issue 17, item 1): >= 8 fps (ResNet-50-Equi), >= 20 fps (small), MPP >= 1.5x the
baseline. (The published MPP gyroscope runs at ~3 images/s at n = 3.)

``accuracy``: error histograms (PNG) and a markdown/JSON table of
(a) the horizon hook on ground-truth heat maps of random rotations (tilts up to 180°),
(b) MPP on pure yaws uniform in (-180°, 180°] (procedural textured sphere, exact renders; and a
    synthetic room of :mod:`omnidl.synth` rotated by resampling),
(c) PVG from random ±10° per-axis 3-DoF perturbations,
(d) the whole pipeline (ground-truth heat maps + MPP + PVG) on random 3-DoF rotations.
The load average is printed: numbers taken on a busy machine are not comparable.
"""
from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._timing import median_times  # noqa: E402
from omnidl.data.horizon import horizon_heatmaps  # noqa: E402
from omnidl.geometry.horizon import fit_horizon  # noqa: E402
from omnidl.geometry.panorama import rotate_panorama  # noqa: E402
from omnidl.geometry.rotations import (axis_angle_to_matrix, random_tilt_rotation, rotation_y,  # noqa: E402
                                       up_from_rotation)
from omnidl.metrics.rotation import horizon_normal_error, rotation_error  # noqa: E402
from omnidl.postprocess.gyroscope.icosahedron import icosahedron_vertices  # noqa: E402
from omnidl.postprocess.gyroscope.mpp import mpp_yaw  # noqa: E402
from omnidl.postprocess.gyroscope.pipeline import Gyroscope, GyroscopeOptions, model_horizon_fn  # noqa: E402
from omnidl.postprocess.gyroscope.pvg import pvg_refine  # noqa: E402
from omnidl.postprocess.gyroscope.scene import procedural_panorama  # noqa: E402


def speed(args) -> dict:
    """Per-frame cost of the gyroscope at 256x128, every job interleaved with the baseline (see module doc)."""
    from benchmarks._timing import host_line, interleaved, is_loaded, load_line, ratio, target_line
    from tests.reference.gyroscope import mpp_yaw_reference, pvg_refine_reference
    from omnidl.models import create_model
    from omnidl.utils.threads import limit_threads
    torch.set_num_threads(args.threads)
    icosahedron_vertices(5)
    R = random_tilt_rotation(1, math.radians(30), generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    ref = procedural_panorama(None, 128, 256, seed=1)
    cur = procedural_panorama(R, 128, 256, seed=1)
    hl, vp = horizon_heatmaps(R.float(), 64, 128)
    hl0, vp0 = horizon_heatmaps(torch.eye(3)[None], 64, 128)
    Ry = rotation_y(torch.tensor([0.6], dtype=torch.float64))
    cur_yaw = procedural_panorama(Ry, 128, 256, seed=1)  # pure yaw: both MPP solvers start from identity
    nets = {"holinet_resnet50_equi": create_model("holinet", backbone="resnet50", conv="equi").eval(),
            "holinet_small_std": create_model("holinet", backbone="resnet18", width=0.25, conv="std").eval()}

    def gyro(net, threads):
        state = {"maps": (hl0, vp0)}
        run_net = model_horizon_fn(net, 128)

        def hfn(images):  # the network runs (its cost counts) but the tilt comes from ground-truth maps:
            run_net(images)  # random weights give no valid horizon
            return state["maps"]
        g = Gyroscope(hfn, GyroscopeOptions(photometric_threads=threads))
        g.set_reference(ref[0])
        state["maps"] = (hl, vp)
        return g

    gyros = {tag: gyro(net, "auto") for tag, net in nets.items()}
    g_all_threads = gyro(nets["holinet_small_std"], None)
    gs = gyros["holinet_small_std"]  # its prepared reference parts, as the pipeline passes them
    seq = [cur] * TRACK_FRAMES
    one = lambda fn: (lambda: _single(fn))  # noqa: E731 - photometric stages as the pipeline runs them

    def _single(fn):
        with limit_threads("auto"):
            fn()
    def baseline():  # MPP as the published gyroscope evaluates it: one start, the N x N sums every iteration
        return mpp_yaw_reference(cur_yaw, ref, level=3, lambda_g=0.325, tries=1, grid_height=0)
    jobs = {
        "baseline MPP (reference-style, 1 start)": one(baseline),
        "MPP 1 start": one(lambda: mpp_yaw(cur_yaw, ref, level=3, lambda_g=0.325, tries=1)),
        "MPP 4 starts": one(lambda: mpp_yaw(cur, ref, R.float(), level=3, lambda_g=0.325, tries=4)),
        "PVG (n=5)": one(lambda: pvg_refine(cur, ref, R.float(), level=5)),
        "MPP 4 starts, prepared reference (as in a frame)": one(lambda: mpp_yaw(
            cur, ref, R.float(), level=3, lambda_g=0.325, tries=4, reference_field=gs.ref_mpp_field)),
        "PVG (n=5), prepared reference (as in a frame)": one(lambda: pvg_refine(
            cur, ref, R.float(), level=5, reference_values=gs.ref_pvg)),
        "MPP 1 start, reference loop (before issue 17)": one(
            lambda: mpp_yaw_reference(cur_yaw, ref, level=3, lambda_g=0.325, tries=1)),
        "PVG (n=5), reference loop (before issue 17)": one(
            lambda: pvg_refine_reference(cur, ref, R.float(), level=5)),
        "horizon RANSAC": one(lambda: fit_horizon(hl, vp)),
        "frame HoLiNet-R50-Equi": lambda: gyros["holinet_resnet50_equi"].estimate(cur),
        "frame HoLiNet-small": lambda: gyros["holinet_small_std"].estimate(cur),
        "frame HoLiNet-small, photometric on all threads": lambda: g_all_threads.estimate(cur),
        f"{TRACK_FRAMES} frames HoLiNet-R50-Equi, track()": lambda: list(gyros["holinet_resnet50_equi"].track(seq)),
        f"{TRACK_FRAMES} frames HoLiNet-small, track()": lambda: list(gs.track(seq)),
    }
    for tag, net in nets.items():
        x = torch.rand(1, 3, 128, 256)

        def fwd(net=net, x=x):
            with torch.no_grad():
                net(x)
        jobs[f"forward {tag}"] = fwd
    print(f"# gyroscope speed, 256x128, batch 1, {args.threads} threads (photometric stages threads='auto'), median of "
          f"{args.reps} interleaved reps")
    print(host_line())
    print(load_line(args.threads, "at start"))
    loaded = is_loaded(args.threads, steal=False)
    times = interleaved(jobs, args.reps, warmup=args.warmup)
    loaded = loaded or is_loaded(args.threads)
    print(load_line(args.threads, "at end"))
    med = {k: statistics.median(v) for k, v in times.items()}
    base = "baseline MPP (reference-style, 1 start)"
    print("| job | median ms | min ms | fps | vs baseline MPP |")
    print("|---|---|---|---|---|")
    for k in jobs:
        print(f"| {k} | {med[k] * 1e3:.1f} | {min(times[k]) * 1e3:.1f} | {1 / med[k]:.1f} | "
              f"{ratio(times, k, base):.2f}x |")
    it_b = baseline().iterations
    it_f = mpp_yaw(cur_yaw, ref, level=3, lambda_g=0.325, tries=1).iterations
    r_mpp = ratio(times, base, "MPP 1 start")
    print(f"(iterations to converge on the pure-yaw pair: baseline {it_b}, omnidl MPP {it_f})")
    print(f"issue 17: MPP 1 start {ratio(times, 'MPP 1 start, reference loop (before issue 17)', 'MPP 1 start'):.2f}x "
          f"faster, PVG {ratio(times, 'PVG (n=5), reference loop (before issue 17)', 'PVG (n=5)'):.2f}x faster "
          "than the reference loops (same results, tests/postprocess/gyroscope/test_fast_paths.py)")
    print(target_line("MPP 1 start speed-up", f"{med['MPP 1 start'] * 1e3:.1f} ms", r_mpp,
                      "faster than the reference-style baseline", ">= 1.5x", r_mpp >= 1.5, loaded))
    res = {"threads": args.threads, "loaded": loaded, "median_s": med, "mpp_speedup": r_mpp}
    for tag, k, tgt in (("HoLiNet-ResNet-50-Equi + MPP + PVG", "frame HoLiNet-R50-Equi", 8.0),
                        ("HoLiNet-small + MPP + PVG", "frame HoLiNet-small", 20.0)):
        fps = 1 / med[k]
        print(target_line(f"{tag} fps", f"{fps:.2f} fps ({med[k] * 1e3:.0f} ms/frame)", ratio(times, k, base),
                          "the baseline MPP's time", f">= {tgt:g} fps", fps >= tgt, loaded))
        res[k + " fps"] = fps
        kt = f"{TRACK_FRAMES} frames {k[len('frame '):]}, track()"
        fps_t = TRACK_FRAMES / med[kt]
        print(target_line(f"{tag} fps, stream (Gyroscope.track, pipeline='auto': network of frame k+1 || horizon "
                          "fit + MPP + PVG of frame k, 1 thread each, where that pays)",
                          f"{fps_t:.2f} fps ({med[kt] * 1e3 / TRACK_FRAMES:.0f} ms/frame)",
                          ratio(times, kt, base) / TRACK_FRAMES, "the baseline MPP's time", f">= {tgt:g} fps",
                          fps_t >= tgt, loaded))
        res[kt + " fps"] = fps_t
    fwd_share = med["forward holinet_resnet50_equi"] / med["frame HoLiNet-R50-Equi"]
    print(f"HoLiNet-R50-Equi forward = {fwd_share:.0%} of its frame; photometric all-threads / 'auto' frame "
          f"(small net) = {ratio(times, 'frame HoLiNet-small, photometric on all threads', 'frame HoLiNet-small'):.2f}x")
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=2, default=float))
    return res


TRACK_FRAMES = 4  # frames per timed Gyroscope.track() call


def _stats(err: torch.Tensor, thr: float) -> dict:
    e = err.double()
    return {"n": int(e.numel()), "mean": float(e.mean()), "median": float(e.median()),
            "p90": float(e.quantile(0.9)), "max": float(e.max()), f"success@{thr:g}": float((e < thr).double().mean())}


def accuracy(args) -> dict:
    torch.set_num_threads(args.threads)
    g = torch.Generator().manual_seed(0)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results: dict = {}
    errs: dict = {}
    # (a) horizon hook, tilts up to 180 deg
    R = random_tilt_rotation(5 * args.n, math.pi, generator=g, dtype=torch.float64)
    hl, vp = horizon_heatmaps(R.float(), 64, 128)
    e = horizon_normal_error(fit_horizon(hl, vp)["up"].double(), up_from_rotation(R))
    errs["horizon hook (GT maps, tilt<=180)"] = (e, 0.5)
    # (b) MPP pure yaw, procedural sphere (exact) and a synthetic room (resampled)
    scenes = {"procedural": procedural_panorama(None, 128, 256, seed=11)}
    try:
        from omnidl.data.synthetic import SyntheticPanoramaDataset
        scenes["synthetic room"] = SyntheticPanoramaDataset(width=256, height=128, length=1, split="test",
                                                            layout=False)[0]["image"][None]
    except Exception as exc:  # noqa: BLE001 - the accuracy table still runs on the procedural scene
        print(f"synthetic room unavailable ({exc}); procedural scene only")
    yaws = (torch.rand(args.n, generator=g, dtype=torch.float64) * 2 - 1) * math.pi
    yaws[0] = math.pi
    for name, ref in scenes.items():
        Ry = rotation_y(yaws)
        cur = procedural_panorama(Ry, 128, 256, seed=11) if name == "procedural" else rotate_panorama(
            ref.expand(args.n, -1, -1, -1).double(), Ry)[0].float()
        r = mpp_yaw(cur, ref, level=3, lambda_g=0.325)
        errs[f"MPP pure yaw ({name})"] = (rotation_error(Ry, r.rotation.double()), 3.0)
    # (c) PVG from +-10 deg per axis
    ref = scenes["procedural"]
    Rg = random_tilt_rotation(args.n, math.pi, generator=g, dtype=torch.float64)
    cur = procedural_panorama(Rg, 128, 256, seed=11)
    w = (torch.rand(args.n, 3, generator=g, dtype=torch.float64) * 2 - 1) * math.radians(10)
    R0 = axis_angle_to_matrix(w) @ Rg
    r = pvg_refine(cur, ref, R0.float(), level=5)
    errs["PVG from +-10 deg/axis"] = (rotation_error(Rg, r.rotation.double()), 0.2)
    results["pvg_initial_error_mean_deg"] = float(rotation_error(Rg, R0).mean())
    # (d) whole pipeline on GT heat maps
    table = {0: torch.eye(3, dtype=torch.float64)}

    def gt_maps(images):
        Rs = Rg if images.shape[0] == args.n else torch.eye(3, dtype=torch.float64)[None]
        return horizon_heatmaps(Rs.float(), 64, 128)
    gy = Gyroscope(gt_maps, GyroscopeOptions(work_height=128))
    gy.set_reference(ref[0])
    est = gy.estimate(cur)
    errs["pipeline GT maps + MPP + PVG"] = (rotation_error(Rg, est["rotation"].double()), 0.5)
    del table
    for k, (e, thr) in errs.items():
        results[k] = _stats(e, thr)
    # histogram PNG + table
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, len(errs), figsize=(4 * len(errs), 3.2))
    for ax, (k, (e, thr)) in zip(axes, errs.items()):
        ax.hist(e.numpy(), bins=20, color="tab:blue")
        ax.axvline(thr, color="r", ls="--", label=f"target {thr:g}°")
        ax.set_title(k, fontsize=8)
        ax.set_xlabel("error (deg)")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "gyroscope_errors.png", dpi=100)
    lines = ["| experiment | n | mean ° | median ° | p90 ° | max ° | success |", "|---|---|---|---|---|---|---|"]
    for k, s in results.items():
        if isinstance(s, dict):
            succ = next(v for kk, v in s.items() if kk.startswith("success"))
            thr = next(kk for kk in s if kk.startswith("success"))
            lines.append(f"| {k} | {s['n']} | {s['mean']:.3f} | {s['median']:.3f} | {s['p90']:.3f} | {s['max']:.3f} | "
                         f"{100 * succ:.0f}% ({thr.replace('success@', '<')}°) |")
    text = "\n".join(lines)
    print(text)
    (out / "gyroscope_errors.md").write_text(text + "\n")
    (out / "gyroscope_errors.json").write_text(json.dumps(results, indent=2))
    print(f"histograms: {out / 'gyroscope_errors.png'}")
    return results


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("mode", choices=["speed", "accuracy"])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--warmup", type=int, default=2, help="speed: untimed runs of every job first")
    ap.add_argument("--n", type=int, default=40, help="samples per accuracy experiment")
    ap.add_argument("--out", default="benchmarks/results/gyroscope")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    speed(args) if args.mode == "speed" else accuracy(args)


if __name__ == "__main__":
    main()
