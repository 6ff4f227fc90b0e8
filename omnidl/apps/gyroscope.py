"""Command line: stabilise a folder of equirectangular frames against a reference frame.

    python -m omnidl.apps.gyroscope FRAMES_DIR --out OUT_DIR [--reference e_000010.png | 10]
        [--checkpoint holinet.pt | --assume-upright] [--height 128] [--no-mpp] [--no-pvg] [--video]

Frames are the image files of ``FRAMES_DIR`` sorted by the number in names like ``e_000123.png`` (else by
name). Writes ``OUT_DIR/rotations.json`` and ``rotations.csv`` (per-frame status, roll/pitch/yaw in
degrees, ``R_ref_cur``), ``stabilised/<name>.png``, ``before_after/<name>.png`` (input above, stabilised
below), ``angles.png`` and, with ``--video``, ``before_after.mp4`` (OpenCV, no ffmpeg needed; skipped
with a message if no codec is available). Unreadable, black or wrongly sized frames are recorded as
``no_estimate`` and the run continues.

The gyroscope itself is :mod:`omnidl.postprocess.gyroscope`; this application adds reading the frames
(:func:`omnidl.data.horizon.read_rgb`), loading a HoLiNet checkpoint of the engine and writing the results.
"""
from __future__ import annotations

import argparse
import csv
import io
import logging
import os
import re
import sys
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from omnidl.data.horizon import read_rgb
from omnidl.postprocess.gyroscope.pipeline import FrameEstimate, GyroscopeOptions, model_horizon_fn, stabilise
from omnidl.utils.io import atomic_imwrite, atomic_write_bytes, atomic_write_json, atomic_write_text

log = logging.getLogger("omnidl.gyroscope")
EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")


