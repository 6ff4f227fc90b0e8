"""The cross-camera study: train a depth network on one camera, evaluate it on cameras it never saw.

``python -m omnidl.apps.cross_camera [--steps N] [--train N] [--test N] [--device cuda] [--scale K]`` prints, for
each method, AbsRel and delta1 on rooms of omnidl's synthetic engine (:mod:`omnidl.synth`, exact range ground truth)
seen through an equirectangular panorama (the training camera), a 195° Kannala-Brandt fisheye, a Mei (unified)
catadioptric camera and a non-central panorama:

* ``standard``: a U-Net with standard 3x3 convolutions trained on the panoramas, run on each camera's image as it
  is;
* ``projected``: the same U-Net with :class:`omnidl.nn.ProjectedConv2d` layers, trained on the panoramas with the
  equirectangular camera and re-calibrated for each test camera (same weights, ``UNet.calibrate``);
* ``views``: the standard U-Net trained on perspective views (cube faces, 110°) of the training rooms, run on every
  test camera through the view chain (:func:`omnidl.geometry.views.depth_through_views`: views cut through the
  camera, per-view scales aligned on overlaps, fused back on the camera's pixels, non-central through its rays).

Every network predicts metric range (views: z-depth); depth maps are compared with the ground-truth range along each
pixel's ray on pixels valid in both. The default is CPU size (32 x 64 panoramas, a U-Net of 8 base channels, a few
minutes on 2 cores); ``--scale 4`` (128 x 256, more rooms and steps) is the GPU setting. Results vary with the seed
at CPU size; the table prints the settings it ran.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from omnidl.cameras import Camera, Equirectangular, KannalaBrandt, NonCentralPanorama, Unified
from omnidl.geometry.views import depth_through_views, view_layout
from omnidl.models.unet import UNet


def cameras(scale: int = 1) -> dict[str, Camera]:
    """The training camera (``equirect``) and the test cameras at ``scale`` x the CPU size."""
    s = int(scale)
    return {
        "equirect": Equirectangular(width=64 * s, height=32 * s),
        "kb195": KannalaBrandt(width=64 * s, height=64 * s, fx=17.0 * s, fy=17.5 * s, cx=32.0 * s, cy=31.5 * s,
                               k0=1.0, k1=-0.01, k2=0.002, k3=-1e-4, k4=1e-6, max_fov=math.radians(195)),
        "mei": Unified(width=64 * s, height=48 * s, xi=0.9, fx=22.0 * s, fy=21.0 * s, s=0.0, cx=32.0 * s,
                       cy=24.0 * s, k1=-0.02, k2=0.002, p1=0.0, p2=0.0),
        "noncentral": NonCentralPanorama(width=64 * s, height=32 * s, rc=0.3),
    }


def _room(camera: Camera, seed: int, split: str, index: int):
    from omnidl.synth import place_camera, sample_room, sample_seeds
    for attempt in range(20):
        room_seed, cam_seed = sample_seeds(seed, split, index, attempt)
        scene = sample_room(room_seed)
        try:
            return scene, place_camera(scene, camera, cam_seed)
        except (RuntimeError, ValueError):
            continue
    raise RuntimeError(f"no room fits {type(camera).__name__} for {split}/{index}")


def render_set(camera: Camera, n: int, split: str, seed: int) -> list[tuple[Tensor, Tensor, Tensor]]:
    """``n`` samples ``(image (3, H, W), range (1, H, W), valid (1, H, W))``."""
    from omnidl.synth import render
    out = []
    for i in range(n):
        scene, pose = _room(camera, seed, split, i)
        r = render(scene, camera, pose, layout=False)
        out.append((r["image"], r["depth"], r["valid"][None] & (r["depth"] > 0)))
    return out


def render_views(camera: Camera, n: int, split: str, seed: int, size: int) -> list[tuple[Tensor, Tensor, Tensor]]:
    """Perspective training views (cube faces, 110°) of the rooms of :func:`render_set`: z-depth targets."""
    from omnidl.synth import render
    out = []
    for i in range(n):
        scene, pose = _room(camera, seed, split, i)
        for v in view_layout("cube", size=size):
            pv = pose.copy()
            pv[:3, :3] = pose[:3, :3] @ v.rotation.numpy()
            r = render(scene, v.camera, pv, layout=False)
            z = r["depth"] * v.camera.unproject_grid().direction[..., 2][None]
            out.append((r["image"], z, r["valid"][None] & (z > 0)))
    return out


def train(model: torch.nn.Module, data: list, steps: int, batch: int, device: str, seed: int,
          lr: float = 3e-3) -> torch.nn.Module:
    """L1 on log depth over valid pixels, Adam."""
    torch.manual_seed(seed)
    model.to(device).train()
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    imgs = torch.stack([d[0] for d in data]).to(device)
    tgts = torch.stack([d[1] for d in data]).to(device)
    masks = torch.stack([d[2] for d in data]).to(device)
    g = torch.Generator().manual_seed(seed)
    for step in range(steps):
        idx = torch.randint(0, len(data), (batch,), generator=g)
        pred = model(imgs[idx])["depth"]
        m = masks[idx]
        loss = (pred.clamp_min(1e-3).log() - tgts[idx].clamp_min(1e-3).log()).abs()[m].mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        for group in opt.param_groups:
            group["lr"] = lr * 0.5 * (1 + math.cos(math.pi * (step + 1) / steps))
    return model.eval()


def depth_metrics(pred: Tensor, gt: Tensor, valid: Tensor) -> tuple[float, float]:
    """``(AbsRel, delta1)`` over ``valid & pred > 0``."""
    ok = valid & (pred > 0) & (gt > 0)
    p, g = pred[ok], gt[ok]
    if p.numel() == 0:
        return math.nan, math.nan
    absrel = float(((p - g).abs() / g).mean())
    d1 = float((torch.maximum(p / g, g / p) < 1.25).float().mean())
    return absrel, d1


def _evaluate(fn, data: list) -> tuple[float, float]:
    rows = [depth_metrics(fn(img), gt, valid) for img, gt, valid in data]
    return float(np.nanmean([r[0] for r in rows])), float(np.nanmean([r[1] for r in rows]))


def run(steps: int = 200, n_train: int = 24, n_test: int = 6, scale: int = 1, device: str = "cpu", seed: int = 0,
        base_channels: int = 8, batch: int = 8, log=print) -> dict[str, dict[str, tuple[float, float]]]:
    """Train the three methods and evaluate them on every camera: ``{method: {camera: (AbsRel, delta1)}}``."""
    cams = cameras(scale)
    train_cam = cams["equirect"]
    t0 = time.time()
    train_set = render_set(train_cam, n_train, "train", seed)
    view_size = 32 * scale
    train_views = render_views(train_cam, n_train, "train", seed, view_size)
    tests = {name: render_set(cam, n_test, "test", seed) for name, cam in cams.items()}
    log(f"rendered {n_train} training rooms ({len(train_views)} views) and {n_test} test rooms per camera "
        f"in {time.time() - t0:.0f} s")

    def unet(conv: str = "standard", camera: Camera | None = None) -> UNet:
        torch.manual_seed(seed)
        return UNet(tasks=("depth",), base_channels=base_channels, levels=3, conv=conv, camera=camera)

    results: dict[str, dict[str, tuple[float, float]]] = {}
    t = time.time()
    std = train(unet(), train_set, steps, batch, device, seed)
    log(f"standard: trained in {time.time() - t:.0f} s")
    t = time.time()
    proj = train(unet("projected", train_cam), train_set, steps, batch, device, seed)
    log(f"projected: trained in {time.time() - t:.0f} s")
    t = time.time()
    view_net = train(unet(), train_views, steps, batch, device, seed)
    log(f"views: trained in {time.time() - t:.0f} s")

    def direct(net):
        def fn(img):
            with torch.no_grad():
                return net(img[None].to(device))["depth"][0].cpu()
        return fn

    results["standard"] = {name: _evaluate(direct(std), data) for name, data in tests.items()}
    results["projected"] = {}
    for name, data in tests.items():
        try:
            proj.calibrate(cams[name])
            results["projected"][name] = _evaluate(direct(proj), data)
        except (ValueError, NotImplementedError, RuntimeError) as e:
            log(f"projected on {name}: {e}")
            results["projected"][name] = (math.nan, math.nan)

    def through_views(camera):
        def predict(images, _views):
            with torch.no_grad():
                return view_net(images.to(device))["depth"].cpu()

        def fn(img):
            return depth_through_views(img, camera, predict, layout="cube", size=view_size, kind="depth",
                                       align="scale", batch=16).depth
        return fn

    results["views"] = {name: _evaluate(through_views(cams[name]), data) for name, data in tests.items()}
    return results


def format_table(results: dict[str, dict[str, tuple[float, float]]]) -> str:
    names = list(next(iter(results.values())))
    head = "| method | " + " | ".join(f"{n} AbsRel / δ1" for n in names) + " |"
    lines = [head, "|" + "---|" * (len(names) + 1)]
    for method, row in results.items():
        lines.append(f"| {method} | " + " | ".join(f"{row[n][0]:.3f} / {row[n][1]:.3f}" for n in names) + " |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m omnidl.apps.cross_camera", description=__doc__.split("\n\n")[0])
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--train", type=int, default=24, help="training rooms")
    p.add_argument("--test", type=int, default=6, help="test rooms per camera")
    p.add_argument("--scale", type=int, default=1, help="image size multiplier (1: CPU size, 32 x 64 panoramas)")
    p.add_argument("--base-channels", type=int, default=8)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--device", default="cpu")
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    for k in ("steps", "train", "test", "scale", "base_channels", "batch"):
        if getattr(a, k) < 1:
            print(f"error: --{k.replace('_', '-')} must be >= 1, got {getattr(a, k)}", file=sys.stderr)
            return 2
    t = time.time()
    res = run(a.steps, a.train, a.test, a.scale, a.device, a.seed, a.base_channels, a.batch)
    print(f"\ntrained on equirect ({32 * a.scale}x{64 * a.scale}), {a.train} rooms, {a.steps} steps, U-Net "
          f"{a.base_channels} base channels; tested on {a.test} unseen rooms per camera; device {a.device}; "
          f"{time.time() - t:.0f} s")
    print(format_table(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
