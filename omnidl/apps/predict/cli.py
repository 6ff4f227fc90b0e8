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
    ap.add_argument("--model", choices=["depth_anything_v2"], default=None,
                    help="depth: zero-shot depth from a perspective foundation model run on views cut through "
                         "--camera (omnidl.apps.zero_shot; needs --weights, not --checkpoint; docs/foundation.md)")
    ap.add_argument("--weights", default=None, metavar="FILE|DIR",
                    help="with --model: the published checkpoint (e.g. depth_anything_v2_vits.pth) or its folder")
    ap.add_argument("--out", required=True, help="output folder")
    ap.add_argument("--upright", choices=["auto", "off"], default="auto",
                    help="depth/layout: level non-upright panoramas first (auto) or take them as upright (off)")
    ap.add_argument("--world", choices=["manhattan", "atlanta"], default="manhattan", help="layout: room model")
    ap.add_argument("--camera-height", type=float, default=1.6,
                    help="layout, central cameras: camera height above the floor in metres (fixes the scale)")
    ap.add_argument("--camera", default=None, metavar="FILE|PRESET",
                    help="the input's own camera: a calibration file (omnidl YAML, COLMAP, Kalibr, OpenCV, ORB-SLAM3, "
                         "OCamCalib, KB text, WoodScape JSON) or a preset (e.g. kb_f195). The image is re-projected "
                         "into the model's camera and the outputs come back to its pixels. Default: a sidecar "
                         "<stem>.camera.yaml/.json next to the input, else the model's own camera")
    ap.add_argument("--overwrite", action="store_true",
                    help="replace the outputs of a previous run in --out (an input file is never replaced)")
    ap.add_argument("--no-ply", action="store_true", help="depth: skip the point clouds")
    ap.add_argument("--mesh", action="append", choices=["glb", "obj"], default=None,
                    help="layout: also write the room as a mesh textured with the image, <name>_room.glb (glTF "
                         "binary) or <name>_room.obj + .mtl + texture PNG; repeat for both")
    ap.add_argument("--max-points", type=int, default=0, metavar="N",
                    help="depth: write at most N points per cloud (an even stride; after --voxel). 0: every "
                         "valid pixel (default)")
    ap.add_argument("--voxel", type=float, default=0.0, metavar="SIZE",
                    help="depth: one point (the mean) per SIZE-metre voxel in the written clouds. 0: off (default)")
    ap.add_argument("--reference", type=int, default=0, help="stabilise: index of the reference frame")
    ap.add_argument("--no-video", action="store_true", help="stabilise: skip before_after.mp4")
    ap.add_argument("--fps", type=float, default=None, help="stabilise: video frame rate (default: the input's)")
    ap.add_argument("--limit", type=int, default=0, help="only the first N images/frames (0: all)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--compile", action="store_true",
                    help="depth/layout: compile the network with torch.compile (Inductor, freezing) before the "
                         "first image; pays off over many images (the compile time is printed)")
    return ap


def _camera_spec(args, source: Path | None):
    """``(spec, what)`` of an item's camera: ``--camera``, else its sidecar file, else ``(None, None)``."""
    from .camera import sidecar_camera
    if args.camera:
        return args.camera, "--camera"
    side = sidecar_camera(source)
    return (side, "sidecar camera file") if side is not None else (None, None)


def _planned_outputs(args, out: Path, pred, items) -> list[Path]:
    from .run import depth_outputs, layout_outputs, upright_outputs
    files: list[Path] = []
    for name, src in items:
        if args.command == "depth":
            spec, _ = _camera_spec(args, src)
            files += depth_outputs(out, name, "semantic" in pred.outputs, not args.no_ply, spec is not None)
        elif args.command == "layout":
            files += layout_outputs(out, name, args.mesh or ())
        else:
            files += upright_outputs(out, name)
    return files


