"""``omnidl predict stabilise``: the gyroscope (:mod:`omnidl.postprocess.gyroscope`) on a folder of frames or
a video, with roll/pitch from a HoLiNet checkpoint or, without one, from the weight-free line-segment
estimator of :mod:`omnidl.geometry.upright`.

Writes into ``out``: ``rotations.json`` / ``rotations.csv`` (per frame: status, roll/pitch/yaw in degrees,
``R_ref_cur``), ``stabilised/<name>.png``, ``before_after/<name>.png`` (input above, stabilised below),
``angles.png`` and ``before_after.mp4`` (H.264, yuv420p: plays in a browser; needs the ``video`` extra).
"""
from __future__ import annotations

import csv
import io
import math
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch

from omnidl.cameras import Equirectangular
from omnidl.geometry.upright import UprightOptions, estimate_upright
from omnidl.utils.io import atomic_imwrite, atomic_write_json, atomic_write_text

from .video import H264Writer


def upright_horizon_fn(options: UprightOptions = UprightOptions(), map_height: int = 128
                       ) -> Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]:
    """A gyroscope ``horizon_fn`` without a network: the up vector of :func:`estimate_upright` drawn as the
    heat maps HoLiNet would give (a sharp horizon great circle and the two vertical vanishing points), which
    :func:`omnidl.geometry.horizon.fit_horizon` turns back into the same up vector. Frames without an
    estimate give empty maps (the gyroscope then marks them as having no horizon)."""
    dirs = Equirectangular(width=2 * map_height, height=map_height).unproject_grid(torch.float64).direction
    sigma = math.pi / map_height                      # one map row

    def fn(images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        hs, vs = [], []
        for img in images:
            est = estimate_upright(img.float().cpu(), options)
            if not est.ok:
                hs.append(torch.zeros(1, map_height, 2 * map_height))
                vs.append(torch.zeros(1, map_height, 2 * map_height))
                continue
            c = (dirs @ est.up).clamp(-1, 1)
            hs.append(torch.exp(-0.5 * (torch.asin(c) / sigma) ** 2)[None].float())
            vs.append(torch.exp(-0.5 * (torch.acos(c.abs()) / sigma) ** 2)[None].float())
        return torch.stack(hs), torch.stack(vs)
    return fn


def _bgr8(img: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray((img.clamp(0, 1).permute(1, 2, 0).cpu().numpy()[..., ::-1] * 255 + 0.5)
                                .astype(np.uint8))


def run_stabilise(frames: Sequence[tuple[str, torch.Tensor | None]], out: Path, reference: int = 0,
                  holinet: str | None = None, video: bool = True, fps: float = 10.0, work_height: int = 128,
                  device: str = "cpu") -> list[Path]:
    """Stabilise ``frames`` (``(name, image or None)``) against frame ``reference``; returns the written files."""
    from omnidl.apps.gyroscope import load_holinet, plot_angles
    from omnidl.postprocess.gyroscope.pipeline import GyroscopeOptions, model_horizon_fn, stabilise
    if not frames:
        raise ValueError("predict stabilise: no frames")
    if not 0 <= reference < len(frames) or frames[reference][1] is None:
        raise ValueError(f"predict stabilise: --reference {reference} is not a readable frame index "
                         f"(0..{len(frames) - 1})")
    if holinet:
        model, mh = load_holinet(holinet, device)
        horizon_fn, source = model_horizon_fn(model, mh), f"HoLiNet {holinet}"
    else:
        horizon_fn, source = upright_horizon_fn(), "line segments (omnidl.geometry.upright, no network)"
    out.mkdir(parents=True, exist_ok=True)
    (out / "stabilised").mkdir(exist_ok=True)
    (out / "before_after").mkdir(exist_ok=True)
    writer = H264Writer(out / "before_after.mp4", fps) if video else None
    ref_img = frames[reference][1]
    files: list[Path] = []

    def on_frame(rec, frame, stab) -> None:
        top = _bgr8(frame)
        bottom = _bgr8(stab) if stab is not None else np.zeros_like(top)
        if stab is not None:
            files.append(atomic_imwrite(out / "stabilised" / f"{Path(rec.name).stem}.png", bottom))
        if bottom.shape != top.shape:
            return
        both = np.concatenate([top, bottom], 0)
        files.append(atomic_imwrite(out / "before_after" / f"{Path(rec.name).stem}.png", both))
        if writer is not None and both.shape[:2] == (2 * ref_img.shape[-2], ref_img.shape[-1]):
            writer.write(both[..., ::-1])

    names = [n for n, _ in frames]
    imgs = (im for _, im in frames)
    opts = GyroscopeOptions(work_height=work_height)
    records = stabilise(imgs, ref_img, horizon_fn=horizon_fn, options=opts, names=names, on_frame=on_frame)
    if writer is not None:
        v = writer.close()
        if v is not None:
            files.append(v)
    files.append(atomic_write_json(out / "rotations.json", {
        "reference": names[reference], "tilt_source": source,
        "convention": "rotation = R_ref_cur (current camera -> reference frame); angles in degrees, "
                      "R = R_y(yaw) R_x(pitch) R_z(roll)", "frames": [r.as_dict() for r in records]}))
    buf = io.StringIO()
    wr = csv.writer(buf)
    wr.writerow(["index", "name", "status", "reason", "roll_deg", "pitch_deg", "yaw_deg", "horizon_valid"])
    for r in records:
        wr.writerow([r.index, r.name, r.status, r.reason, f"{r.roll:.4f}", f"{r.pitch:.4f}", f"{r.yaw:.4f}",
                     int(r.horizon_valid)])
    files.append(atomic_write_text(out / "rotations.csv", buf.getvalue()))
    plot_angles(records, out / "angles.png")
    files.append(out / "angles.png")
    return files
