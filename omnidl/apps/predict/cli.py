"""Argument parsing and the loop over INPUT of ``omnidl predict`` (see :mod:`omnidl.apps.predict`)."""
from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

COMMANDS = ("depth", "layout", "upright", "stabilise")


def build_parser(prog: str = "omnidl predict") -> argparse.ArgumentParser:
    from . import __doc__ as doc
    ap = argparse.ArgumentParser(prog=prog, description=(doc or "").split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("command", choices=COMMANDS, help="what to predict")
    ap.add_argument("input", help="an image, a folder of images or a video")
    ap.add_argument("--checkpoint", help="best.pt/last.pt of train.py, converted FreDSNet weights, an official "
                    "HorizonNet .pth (depth, layout); a HoLiNet checkpoint for stabilise (optional)")
    ap.add_argument("--out", required=True, help="output folder")
    ap.add_argument("--upright", choices=["auto", "off"], default="auto",
                    help="depth/layout: level non-upright panoramas first (auto) or take them as upright (off)")
    ap.add_argument("--world", choices=["manhattan", "atlanta"], default="manhattan", help="layout: room model")
    ap.add_argument("--camera-height", type=float, default=1.6,
                    help="layout, central cameras: camera height above the floor in metres (fixes the scale)")
    ap.add_argument("--no-ply", action="store_true", help="depth: skip the point clouds")
    ap.add_argument("--reference", type=int, default=0, help="stabilise: index of the reference frame")
    ap.add_argument("--no-video", action="store_true", help="stabilise: skip before_after.mp4")
    ap.add_argument("--fps", type=float, default=None, help="stabilise: video frame rate (default: the input's)")
    ap.add_argument("--limit", type=int, default=0, help="only the first N images/frames (0: all)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--compile", action="store_true",
                    help="depth/layout: compile the network with torch.compile (Inductor, freezing) before the "
                         "first image; pays off over many images (the compile time is printed)")
    return ap


def main(argv: Sequence[str] | None = None, prog: str = "omnidl predict") -> int:
    args = build_parser(prog).parse_args(argv)
    from .inputs import iter_inputs, kind_of, video_fps
    out = Path(args.out)
    try:
        kind_of(args.input)
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.command in ("depth", "layout") and not args.checkpoint:
        print(f"error: omnidl predict {args.command} needs --checkpoint CKPT (a train.py checkpoint or converted "
              "official weights, see docs/model_zoo.md)", file=sys.stderr)
        return 2
    if args.compile and args.command not in ("depth", "layout"):
        print(f"note: --compile applies to depth and layout; {args.command} runs uncompiled", file=sys.stderr)
    if args.command == "stabilise":
        from .stabilise import run_stabilise
        from .video import INSTALL_HINT, backend
        if not args.no_video and backend() is None:
            print(f"error: {INSTALL_HINT}; or pass --no-video", file=sys.stderr)
            return 2
        frames = list(iter_inputs(args.input, args.limit))
        files = run_stabilise(frames, out, reference=args.reference, holinet=args.checkpoint,
                              video=not args.no_video, fps=args.fps or video_fps(args.input),
                              device=args.device)
        print(f"stabilise: {len(frames)} frames; {len(files)} files in {out}")
        return 0
    from .run import UprightPolicy, predict_depth, predict_layout, predict_upright
    pred = None
    if args.command in ("depth", "layout"):
        from .loader import load_predictor
        try:
            pred = load_predictor(args.checkpoint, args.device, compile=args.compile)
        except (FileNotFoundError, ValueError, RuntimeError) as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        print(f"{pred.name} from {args.checkpoint} ({pred.source}); network input {pred.width}x{pred.height}")
        if pred.info.get("compiled"):
            print(f"compiled the model in {pred.info['compile_s']:.1f} s (torch.compile, Inductor with freezing: "
                  f"the first forward pass at {pred.width}x{pred.height} took {pred.info['first_call_s']:.1f} s, "
                  f"the next {pred.info['call_s']:.3f} s)")
    policy = UprightPolicy(mode=args.upright)
    out.mkdir(parents=True, exist_ok=True)
    n_ok = n_bad = 0
    for name, image in iter_inputs(args.input, args.limit):
        t0 = time.perf_counter()
        if image is None:                   # iter_inputs warned with the file name
            n_bad += 1
            continue
        try:
            if args.command == "depth":
                files = predict_depth(pred, name, image, out, policy, ply=not args.no_ply)
            elif args.command == "layout":
                files = predict_layout(pred, name, image, out, policy, args.world, args.camera_height)
            else:
                files = predict_upright(name, image, out)
        except ValueError as e:
            print(f"error: {name}: {e}", file=sys.stderr)
            if args.command in ("depth", "layout") and "has no" in str(e):
                return 2
            n_bad += 1
            continue
        n_ok += 1
        print(f"{name} ({image.shape[-1]}x{image.shape[-2]}): {len(files)} files, {time.perf_counter() - t0:.1f} s")
    print(f"predict {args.command}: {n_ok} done, {n_bad} skipped; results in {out}")
    return 0 if n_ok > 0 else 1