def main(argv: Sequence[str] | None = None, prog: str = "omnidl predict") -> int:
    args = build_parser(prog).parse_args(argv)
    if args.model:
        return _zero_shot(args)
    from omnidl.utils.outputs import OutputClaims, OutputExistsError, RunLock, RunLockedError

    from .inputs import kind_of
    from .points import CloudOptions
    out = Path(args.out)
    try:
        kind_of(args.input)
        cloud = CloudOptions(max_points=args.max_points, voxel=args.voxel)
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.command in ("depth", "layout") and not args.checkpoint:
        print(f"error: omnidl predict {args.command} needs --checkpoint CKPT (a train.py checkpoint or converted "
              "official weights, see docs/model_zoo.md)", file=sys.stderr)
        return 2
    if args.compile and args.command not in ("depth", "layout"):
        print(f"note: --compile applies to depth and layout; {args.command} runs uncompiled", file=sys.stderr)
    try:
        with RunLock(out, what=f"omnidl predict {args.command}"):
            return _run(args, out, cloud, OutputClaims([args.input], overwrite=args.overwrite))
    except (RunLockedError, OutputExistsError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


def _zero_shot(args) -> int:
    """``omnidl predict depth INPUT --camera CALIB --model depth_anything_v2 --weights W --out DIR``: the view
    chain of :mod:`omnidl.apps.zero_shot` (one image; the camera is required, the options that drive a trained
    checkpoint do not apply)."""
    problems = [f"--model needs {need}" for need, ok in (("the depth command", args.command == "depth"),
                                                         ("--weights FILE|DIR", args.weights),
                                                         ("--camera FILE|PRESET", args.camera)) if not ok]
    problems += [f"--model does not take {opt}" for opt, given in (("--checkpoint", args.checkpoint),
                                                                    ("--compile", args.compile)) if given]
    if problems:
        print(f"error: {'; '.join(problems)}", file=sys.stderr)
        return 2
    from omnidl.apps.zero_shot import main as zero_shot_main
    argv = [args.input, "--camera", args.camera, "--model", args.model, "--weights", args.weights,
            "--out", args.out, "--device", args.device] + (["--overwrite"] if args.overwrite else [])
    return zero_shot_main(argv)


def _run(args, out: Path, cloud, claims) -> int:
    from omnidl.utils.outputs import OutputExistsError, guard_outputs

    from .inputs import iter_items, planned_items, video_fps
    if args.command == "stabilise":
        from .camera import input_camera
        from .run import _full_equirect
        from .stabilise import run_stabilise
        from .video import INSTALL_HINT, backend
        if not args.no_video and backend() is None:
            print(f"error: {INSTALL_HINT}; or pass --no-video", file=sys.stderr)
            return 2
        items = list(iter_items(args.input, args.limit))
        frames = [(n, im) for n, im, _ in items]
        first = next(((im, src) for _, im, src in items if im is not None), None)
        if first is not None:
            spec, what = _camera_spec(args, first[1])
            if spec is not None:
                try:
                    cam = input_camera(spec, first[0].shape[-1], first[0].shape[-2], what)
                except ValueError as e:
                    print(f"error: {e}", file=sys.stderr)
                    return 2
                if not _full_equirect(cam):
                    print(f"error: {what} {str(spec)!r}: predict stabilise works on full equirectangular panoramas "
                          f"(W = 2 H); this camera is {type(getattr(cam, 'base', cam)).__name__}", file=sys.stderr)
                    return 2
        fixed = [out / n for n in ("rotations.json", "rotations.csv", "angles.png")]
        fixed += [out / "before_after.mp4"] if not args.no_video else []
        try:
            guard_outputs(fixed + [out / d / f"{n}.png" for n, _ in frames for d in ("stabilised", "before_after")],
                          [args.input], overwrite=args.overwrite)
        except (OutputExistsError, ValueError) as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        files = run_stabilise(frames, out, reference=args.reference, holinet=args.checkpoint,
                              video=not args.no_video, fps=args.fps or video_fps(args.input),
                              device=args.device)
        print(f"stabilise: {len(frames)} frames; {len(files)} files in {out}")
        return 0
    from .camera import input_camera
    from .run import UprightPolicy, _full_equirect, predict_depth, predict_layout, predict_upright
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
    planned = planned_items(args.input, args.limit)
    if planned is not None:                      # refuse before any work (a video is checked frame by frame)
        try:
            guard_outputs(_planned_outputs(args, out, pred, planned), [args.input], overwrite=args.overwrite)
        except (OutputExistsError, ValueError) as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
    policy = UprightPolicy(mode=args.upright)
    out.mkdir(parents=True, exist_ok=True)
    n_ok = n_bad = 0
    cameras: dict = {}
    for name, image, source in iter_items(args.input, args.limit):
        t0 = time.perf_counter()
        if image is None:                   # iter_items warned with the file name
            n_bad += 1
            continue
        H, W = int(image.shape[-2]), int(image.shape[-1])
        try:
            spec, what = _camera_spec(args, source)
            cam = None
            if spec is not None:
                key = (str(spec), W, H)
                if key not in cameras:
                    cameras[key] = input_camera(spec, W, H, what)
                    if what != "--camera":
                        print(f"{name}: camera from {what} {spec}")
                cam = cameras[key]
            if args.command == "depth":
                files = predict_depth(pred, name, image, out, policy, ply=not args.no_ply, camera=cam,
                                      claims=claims, cloud=cloud)
            elif args.command == "layout":
                files = predict_layout(pred, name, image, out, policy, args.world, args.camera_height, camera=cam,
                                       claims=claims, mesh=args.mesh or ())
            else:
                if cam is not None and not _full_equirect(cam):
                    raise ValueError(f"{what} {str(spec)!r}: predict upright needs a full equirectangular panorama "
                                     f"(W = 2 H); this camera is {type(getattr(cam, 'base', cam)).__name__}")
                files = predict_upright(name, image, out, claims=claims)
        except OutputExistsError as e:
            print(f"error: {name}: {e}", file=sys.stderr)
            return 2
        except ValueError as e:
            print(f"error: {name}: {e}", file=sys.stderr)
            if args.command in ("depth", "layout") and "has no" in str(e):
                return 2
            n_bad += 1
            continue
        n_ok += 1
        msg = f"{name} ({W}x{H}): {len(files)} files, {time.perf_counter() - t0:.1f} s"
        cov = _coverage_line(out, name, args.command)
        print(msg + (f"; {cov}" if cov else ""))
    print(f"predict {args.command}: {n_ok} done, {n_bad} skipped; results in {out}")
    return 0 if n_ok > 0 else 1


def _coverage_line(out: Path, name: str, command: str) -> str | None:
    """The coverage sentence of an item run through its camera (read back from its JSON)."""
    import json
    f = out / (f"{name}_predict.json" if command == "depth" else f"{name}_layout.json")
    if command not in ("depth", "layout") or not f.is_file():
        return None
    cam = json.loads(f.read_text()).get("camera")
    if not cam:
        return None
    from .camera import Coverage
    c = cam["coverage"]
    return Coverage(c["input_valid_pixels"], c["input_covered_pixels"], c["model_valid_pixels"],
                    c["model_seen_pixels"]).line()