def list_frames(folder: str | Path) -> list[Path]:
    """Image files of ``folder``: sorted by the integer of ``e_XXXXXX`` names when all have one, else by name."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"frames folder {folder} does not exist")
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in EXTENSIONS]
    if not files:
        raise FileNotFoundError(f"frames folder {folder} holds no images ({', '.join(EXTENSIONS)})")
    nums = [re.search(r"(\d+)$", p.stem) for p in files]
    if all(nums):
        return [p for _, p in sorted(zip((int(m.group(1)) for m in nums), files), key=lambda t: (t[0], t[1].name))]
    return sorted(files, key=lambda p: p.name)


def _read(path: Path) -> torch.Tensor | None:
    try:
        return read_rgb(path)
    except Exception as e:  # noqa: BLE001 - an unreadable frame is flagged, not fatal
        log.warning("%s", e)
        return None


def load_holinet(checkpoint: str | Path, device: str = "cpu") -> tuple[torch.nn.Module, int]:
    """A HoLiNet from a training checkpoint (``omnidl.engine`` format: ``model`` state + ``config``).

    Returns the model (eval mode) and its training input height (``data.height``, default 128).
    """
    from omegaconf import OmegaConf

    from omnidl.engine.checkpoint import load_checkpoint, load_model_weights, model_config
    from omnidl.models import create_model
    ckpt = load_checkpoint(checkpoint, map_location=device)
    name, mcfg, conf = model_config(ckpt, f"checkpoint {checkpoint}",
                                    "it must come from `python train.py model=holinet...`", default_name="holinet")
    if name != "holinet":
        raise ValueError(f"checkpoint {checkpoint} holds a {name!r} model (config model.name); the gyroscope's "
                         "--checkpoint needs a HoLiNet (python train.py model=holinet or holinet_small), which "
                         "predicts the horizon and vanishing points. Without one, run with --assume-upright")
    model = create_model(name, **mcfg)
    load_model_weights(model, ckpt, checkpoint)
    height = int(OmegaConf.select(conf, "data.height", default=128) or 128)
    return model.to(device).eval(), height


def _to_bgr8(img: torch.Tensor) -> np.ndarray:
    arr = (img.clamp(0, 1).permute(1, 2, 0).cpu().numpy() * 255 + 0.5).astype(np.uint8)
    return np.ascontiguousarray(arr[..., ::-1])


def plot_angles(records: Sequence[FrameEstimate], path: Path) -> None:
    """Roll / pitch / yaw (degrees) per frame index -> PNG (frames without estimate are gaps)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    idx = [r.index for r in records]
    fig, ax = plt.subplots(figsize=(8, 3.5))
    for key in ("roll", "pitch", "yaw"):
        ax.plot(idx, [getattr(r, key) for r in records], marker=".", label=key)
    bad = [r.index for r in records if r.status != "ok"]
    if bad:
        ax.plot(bad, [0] * len(bad), "rx", label="no estimate")
    ax.set_xlabel("frame")
    ax.set_ylabel("degrees")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m omnidl.apps.gyroscope", description=__doc__.split("\n\n")[0])
    ap.add_argument("frames", help="folder of equirectangular frames (e_XXXXXX.png or any sorted names)")
    ap.add_argument("--out", required=True, help="output folder")
    ap.add_argument("--reference", default="0", help="reference frame: file name or index in the sorted list (0)")
    ap.add_argument("--checkpoint", help="HoLiNet checkpoint (from train.py model=holinet...) for roll/pitch")
    ap.add_argument("--assume-upright", action="store_true",
                    help="no HoLiNet: treat every frame as upright and let MPP + PVG find the rotation")
    ap.add_argument("--height", type=int, default=128, help="working height of the photometric steps (128)")
    ap.add_argument("--batch-size", type=int, default=4)
    ap.add_argument("--no-mpp", action="store_true")
    ap.add_argument("--no-pvg", action="store_true")
    ap.add_argument("--lambda-g", type=float, default=0.325)
    ap.add_argument("--mpp-level", type=int, default=3)
    ap.add_argument("--pvg-level", type=int, default=5)
    ap.add_argument("--coherence", choices=["thesis", "reference", "none"], default="thesis")
    ap.add_argument("--limit", type=int, default=0, help="process only the first N frames (0: all)")
    ap.add_argument("--video", action="store_true", help="also write before_after.mp4 with OpenCV")
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    for flag, value, low in (("--height", args.height, 8), ("--batch-size", args.batch_size, 1),
                             ("--limit", args.limit, 0), ("--mpp-level", args.mpp_level, 0),
                             ("--pvg-level", args.pvg_level, 0)):
        if value < low:
            print(f"error: {flag} must be >= {low}, got {value}", file=sys.stderr)
            return 2
    if not (args.lambda_g >= 0 and np.isfinite(args.lambda_g)):
        print(f"error: --lambda-g must be a finite number >= 0, got {args.lambda_g}", file=sys.stderr)
        return 2
    try:
        files = list_frames(args.frames)
    except FileNotFoundError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.limit > 0:
        files = files[: args.limit]
    names = [p.name for p in files]
    ref_path = None
    if args.reference.isdigit() and int(args.reference) < len(files):
        ref_path = files[int(args.reference)]
    elif args.reference in names:
        ref_path = files[names.index(args.reference)]
    else:
        cand = Path(args.reference)
        ref_path = cand if cand.is_file() else None
    if ref_path is None:
        print(f"error: reference {args.reference!r} is neither an index < {len(files)}, a frame name in "
              f"{args.frames}, nor an image file", file=sys.stderr)
        return 2
    reference = _read(ref_path)
    if reference is None:
        print(f"error: could not read the reference image {ref_path}", file=sys.stderr)
        return 2
    if args.checkpoint and args.assume_upright:
        print("error: give either --checkpoint or --assume-upright, not both", file=sys.stderr)
        return 2
    if args.checkpoint:
        try:
            model, mh = load_holinet(args.checkpoint, args.device)
        except (ValueError, RuntimeError, FileNotFoundError) as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        horizon_fn = model_horizon_fn(model, mh)
    elif args.assume_upright:
        horizon_fn = None
    else:
        print("error: give --checkpoint (a trained HoLiNet for roll/pitch) or --assume-upright", file=sys.stderr)
        return 2
    opts = GyroscopeOptions(work_height=args.height, use_mpp=not args.no_mpp, use_pvg=not args.no_pvg,
                            lambda_g=args.lambda_g, mpp_level=args.mpp_level, pvg_level=args.pvg_level,
                            horizon={"coherence": args.coherence})
    out = Path(args.out)
    (out / "stabilised").mkdir(parents=True, exist_ok=True)
    (out / "before_after").mkdir(parents=True, exist_ok=True)
    video = {"writer": None, "tmp": None}

    def on_frame(rec: FrameEstimate, frame: torch.Tensor, stab: torch.Tensor | None) -> None:
        stem = Path(rec.name).stem
        top = _to_bgr8(frame)
        if stab is not None:
            bottom = _to_bgr8(stab)
            atomic_imwrite(out / "stabilised" / f"{stem}.png", bottom)
        else:
            bottom = np.zeros_like(top)
            bottom[..., 2] = 128  # dark red: no estimate
        if bottom.shape != top.shape:
            return
        both = np.concatenate([top, bottom], 0)
        atomic_imwrite(out / "before_after" / f"{stem}.png", both)
        if args.video:
            import cv2
            if video["writer"] is None and video["tmp"] is None:
                tmp = out / ".before_after.mp4.tmp.mp4"
                w = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (both.shape[1], both.shape[0]))
                if w.isOpened():
                    video["writer"], video["tmp"] = w, tmp
                else:
                    video["tmp"] = False
                    log.warning("OpenCV cannot write mp4 here; the PNG sequence in before_after/ is the video")
            if video["writer"] is not None:
                video["writer"].write(both)

    frames = (_read(p) for p in files)
    try:
        records = stabilise(frames, reference, horizon_fn=horizon_fn, options=opts, names=names,
                            batch_size=args.batch_size, on_frame=on_frame, progress=True)
    except ValueError as e:  # the reference frame cannot be used (black/flat, not an equirectangular panorama)
        print(f"error: reference frame {ref_path}: {e}", file=sys.stderr)
        return 2
    if video["writer"] is not None:
        import cv2
        video["writer"].release()
        cap = cv2.VideoCapture(str(video["tmp"]))
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) if cap.isOpened() else 0
        cap.release()
        if n > 0:
            os.replace(video["tmp"], out / "before_after.mp4")
        else:
            os.unlink(video["tmp"])
            log.warning("OpenCV could not encode the video; the PNG sequence in before_after/ is the result")
    atomic_write_json(out / "rotations.json", {"reference": ref_path.name, "convention":
                      "rotation = R_ref_cur (current camera -> reference frame); angles in degrees, "
                      "R = R_y(yaw) R_x(pitch) R_z(roll)", "frames": [r.as_dict() for r in records]})
    buf = io.StringIO()
    wr = csv.writer(buf)
    wr.writerow(["index", "name", "status", "reason", "roll_deg", "pitch_deg", "yaw_deg", "horizon_valid",
                 "mpp_cost", "pvg_cost"])
    for r in records:
        wr.writerow([r.index, r.name, r.status, r.reason, f"{r.roll:.4f}", f"{r.pitch:.4f}", f"{r.yaw:.4f}",
                     int(r.horizon_valid), f"{r.mpp_cost:.6g}", f"{r.pvg_cost:.6g}"])
    atomic_write_text(out / "rotations.csv", buf.getvalue())
    plot_angles(records, out / "angles.png")
    ok = sum(r.status == "ok" for r in records)
    for r in records:
        if r.status != "ok":
            log.warning("frame %s: no estimate (%s)", r.name, r.reason)
    print(f"{ok}/{len(records)} frames stabilised; results in {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
